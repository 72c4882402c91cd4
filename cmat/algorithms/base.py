"""What an algorithm supplies to the shared trainer: acting, values and its loss.

Rollout, buffer, GAE, target critic, value normalisation, optimiser, evaluation, logging and
checkpoints are shared; an algorithm package (`cmat/algorithms/<name>/`) holds only its network
and its loss.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol, cast, runtime_checkable

import jax
import optax

from cmat.config import AlgorithmOptions, NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec

Params = Any


class Batch(NamedTuple):
    """Flattened samples [B, ...] for one PPO minibatch."""

    obs: jax.Array
    """[B, n, obs_dim]"""
    action_mask: jax.Array
    """[B, n, A]"""
    actions: jax.Array
    """[B, n] (discrete) or [B, n, A] (continuous)"""
    log_probs: jax.Array
    """[B, n] per-agent log-probabilities under the collecting parameters"""
    values: jax.Array
    """[B] team values (or [B, n] per-agent values) of the collecting parameters (normalised
    space), for the clipped value loss"""
    advantages: jax.Array
    """[B] team advantages, or [B, n] per-agent ones (per-agent GAE)"""
    targets: jax.Array
    """[B] or [B, n] value targets (normalised space), shaped as `values`"""
    extras: Any = ()
    """[B, ...] whatever the algorithm's `act` stored with each step (e.g. a sampled agent order)"""
    alive: jax.Array | None = None
    """[B, n] bool: agents active in the observation (the env's `alive`); None: all of them"""
    global_state: jax.Array | None = None
    """[B, state_dim] the environment's global state (state_dim 0 where it has none); None:
    none given (a critic that needs one raises)"""
    starts: jax.Array | None = None
    """Recurrent algorithms only ([B, T]): the step's observation begins an episode. Their
    batches are B sequences of T steps ([B, T, ...] in every field above)."""
    memory: Any = ()
    """Recurrent algorithms only ([B, ...]): the state each sequence starts from."""


Loss = Callable[[Params, Batch, PPOConfig], tuple[jax.Array, dict[str, jax.Array]]]
"""A minibatch loss: (params, batch, ppo) -> (scalar to minimise, metrics)."""


def active_mask(batch: Batch, ppo: PPOConfig) -> jax.Array | None:
    """The [B, n] mask the loss means run over: the batch's `alive` with `ppo.active_masks`,
    else None (every agent)."""
    return batch.alive if ppo.active_masks and batch.alive is not None else None


def value_loss_masked(ppo: PPOConfig) -> bool:
    """Whether a per-agent value loss averages over active agents only: `ppo.value_active_masks`,
    or `ppo.active_masks` where that is None."""
    return ppo.active_masks if ppo.value_active_masks is None else ppo.value_active_masks


def value_active_mask(batch: Batch, ppo: PPOConfig) -> jax.Array | None:
    """The [B, n] mask a per-agent value loss's mean runs over: the batch's `alive` with
    `value_loss_masked(ppo)`, else None (every agent)."""
    return batch.alive if value_loss_masked(ppo) and batch.alive is not None else None


def loss_is_sample_mean(ppo: PPOConfig) -> bool:
    """Whether the shared PPO losses are plain means over the minibatch's samples: no active
    masks in the policy, entropy or value means, whose denominators (the active entries) would
    differ from slice to slice. Then a minibatch's loss and gradient are the means of those of
    equal slices of it (`cmat.algorithms.sgd.minibatch_gradient`)."""
    return not ppo.active_masks and not value_loss_masked(ppo)


class ActResult(NamedTuple):
    actions: jax.Array
    """[n] int32 (discrete) or [n, A] float32 (continuous) joint action"""
    log_probs: jax.Array
    """[n] per-agent log-probabilities of the sampled actions"""
    value: jax.Array
    """[] team value, or [n] per-agent values with per-agent GAE (normalised space)"""
    extras: Any = ()
    """any pytree the loss needs back from acting time; stored with the transition"""


