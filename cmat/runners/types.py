"""What a collector hands the learner (`cmat.runners.collector` in-graph, `cmat.runners.host`
on the host; `cmat.runners.learner.learn` takes it): one rollout of every environment."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax


class Transition(NamedTuple):
    """One step of every environment, stacked to [T, envs, ...] by a collector."""

    obs: jax.Array
    action_mask: jax.Array
    actions: jax.Array
    log_probs: jax.Array
    value: jax.Array
    reward: jax.Array
    done: jax.Array
    won: jax.Array
    finished_return: jax.Array
    """Return of the episode this step ended (0 where it ended none)."""
    alive: jax.Array
    """[n] agents active in `obs`."""
    global_state: jax.Array
    """[state_dim] the environment's global state at `obs`."""
    extras: Any
    start: jax.Array
    """[] `obs` begins an episode (the step before ended one; False after the first reset,
    where a recurrent algorithm's state is empty anyway)."""


class Rollout(NamedTuple):
    """What a collector hands the learner: T steps of every environment and what the
    environments showed after the last one (to bootstrap the returns)."""

    steps: Transition
    """[T, envs, ...]."""
    next_obs: jax.Array
    """[envs, n, obs_dim]."""
    next_global_state: jax.Array
    """[envs, state_dim]."""
    memory: Any = ()
    """[envs, ...] a recurrent algorithm's state before the first step (() otherwise)."""
