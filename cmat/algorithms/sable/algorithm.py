"""Sable (Mahjoub et al., ICML 2025): MAT's autoregressive PPO on a retention network.

Acting, values and the per-agent clipped objective are MAT's (cmat.algorithms.mat), on
`network.SableNetwork`. `sable` is the Sable paper's Sable, the recurrent one
(Mava's `rec_sable`, mava/systems/sable/anakin/rec_sable.py): the retention states are carried
from step to step of an episode (decayed by κ, reset at episode starts, `SableCarry`), the
timestep within the episode is encoded into every retention, and the update trains on whole
rollout sequences of each environment, from the state it had before the rollout: minibatches
are sets of environments, the chunkwise form of retention computes each sequence
(`sable.retention_chunk`; None, the whole rollout at once, is Mava's
`timestep_chunk_size: ~`). `ff_sable` (`FFSable`) is Mava's feed-forward Sable
(mava/systems/sable/anakin/ff_sable.py): every step starts from empty states.

What both references do differently from MAT, and cmat does with them:

- Every epoch permutes the agents of the whole batch with one random permutation, so the
  decoder is trained along a new agent order each epoch while acting keeps the index order; the
  stored log-probs stay those of acting (`permute_agents`; the carried state stays the one
  acting produced).
- Advantages are normalised per minibatch over all agents, not per update
  (`ppo.normalize_advantages` is off and the loss normalises).
- Per-agent values and GAE with the team reward, squared-error value loss (½·MSE, clipped with
  `clip_eps`, weight 0.5), no value normalisation, no active masks; one block of width 64 with
  one head, decay scale 0.8 (mava/configs/network/rec_retention.yaml, ff_retention.yaml).

Their PPO settings differ: `sable` runs mava/configs/system/sable/rec_sable.yaml (instadeepai/
Mava at 18c0f2d): lr 5e-4, 10 epochs of one minibatch, clip 0.2, gradient norm 10; `ff_sable`
runs ff_sable.yaml (b53e2de): lr 2.5e-4, 4 epochs of 2 minibatches, clip 0.2, gradient norm
0.5. Mava uses these on every environment; the Sable paper's per-task tuned values are not
published in a form this project has, so no task overrides them (docs/algorithms.md).

Rollout length and number of environments stay the suite's (SMAX: 100 steps × 32 envs) so that
Sable and the other methods collect the same batches; the reference's 128 steps × 16 envs × 2
vectorised updates per device is the same 4,096-sample batch split into two gradient steps.
Continuous actions use cmat's Gaussian head (MAT's), not the reference's tanh-squashed Normal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple, cast

import jax
import jax.numpy as jnp
import optax

from cmat.algorithms.base import ActResult, Batch, Params
from cmat.algorithms.mat.algorithm import MAT
from cmat.algorithms.mat.network import MATOutput
from cmat.algorithms.options import options_of
from cmat.algorithms.ppo import normalize
from cmat.algorithms.sable.network import SableMemory, SableNetwork, empty_memory
from cmat.algorithms.sable.options import FFSableOptions, SableOptions
from cmat.algorithms.sgd import Metrics, minibatch_sgd
from cmat.config import AlgorithmOptions, NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec


class SableCarry(NamedTuple):
    """A team's recurrent state between steps."""

    memory: SableMemory
    position: jax.Array
    """[] int32: the index within its episode of the last step acted (-1 before the first)."""


def step_positions(last: jax.Array, starts: jax.Array) -> jax.Array:
    """Indices [T] within their episodes of T steps after one at index `last` [] (starts [T]:
    the step begins an episode)."""

    def advance(previous: jax.Array, start: jax.Array) -> tuple[jax.Array, jax.Array]:
        position = jnp.where(start, 0, previous + 1)
        return position, position

    return jax.lax.scan(advance, last, starts)[1]


def permute_agents(batch: Batch, key: jax.Array) -> Batch:
    """`batch` with its agents in one random order (the same for every sample and step):
    observations, masks, actions, log-probs, activity, stored extras and the per-agent values,
    advantages and targets ([..., n] after the sample axes: [B] or, for sequences, [B, T]);
    team quantities, the global state, episode starts and carried states as they are."""
    axis = batch.obs.ndim - 2
    order = jax.random.permutation(key, batch.obs.shape[axis])

    def permuted(x: jax.Array) -> jax.Array:
        return jnp.take(x, order, axis=axis)

    def per_agent(x: jax.Array) -> jax.Array:
        return permuted(x) if x.ndim > axis else x

    return batch._replace(
        obs=permuted(batch.obs),
        action_mask=permuted(batch.action_mask),
        actions=permuted(batch.actions),
        log_probs=permuted(batch.log_probs),
        values=per_agent(batch.values),
        advantages=per_agent(batch.advantages),
        targets=per_agent(batch.targets),
        extras=jax.tree.map(per_agent, batch.extras),
        alive=None if batch.alive is None else permuted(batch.alive),
    )


def flat(x: jax.Array) -> jax.Array:
    """[B, T, ...] -> [B·T, ...]."""
    return x.reshape(x.shape[0] * x.shape[1], *x.shape[2:])


def flatten_sequences(batch: Batch) -> Batch:
    """A batch of B sequences of T steps as B·T samples (starts and carried states dropped)."""
    return batch._replace(
        obs=flat(batch.obs), action_mask=flat(batch.action_mask), actions=flat(batch.actions),
        log_probs=flat(batch.log_probs), values=flat(batch.values),
        advantages=flat(batch.advantages), targets=flat(batch.targets),
        extras=jax.tree.map(flat, batch.extras),
        alive=None if batch.alive is None else flat(batch.alive),
        global_state=None if batch.global_state is None else flat(batch.global_state),
        starts=None, memory=(),
    )


