"""What an algorithm supplies to the shared trainer: acting, values and its loss.

Rollout, buffer, GAE, target critic, value normalisation, optimiser, evaluation, logging and
checkpoints are shared; an algorithm module holds only its network and its loss.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol

import jax

from cmat.config import PPOConfig

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
    """[B] values of the collecting parameters (normalised space), for the clipped value loss"""
    advantages: jax.Array
    """[B] team advantages"""
    targets: jax.Array
    """[B] value targets (normalised space)"""
    extras: Any = ()
    """[B, ...] whatever the algorithm's `act` stored with each step (e.g. a sampled agent order)"""


class ActResult(NamedTuple):
    actions: jax.Array
    log_probs: jax.Array
    """[n] per-agent log-probabilities of the sampled actions"""
    value: jax.Array
    """[] team value (normalised space)"""
    extras: Any = ()
    """any pytree the loss needs back from acting time; stored with the transition"""


class Algorithm(Protocol):
    """Per-team functions (no batch axis except in `loss`); the trainer vmaps them."""

    def init(self, key: jax.Array, obs: jax.Array, action_mask: jax.Array) -> Params: ...

    def act(
        self, params: Params, obs: jax.Array, action_mask: jax.Array, key: jax.Array
    ) -> ActResult: ...

    def greedy(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array: ...

    def value(self, params: Params, obs: jax.Array) -> jax.Array: ...

    def loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]: ...