class Algorithm(Protocol):
    """Per-team functions (no batch axis except in `loss`); the trainer vmaps them.

    `global_state` [state_dim] is the environment's global state (`TimeStep.global_state`,
    empty where it has none); only centralised critics read it. What the rest of cmat needs to
    know about an algorithm without building it (its name, config layers, capabilities,
    fine-tuning stages, network fields) is its `cmat.algorithms.entry.AlgorithmEntry`, not part
    of this protocol. An algorithm whose acting carries a state across an episode's steps is
    `Recurrent` as well.
    """

    @classmethod
    def build(
        cls, network: NetworkConfig, spec: EnvSpec, ppo: PPOConfig | None = None,
        options: AlgorithmOptions | None = None,
    ) -> Algorithm:
        """The algorithm for an environment of `spec` with the sizes of `network`, the PPO
        settings that shape its networks (e.g. `ppo.minibatch_chunks`) and its own section
        `options` (its entry's `options` class; None: its defaults)."""
        ...

    def init(self, key: jax.Array, obs: jax.Array, action_mask: jax.Array) -> Params:
        """Fresh parameters, shaped by one team's obs [n, obs_dim] and action_mask [n, A]."""
        ...

    def act(
        self, params: Params, obs: jax.Array, action_mask: jax.Array, key: jax.Array,
        global_state: jax.Array | None = None,
    ) -> ActResult:
        """Sample one team's joint action from obs [n, obs_dim] with action_mask [n, A] (True:
        available; a masked action is never sampled), with its log-probabilities and value."""
        ...

    def greedy(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        """The most likely available joint action [n] (continuous: the means [n, A]), for
        evaluation."""
        ...

    def value(
        self, params: Params, obs: jax.Array, global_state: jax.Array | None = None
    ) -> jax.Array:
        """The critic's value of one team's obs [n, obs_dim]: [] (team value) or [n]
        (per-agent values), in the value normaliser's space, as `ActResult.value`."""
        ...

    def loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """The scalar to minimise on one minibatch (`Batch`, [B, ...]) and its metrics
        (policy_loss, value_loss, entropy, approx_kl, clip_frac, ...)."""
        ...

    def update(
        self, optimizer: optax.GradientTransformation, params: Params, opt_state: Any,
        batch: Batch, rng: jax.Array, ppo: PPOConfig,
    ) -> tuple[Params, Any, dict[str, jax.Array]]:
        """One update's optimisation on a rollout's `batch`: new params, optimiser state and
        metrics. `cmat.algorithms.sgd.PPOAlgorithm` gives PPO's epochs × minibatches on `loss`;
        an algorithm with its own scheme (HAPPO's agent-by-agent phases) overrides it."""
        ...

    def finetune_labels(self, params: Params, mode: str) -> Any:
        """A tree like `params` labelling each leaf `sgd.TRAIN` or `sgd.FROZEN` for fine-tuning
        stage `mode`; raises `CmatError` for an algorithm without fine-tuning stages."""
        ...


@runtime_checkable
class Recurrent(Protocol):
    """An algorithm whose acting carries a state across the steps of an episode (recurrent
    Sable). The runners act and evaluate every algorithm through these methods, a feed-forward
    one through `Stateless` (`with_memory`); for a recurrent one the learner hands `loss` whole
    sequences and their first states, and values come from `sequence_values`."""

    @property
    def recurrent(self) -> bool:
        """Whether this instance carries its state (False for a class built either way, as
        Sable's feed-forward variant)."""
        ...

    def initial_memory(self) -> Any:
        """One team's state before its first step."""
        ...

    def act_with_memory(
        self, params: Params, memory: Any, obs: jax.Array, action_mask: jax.Array,
        key: jax.Array, global_state: jax.Array, start: jax.Array,
    ) -> tuple[ActResult, Any]:
        """`Algorithm.act` from `memory`, the state after the previous step; `start` [] says
        `obs` begins an episode (the state is reset first). Returns the new state too."""
        ...

    def greedy_with_memory(
        self, params: Params, memory: Any, obs: jax.Array, action_mask: jax.Array,
        start: jax.Array,
    ) -> tuple[jax.Array, Any]:
        """`Algorithm.greedy` from `memory` (as `act_with_memory`); returns the new state too."""
        ...

    def sequence_values(
        self, params: Params, memory: Any, obs: jax.Array, global_state: jax.Array,
        starts: jax.Array,
    ) -> jax.Array:
        """Values [T] or [T, n] of T consecutive steps of one environment (obs [T, n, obs_dim],
        global_state [T, state_dim], starts [T]) from the state `memory` before them."""
        ...


@runtime_checkable
class Factorised(Protocol):
    """An algorithm whose agents decide independently given the team's observations: CMAT (on
    its consensus), MAPPO, HAPPO and Triple-BERT, not MAT, PMAT or Sable, which decode one
    agent after another. Each agent's action distribution on its own is then the team's
    policy, which is what a joint decision under constraints between agents (the dispatch
    tasks' conflict-free matching, `cmat.envs.dispatch.matched`) scores."""

    def action_logits(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        """Every agent's masked logits [n, A] for one team's obs [n, obs_dim] and action_mask
        [n, A] (unavailable actions at `cmat.networks.heads.MASKED_LOGIT`): those `greedy`
        takes the argmax of. Discrete actions only."""
        ...


def is_recurrent(algorithm: Algorithm) -> bool:
    """Whether `algorithm` acts from a carried state (`Recurrent`, its `recurrent` true)."""
    return isinstance(algorithm, Recurrent) and algorithm.recurrent


@dataclass(frozen=True)
class Stateless:
    """A feed-forward algorithm seen through `Recurrent`'s methods: an empty state, `act` and
    `greedy` of each step alone, `value` of every step on its own."""

    algorithm: Algorithm

    @property
    def recurrent(self) -> bool:
        return False

    def initial_memory(self) -> Any:
        return ()

    def act_with_memory(
        self, params: Params, memory: Any, obs: jax.Array, action_mask: jax.Array,
        key: jax.Array, global_state: jax.Array, start: jax.Array,
    ) -> tuple[ActResult, Any]:
        return self.algorithm.act(params, obs, action_mask, key, global_state), memory

    def greedy_with_memory(
        self, params: Params, memory: Any, obs: jax.Array, action_mask: jax.Array,
        start: jax.Array,
    ) -> tuple[jax.Array, Any]:
        return self.algorithm.greedy(params, obs, action_mask), memory

    def sequence_values(
        self, params: Params, memory: Any, obs: jax.Array, global_state: jax.Array,
        starts: jax.Array,
    ) -> jax.Array:
        values: jax.Array = jax.vmap(self.algorithm.value, in_axes=(None, 0, 0))(
            params, obs, global_state)
        return values


def with_memory(algorithm: Algorithm) -> Recurrent:
    """`algorithm` itself where it is recurrent (`is_recurrent`), else `Stateless(algorithm)`:
    what the runners act, evaluate and compute sequence values through."""
    if is_recurrent(algorithm):
        return cast(Recurrent, algorithm)
    return Stateless(algorithm)


def initial_memories(algorithm: Algorithm, *batch: int) -> Any:
    """`with_memory(algorithm).initial_memory()` for every team of a batch of shape `batch`
    ([*batch, ...]; () for feed-forward algorithms)."""
    return jax.tree.map(lambda x: jax.numpy.broadcast_to(x, (*batch, *jax.numpy.shape(x))),
                        with_memory(algorithm).initial_memory())


def chunked(function: Callable[..., Any], chunks: int, out_axes: Any = 0) -> Callable[..., Any]:
    """`function` of arrays batched along their first axis [B, ...], run over `chunks`
    sequential slices of B (`jax.lax.map`), each slice's forward pass recomputed for the
    backward pass (`jax.checkpoint`) rather than kept: the same outputs and gradients up to
    floating-point order, with the activation memory of B / chunks samples
    (`ppo.minibatch_chunks`). `out_axes` is a prefix of the output tree as `jax.vmap` takes
    it: 0 for outputs batched along the first axis, None for outputs equal in every slice
    (taken from the first). chunks = 1 returns `function` itself. B must be divisible by
    chunks (`TrainConfig.validate` checks it for minibatches)."""
    if chunks == 1:
        return function

    def run(*args: Any) -> Any:
        sliced = jax.tree.map(lambda x: x.reshape(chunks, x.shape[0] // chunks, *x.shape[1:]), args)
        stacked = jax.lax.map(jax.checkpoint(lambda chunk: function(*chunk)), sliced)
        return jax.tree.map(
            lambda axis, x: jax.tree.map(
                lambda leaf: leaf[0] if axis is None else leaf.reshape(-1, *leaf.shape[2:]), x
            ),
            out_axes, stacked, is_leaf=lambda node: node is None,
        )

    return run