@dataclass(frozen=True)
class Sable(MAT):
    """The recurrent Sable (`memory` True), and through `FFSable` the feed-forward one."""

    network: SableNetwork

    memory: ClassVar[bool] = True
    """Whether the retention states carry across an episode's steps (module docstring)."""

    @classmethod
    def build(
        cls, config: NetworkConfig, spec: EnvSpec, ppo: PPOConfig | None = None,
        options: AlgorithmOptions | None = None,
    ) -> Sable:
        own = options_of(options, SableOptions if cls.memory else FFSableOptions)
        network = SableNetwork(
            config, spec.num_agents, spec.action_dim, spec.discrete, memory=cls.memory,
            decay_scale=own.retention_decay,
            chunk_steps=own.retention_chunk if isinstance(own, SableOptions) else None,
        )
        return cls(network, own.per_agent_gae)

    @property
    def recurrent(self) -> bool:
        """The recurrent Sable's retention carries across steps; `FFSable` acts through
        `cmat.algorithms.base.Stateless` instead."""
        return self.network.memory

    def initial_memory(self) -> Any:
        """`SableCarry` with empty states."""
        return SableCarry(empty_memory(self.network.config), jnp.array(-1, jnp.int32))

    def act_step(
        self, params: Params, carry: SableCarry, obs: jax.Array, action_mask: jax.Array,
        key: jax.Array | None, start: jax.Array,
    ) -> tuple[jax.Array, jax.Array, jax.Array, SableCarry]:
        """One step from `carry`: actions, log-probs and values [n], and the new carry."""
        position = jnp.where(start, 0, carry.position + 1)
        actions, log_probs, values, memory = cast(
            tuple[jax.Array, jax.Array, jax.Array, SableMemory],
            self.network.apply(
                params, obs, action_mask, self.identity, key, carry.memory, start, position,
                method="act_step",
            ),
        )
        return actions, log_probs, values, SableCarry(memory, position)

    def act_with_memory(
        self, params: Params, memory: Any, obs: jax.Array, action_mask: jax.Array,
        key: jax.Array, global_state: jax.Array, start: jax.Array,
    ) -> tuple[ActResult, Any]:
        actions, log_probs, values, carry = self.act_step(
            params, memory, obs, action_mask, key, start
        )
        return self.acted(actions, log_probs, values), carry

    def greedy_with_memory(
        self, params: Params, memory: Any, obs: jax.Array, action_mask: jax.Array,
        start: jax.Array,
    ) -> tuple[jax.Array, Any]:
        actions, _, _, carry = self.act_step(params, memory, obs, action_mask, None, start)
        return actions, carry

    def sequence_values(
        self, params: Params, memory: Any, obs: jax.Array, global_state: jax.Array,
        starts: jax.Array,
    ) -> jax.Array:
        """Per-agent values [T, n] (their mean [T] without per-agent GAE) of one environment's
        steps, encoded from the carried state."""
        carry = cast(SableCarry, memory)
        _, values, _ = cast(tuple[jax.Array, jax.Array, jax.Array], self.network.apply(
            params, obs, carry.memory, starts, step_positions(carry.position, starts),
            method="encode_sequence",
        ))
        return values if self.per_agent_gae else jnp.mean(values, axis=-1)

    def sequence_outputs(self, params: Params, batch: Batch) -> MATOutput:
        """The training pass over each of the batch's sequences [B, T, ...] from its carried
        state, flattened to [B·T, ...]."""

        def one(obs: jax.Array, mask: jax.Array, actions: jax.Array, carry: SableCarry,
                starts: jax.Array) -> MATOutput:
            output, _ = self.network.apply(
                params, obs, mask, actions, carry.memory, starts,
                step_positions(carry.position, starts), method="sequence",
            )
            return cast(MATOutput, output)

        assert batch.starts is not None, "a recurrent batch carries its sequences' starts"
        out_axes = MATOutput._make((0, None, 0, 0))
        outputs = jax.vmap(one, out_axes=out_axes)(
            batch.obs, batch.action_mask, batch.actions, batch.memory, batch.starts
        )
        return MATOutput(flat(outputs.action_params), outputs.log_std,
                         flat(outputs.agent_values), flat(outputs.encoded))

    def loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """MAT's loss on the minibatch's advantages normalised over all its entries (the
        reference normalises per minibatch); recurrent: on its sequences' training pass."""
        batch = batch._replace(advantages=normalize(batch.advantages))
        if not self.recurrent:
            return super().loss(params, batch, ppo)
        output = self.sequence_outputs(params, batch)
        flat = flatten_sequences(batch)
        return self.objective(output, flat, self.collected_agent_values(flat, flat.extras), ppo)

    def update(
        self, optimizer: optax.GradientTransformation, params: Params, opt_state: Any,
        batch: Batch, rng: jax.Array, ppo: PPOConfig,
    ) -> tuple[Params, Any, Metrics]:
        """PPO's epochs × minibatches, the agents permuted anew each epoch."""
        return minibatch_sgd(
            self.loss, optimizer, params, opt_state, batch, rng, ppo, permute_agents
        )


class FFSable(Sable):
    """Mava's feed-forward Sable (`ff_sable`): every step from empty retention states."""

    memory: ClassVar[bool] = False
