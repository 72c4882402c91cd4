"""MAT (Wen et al. 2022): agents act one after another in a fixed order (paper eq. mat).

Each agent's ratio r_i = π_i(a_i | O, a_<i) / π_i,old(a_i | O, a_<i) is clipped on its own with
the same team advantage, and the clipped objectives are averaged over agents and samples. The
team value V(O) = mean_i V(ô_i) feeds GAE; as in the reference implementation, each V(ô_i) is
regressed on the team's value target with its own clipped value loss around its collecting-time
value, which acting stores with the transition (`ActResult.extras`).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from cmat.algorithms.base import ActResult, Batch, Params
from cmat.algorithms.distributions import action_distribution
from cmat.algorithms.ppo import clipped_surrogate_loss, value_loss
from cmat.config import NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.networks.mat import MATNetwork, MATOutput


@dataclass(frozen=True)
class MAT:
    network: MATNetwork

    @classmethod
    def build(cls, config: NetworkConfig, spec: EnvSpec) -> "MAT":
        return cls(MATNetwork(config, spec.num_agents, spec.action_dim, spec.discrete))

    @property
    def identity(self) -> jax.Array:
        """The decision order 0..n-1."""
        return jnp.arange(self.network.num_agents)

    def init(self, key: jax.Array, obs: jax.Array, action_mask: jax.Array) -> Params:
        if self.network.discrete:
            actions = jnp.zeros(action_mask.shape[:1], jnp.int32)
        else:
            actions = jnp.zeros(action_mask.shape)
        return self.network.init(key, obs, action_mask, actions, self.identity)

    def encode(self, params: Params, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Ô and the per-agent values V(ô_i)."""
        return self.network.apply(params, obs, method=MATNetwork.encode)

    def decode(
        self,
        params: Params,
        encoded: jax.Array,
        action_mask: jax.Array,
        order: jax.Array,
        key: jax.Array | None,
    ) -> tuple[jax.Array, jax.Array]:
        """Autoregressive actions along `order` and their per-agent log-probs."""
        return self.network.apply(
            params, encoded, action_mask, order, key, method=MATNetwork.decode
        )

    def act(
        self, params: Params, obs: jax.Array, action_mask: jax.Array, key: jax.Array
    ) -> ActResult:
        encoded, agent_values = self.encode(params, obs)
        actions, log_probs = self.decode(params, encoded, action_mask, self.identity, key)
        return ActResult(actions, log_probs, jnp.mean(agent_values), agent_values)

    def greedy(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        encoded, _ = self.encode(params, obs)
        return self.decode(params, encoded, action_mask, self.identity, None)[0]

    def value(self, params: Params, obs: jax.Array) -> jax.Array:
        return self.network.apply(params, obs, method=MATNetwork.value)

    def teacher_forced(self, params: Params, batch: Batch, orders: jax.Array) -> MATOutput:
        """Network outputs for every sample of the batch, decoded along orders [B, n]."""
        return jax.vmap(
            self.network.apply, in_axes=(None, 0, 0, 0, 0), out_axes=MATOutput(0, None, 0, 0)
        )(params, batch.obs, batch.action_mask, batch.actions, orders)

    def loss_along(
        self,
        params: Params,
        batch: Batch,
        orders: jax.Array,
        old_agent_values: jax.Array,
        ppo: PPOConfig,
    ) -> tuple[jax.Array, dict[str, jax.Array], MATOutput]:
        """Eq. mat with the actions decoded along orders [B, n], and every agent's value
        regressed on the team target around its collecting-time value [B, n]; also returns the
        outputs."""
        output = self.teacher_forced(params, batch, orders)
        distribution = action_distribution(
            output.action_params, output.log_std, self.network.discrete
        )
        log_ratio = distribution.log_prob(batch.actions) - batch.log_probs
        advantages = jnp.broadcast_to(batch.advantages[:, None], log_ratio.shape)
        policy_loss, diagnostics = clipped_surrogate_loss(log_ratio, advantages, ppo.clip_eps)
        entropy = jnp.mean(distribution.entropy())
        targets = jnp.broadcast_to(batch.targets[:, None], output.agent_values.shape)
        critic_loss = value_loss(
            output.agent_values, old_agent_values, targets, ppo.clip_eps,
            ppo.huber_loss, ppo.huber_delta, ppo.clipped_value_loss,
        )
        total = policy_loss - ppo.ent_coef * entropy + ppo.value_coef * critic_loss
        metrics = {
            "policy_loss": policy_loss,
            "value_loss": critic_loss,
            "entropy": entropy,
            **diagnostics,
        }
        return total, metrics, output

    def loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """Per-agent clipped surrogates with the team advantage, mean entropy, per-agent value
        losses on the team target."""
        orders = jnp.broadcast_to(self.identity, batch.log_probs.shape)
        total, metrics, _ = self.loss_along(params, batch, orders, batch.extras, ppo)
        return total, metrics
