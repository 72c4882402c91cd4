"""MAPPO (Yu et al. 2022): one actor shared by all agents, a centralized critic, per-agent PPO.

Agent i acts from [o_i; one-hot(i)] alone (decentralised execution; the id lets the shared actor
tell agents apart). The critic sees the global state, which this protocol does not provide
separately: it is all agents' observations concatenated, so MAPPO trains on the same information
as CMAT. Each agent's ratio r_i = π_i / π_i,old is clipped on its own against the team advantage
and the surrogate is averaged over agents (unlike CMAT's joint ratio, paper eq. ratio).
The feed-forward actor stands in for the reference's optional recurrent one.
"""

from __future__ import annotations

from dataclasses import dataclass

import distrax
import jax
import jax.numpy as jnp

from cmat.algorithms.base import ActResult, Batch, Params
from cmat.algorithms.distributions import action_distribution, greedy_action
from cmat.algorithms.ppo import clipped_surrogate_loss, value_loss
from cmat.config import NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.networks.mlp import MLPActor, MLPCritic


@dataclass(frozen=True)
class MAPPO:
    actor: MLPActor
    critic: MLPCritic
    num_agents: int
    discrete: bool

    @classmethod
    def build(cls, config: NetworkConfig, spec: EnvSpec) -> "MAPPO":
        actor = MLPActor(config.n_embd, spec.action_dim, spec.discrete, config.init_gain)
        return cls(actor, MLPCritic(config.n_embd), spec.num_agents, spec.discrete)

    def actor_inputs(self, obs: jax.Array) -> jax.Array:
        """[o_i; one-hot(i)] for every agent: [..., n, obs_dim + n]."""
        ids = jnp.eye(self.num_agents, dtype=obs.dtype)
        return jnp.concatenate([obs, jnp.broadcast_to(ids, (*obs.shape[:-1], ids.shape[1]))], -1)

    def init(self, key: jax.Array, obs: jax.Array, action_mask: jax.Array) -> Params:
        actor_key, critic_key = jax.random.split(key)
        return {
            "actor": self.actor.init(actor_key, self.actor_inputs(obs), action_mask),
            "critic": self.critic.init(critic_key, obs),
        }

    def policy(
        self, params: Params, obs: jax.Array, action_mask: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """Every agent's action parameters [..., n, A] and log-std."""
        return self.actor.apply(params["actor"], self.actor_inputs(obs), action_mask)

    def distribution(
        self, params: Params, obs: jax.Array, action_mask: jax.Array
    ) -> distrax.Distribution:
        return action_distribution(*self.policy(params, obs, action_mask), self.discrete)

    def act(
        self, params: Params, obs: jax.Array, action_mask: jax.Array, key: jax.Array
    ) -> ActResult:
        distribution = self.distribution(params, obs, action_mask)
        actions, log_probs = distribution.sample_and_log_prob(seed=key)
        return ActResult(actions, log_probs, self.value(params, obs))

    def greedy(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        return greedy_action(self.policy(params, obs, action_mask)[0], self.discrete)

    def value(self, params: Params, obs: jax.Array) -> jax.Array:
        return self.critic.apply(params["critic"], obs)

    def critic_loss(self, params: Params, batch: Batch, ppo: PPOConfig) -> jax.Array:
        return value_loss(
            self.value(params, batch.obs), batch.values, batch.targets, ppo.clip_eps,
            ppo.huber_loss, ppo.huber_delta, ppo.clipped_value_loss,
        )

    def loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """Per-agent clipped surrogate with the team advantage, mean entropy, value loss."""
        distribution = self.distribution(params, batch.obs, batch.action_mask)
        log_ratio = distribution.log_prob(batch.actions) - batch.log_probs
        policy_loss, diagnostics = clipped_surrogate_loss(
            log_ratio, batch.advantages[:, None], ppo.clip_eps
        )
        entropy = jnp.mean(distribution.entropy())
        critic_loss = self.critic_loss(params, batch, ppo)
        total = policy_loss - ppo.ent_coef * entropy + ppo.value_coef * critic_loss
        return total, {
            "policy_loss": policy_loss,
            "value_loss": critic_loss,
            "entropy": entropy,
            **diagnostics,
        }
