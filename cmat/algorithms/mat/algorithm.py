"""MAT (Wen et al. 2022): agents act one after another in a fixed order (paper eq. mat).

Each agent's ratio r_i = π_i(a_i | O, a_<i) / π_i,old(a_i | O, a_<i) is clipped on its own with
its advantage, and the clipped objectives are averaged over agents and samples; with
`ppo.active_masks` (the reference default) over the active agents only, as is the entropy
(mat/algorithms/mat/mat_trainer.py, `use_policy_active_masks`); the value loss averages over
every agent, dead ones too, as the reference SMAC script runs it (`ppo.value_active_masks`
false: `train_smac.sh` passes the store_false flag `--use_value_active_masks`).

Values, as the reference with value normalisation (`mat.per_agent_gae`, the default): GAE runs
per agent on each agent's own V(ô_i) with the shared team reward, and each V(ô_i) is regressed
on its own return (mat/utils/shared_buffer.py, `compute_returns`). Without it, one GAE runs on
the team value V(O) = mean_i V(ô_i) and every V(ô_i) is regressed on the team target, around
its own collecting-time value stored with the transition (`ActResult.extras`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, cast

import jax
import jax.numpy as jnp

from cmat.algorithms.base import ActResult, Batch, Params, active_mask, chunked, value_active_mask
from cmat.algorithms.mat.network import MATNetwork, MATOutput
from cmat.algorithms.mat.options import MATOptions
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
from cmat.networks.heads import action_distribution


class EncoderDecoder(Protocol):
    """What MAT reads of its network: a Flax module of one team with `MATNetwork`'s methods
    (`encode`, `value`, `decode` and the teacher-forced `__call__`, run through `init` and
    `apply`). MAT's own is `MATNetwork`, Sable's `SableNetwork`: MAT names only its own, so
    that Sable's package depends on MAT's and not the other way round."""

    num_agents: int
    discrete: bool

    def init(self, rngs: Any, *args: Any, **kwargs: Any) -> Any: ...

    def apply(self, variables: Any, *args: Any, **kwargs: Any) -> Any: ...


@dataclass(frozen=True)
class MAT(PPOAlgorithm):
    network: EncoderDecoder
    """The encoder-decoder: MAT's (`MATNetwork`), or Sable's with the same methods
    (`cmat.algorithms.sable`)."""
    per_agent_gae: bool = False
    """Values are per agent ([n], `mat.per_agent_gae`), else their team mean ([])."""

    @classmethod
    def build(
        cls, config: NetworkConfig, spec: EnvSpec, ppo: PPOConfig | None = None,
        options: AlgorithmOptions | None = None,
    ) -> MAT:
        own = options_of(options, MATOptions)
        network = MATNetwork(config, spec.num_agents, spec.action_dim, spec.discrete,
                             own.attention_block, own.inducing_points)
        return cls(network, own.per_agent_gae)

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
        return cast(
            tuple[jax.Array, jax.Array], self.network.apply(params, obs, method="encode")
        )

    def decode(
        self,
        params: Params,
        encoded: jax.Array,
        action_mask: jax.Array,
        order: jax.Array,
        key: jax.Array | None,
    ) -> tuple[jax.Array, jax.Array]:
        """Autoregressive actions along `order` and their per-agent log-probs."""
        return cast(
            tuple[jax.Array, jax.Array],
            self.network.apply(params, encoded, action_mask, order, key, method="decode"),
        )

    def act(
        self, params: Params, obs: jax.Array, action_mask: jax.Array, key: jax.Array,
        global_state: jax.Array | None = None,
    ) -> ActResult:
        """Actions along the identity order; the value is [n] per agent with per-agent GAE,
        else the team mean, with the per-agent values in `extras` for the value loss."""
        encoded, agent_values = self.encode(params, obs)
        actions, log_probs = self.decode(params, encoded, action_mask, self.identity, key)
        return self.acted(actions, log_probs, agent_values)

    def acted(
        self, actions: jax.Array, log_probs: jax.Array, agent_values: jax.Array
    ) -> ActResult:
        """What acting returns: the values [n] per agent with per-agent GAE, else their team
        mean with the per-agent values in `extras` for the value loss."""
        if self.per_agent_gae:
            return ActResult(actions, log_probs, agent_values)
        return ActResult(actions, log_probs, jnp.mean(agent_values), agent_values)

    def greedy(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        encoded, _ = self.encode(params, obs)
        return self.decode(params, encoded, action_mask, self.identity, None)[0]

    def value(
        self, params: Params, obs: jax.Array, global_state: jax.Array | None = None
    ) -> jax.Array:
        """[n] per-agent values V(ô_i) with per-agent GAE, else V(O) = their mean."""
        if self.per_agent_gae:
            return self.encode(params, obs)[1]
        return cast(jax.Array, self.network.apply(params, obs, method="value"))

    def teacher_forced(
        self, params: Params, batch: Batch, orders: jax.Array, chunks: int = 1
    ) -> MATOutput:
        """Network outputs for every sample of the batch, decoded along orders [B, n], in
        `chunks` sequential slices of the batch (`chunked`)."""
        # `_make`: the axes spec holds ints and None where MATOutput declares arrays.
        out_axes = MATOutput._make((0, None, 0, 0))
        per_sample = jax.vmap(self.network.apply, in_axes=(None, 0, 0, 0, 0), out_axes=out_axes)
        return cast(MATOutput, chunked(
            lambda *samples: per_sample(params, *samples), chunks, out_axes
        )(batch.obs, batch.action_mask, batch.actions, orders))

    def loss_along(
        self,
        params: Params,
        batch: Batch,
        orders: jax.Array,
        old_agent_values: jax.Array,
        ppo: PPOConfig,
    ) -> tuple[jax.Array, dict[str, jax.Array], MATOutput]:
        """Eq. mat with the actions decoded along orders [B, n], and every agent's value
        regressed on its target (per agent, or the team's) around its collecting-time value
        [B, n]; policy and entropy means over active agents with `ppo.active_masks`, the value
        loss's with `ppo.value_active_masks`. Also returns the outputs."""
        output = self.teacher_forced(params, batch, orders, ppo.minibatch_chunks)
        total, metrics = self.objective(output, batch, old_agent_values, ppo)
        return total, metrics, output

    def objective(
        self, output: MATOutput, batch: Batch, old_agent_values: jax.Array, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """Eq. mat on the network's outputs [B, n, ...] for the batch's samples: per-agent
        clipped surrogates, mean entropy, per-agent value losses around old_agent_values
        [B, n]; the total loss and its metrics."""
        distribution = action_distribution(
            output.action_params, output.log_std, self.network.discrete
        )
        mask = active_mask(batch, ppo)
        log_ratio = distribution.log_prob(batch.actions) - batch.log_probs
        advantages = per_agent(batch.advantages, log_ratio.shape)
        policy_loss, diagnostics = clipped_surrogate_loss(
            log_ratio, advantages, ppo.clip_eps, mask
        )
        entropies = distribution.entropy()
        entropy = masked_mean(entropies, mask)
        critic_loss = value_loss(
            output.agent_values, old_agent_values, per_agent(batch.targets, log_ratio.shape),
            ppo, value_active_mask(batch, ppo),
        )
        total, terms = total_loss(policy_loss, entropy, critic_loss, ppo)
        metrics = {
            **terms,
            **diagnostics,
            **policy_diagnostics(
                log_ratio, jnp.sum(log_ratio, axis=-1), ppo.clip_eps, entropies, batch.alive
            ),
        }
        return total, metrics

    def loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """Per-agent clipped surrogates with the team advantage, mean entropy, per-agent value
        losses on the team target."""
        orders = jnp.broadcast_to(self.identity, batch.log_probs.shape)
        total, metrics, _ = self.loss_along(
            params, batch, orders, self.collected_agent_values(batch, batch.extras), ppo
        )
        return total, metrics

    def collected_agent_values(self, batch: Batch, stored: Any) -> jax.Array:
        """Every agent's collecting-time value [B, n]: the batch's values with per-agent GAE,
        else the per-agent values acting stored with the transition."""
        return batch.values if self.per_agent_gae else stored


def per_agent(x: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """Team quantities [B] broadcast over agents to [B, n]; per-agent ones [B, n] as they are."""
    return jnp.broadcast_to(x if x.ndim == len(shape) else x[:, None], shape)
