"""CMAT: the whole team is one multi-action agent trained with single-agent PPO.

The joint ratio is Π_i π_i(a_i | O, μ_θ(O)) / Π_i π_i,old(a_i | O, μ_θ-(O)) (paper eq. ratio):
the deterministic consensus has probability 1, so only the per-agent factors enter, and the
gradient reaches μ_θ through c. The critic is one team value V(O) from e0 (paper eq. cmat).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from cmat.algorithms.base import ActResult, Batch, Params
from cmat.algorithms.distributions import action_distribution, greedy_action
from cmat.algorithms.ppo import clipped_surrogate_loss, joint_log_ratio, value_loss
from cmat.config import NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.networks.cmat import CMATNetwork


@dataclass(frozen=True)
class CMAT:
    network: CMATNetwork

    @classmethod
    def build(cls, config: NetworkConfig, spec: EnvSpec) -> "CMAT":
        return cls(CMATNetwork(config, spec.num_agents, spec.action_dim, spec.discrete))

    def init(self, key: jax.Array, obs: jax.Array, action_mask: jax.Array) -> Params:
        return self.network.init(key, obs, action_mask)

    def act(
        self, params: Params, obs: jax.Array, action_mask: jax.Array, key: jax.Array
    ) -> ActResult:
        output = self.network.apply(params, obs, action_mask)
        distribution = action_distribution(
            output.action_params, output.log_std, self.network.discrete
        )
        actions, log_probs = distribution.sample_and_log_prob(seed=key)
        return ActResult(actions, log_probs, output.value)

    def greedy(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        output = self.network.apply(params, obs, action_mask)
        return greedy_action(output.action_params, self.network.discrete)

    def value(self, params: Params, obs: jax.Array) -> jax.Array:
        return self.network.apply(params, obs, method="value")

    def loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """Clipped surrogate on the joint ratio, mean per-agent entropy, team value loss."""
        output = self.network.apply(params, batch.obs, batch.action_mask)
        distribution = action_distribution(
            output.action_params, output.log_std, self.network.discrete
        )
        log_ratio = joint_log_ratio(distribution.log_prob(batch.actions), batch.log_probs)
        policy_loss, diagnostics = clipped_surrogate_loss(
            log_ratio, batch.advantages, ppo.clip_eps
        )
        entropy = jnp.mean(distribution.entropy())
        critic_loss = value_loss(
            output.value, batch.values, batch.targets, ppo.clip_eps,
            ppo.huber_loss, ppo.huber_delta, ppo.clipped_value_loss,
        )
        total = policy_loss - ppo.ent_coef * entropy + ppo.value_coef * critic_loss
        return total, {
            "policy_loss": policy_loss,
            "value_loss": critic_loss,
            "entropy": entropy,
            **diagnostics,
        }
