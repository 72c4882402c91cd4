"""MAPPO (Yu et al. 2022): one actor shared by all agents, a centralized critic, per-agent PPO.

Agent i acts from [o_i; one-hot(i)] alone (decentralised execution; the id lets the shared actor
tell agents apart; where the environment's observations already end with it, `EnvSpec.agent_id`,
o_i is used as it is). The critic V(s) reads the environment's global state (`TimeStep.
global_state`; on SMAX the world state JaxMARL's own MAPPO critic uses), or all agents'
observations concatenated where the environment has none. Each agent's ratio r_i = π_i / π_i,old
is clipped on its own against the team advantage and the surrogate is averaged over agents
(unlike CMAT's joint ratio, paper eq. ratio); with `ppo.active_masks` (the reference default) the
policy loss and entropy average over active agents only. The feed-forward actor stands in for
the reference's optional recurrent one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, cast

import distrax
import jax
import jax.numpy as jnp

from cmat.algorithms.base import ActResult, Batch, Params, active_mask
from cmat.algorithms.mappo.network import MLPActor, MLPCritic
from cmat.algorithms.mappo.options import MLPOptions
from cmat.algorithms.options import options_of
from cmat.algorithms.ppo import (
    clipped_surrogate_loss,
    masked_mean,
    policy_diagnostics,
    total_loss,
    value_loss,
)
from cmat.algorithms.sgd import PPOAlgorithm
from cmat.config import AlgorithmOptions, NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.networks.heads import action_distribution, greedy_action


@dataclass(frozen=True)
class MAPPO(PPOAlgorithm):
    actor: MLPActor
    critic: MLPCritic
    num_agents: int
    discrete: bool
    state_dim: int = 0
    """The environment's global state size; 0: the critic reads the concatenated observations."""
    shared_actor: ClassVar[bool] = True
    """One actor for every agent, so it reads the agent's one-hot id after o_i (`MLPActor`'s
    `agent_ids`, where the observations do not end with it already: `EnvSpec.agent_id`)."""

    @classmethod
    def build(
        cls, config: NetworkConfig, spec: EnvSpec, ppo: PPOConfig | None = None,
        options: AlgorithmOptions | None = None,
    ) -> MAPPO:
        layers = options_of(options, MLPOptions).mlp_layers
        appends_ids = cls.shared_actor and not spec.agent_id
        actor = MLPActor(
            config.n_embd, spec.action_dim, spec.discrete, config.init_gain, config.log_std_init,
            layers, spec.num_agents if appends_ids else 0,
        )
        return cls(
            actor,
            MLPCritic(config.n_embd, layers),
            spec.num_agents,
            spec.discrete,
            spec.state_dim,
        )

    def critic_input(self, obs: jax.Array, global_state: jax.Array | None) -> jax.Array:
        """The critic's input [..., s]: the global state, or obs [..., n, obs_dim] flattened
        where the environment has none.

        Raises ValueError if the environment has a global state and none is given."""
        if self.state_dim == 0:
            return obs.reshape(*obs.shape[:-2], obs.shape[-2] * obs.shape[-1])
        if global_state is None or global_state.shape[-1] != self.state_dim:
            found = None if global_state is None else global_state.shape
            raise ValueError(
                f"the critic needs the global state [..., {self.state_dim}], got {found}"
            )
        return global_state

    def init(self, key: jax.Array, obs: jax.Array, action_mask: jax.Array) -> Params:
        actor_key, critic_key = jax.random.split(key)
        return {
            "actor": self.actor.init(actor_key, obs, action_mask),
            "critic": self.critic.init(critic_key, self.critic_input(obs, self.blank_state)),
        }

    @property
    def blank_state(self) -> jax.Array:
        """A zero global state, to shape the critic's parameters."""
        return jnp.zeros(self.state_dim)

    def policy(
        self, params: Params, obs: jax.Array, action_mask: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """Every agent's action parameters [..., n, A] and log-std."""
        return cast(
            tuple[jax.Array, jax.Array],
            self.actor.apply(params["actor"], obs, action_mask),
        )

    def distribution(
        self, params: Params, obs: jax.Array, action_mask: jax.Array
    ) -> distrax.Distribution:
        return action_distribution(*self.policy(params, obs, action_mask), self.discrete)

    def act(
        self, params: Params, obs: jax.Array, action_mask: jax.Array, key: jax.Array,
        global_state: jax.Array | None = None,
    ) -> ActResult:
        distribution = self.distribution(params, obs, action_mask)
        actions, log_probs = distribution.sample_and_log_prob(seed=key)
        return ActResult(actions, log_probs, self.value(params, obs, global_state))

    def greedy(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        return greedy_action(self.action_logits(params, obs, action_mask), self.discrete)

    def action_logits(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        """Every agent's masked logits [n, A] (`Factorised`)."""
        return self.policy(params, obs, action_mask)[0]

    def value(
        self, params: Params, obs: jax.Array, global_state: jax.Array | None = None
    ) -> jax.Array:
        """V(s) of the team (`critic_input`)."""
        return cast(
            jax.Array, self.critic.apply(params["critic"], self.critic_input(obs, global_state))
        )

    def critic_loss(self, params: Params, batch: Batch, ppo: PPOConfig) -> jax.Array:
        """The team value loss (one value per sample: no agent to mask)."""
        return value_loss(
            self.value(params, batch.obs, batch.global_state), batch.values, batch.targets, ppo
        )

    def loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """Per-agent clipped surrogate with the team advantage, mean entropy, value loss."""
        distribution = self.distribution(params, batch.obs, batch.action_mask)
        mask = active_mask(batch, ppo)
        log_ratio = distribution.log_prob(batch.actions) - batch.log_probs
        policy_loss, diagnostics = clipped_surrogate_loss(
            log_ratio, batch.advantages[:, None], ppo.clip_eps, mask
        )
        entropies = distribution.entropy()
        entropy = masked_mean(entropies, mask)
        critic_loss = self.critic_loss(params, batch, ppo)
        total, terms = total_loss(policy_loss, entropy, critic_loss, ppo)
        return total, {
            **terms,
            **diagnostics,
            **policy_diagnostics(
                log_ratio, jnp.sum(log_ratio, axis=-1), ppo.clip_eps, entropies, batch.alive
            ),
        }
