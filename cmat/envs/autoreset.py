"""The in-graph automatic reset every JAX environment adapter's `step` ends with."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from cmat.envs.protocol import TimeStep


def auto_reset(
    next_state: Any, timestep: TimeStep, reset_state: Any, first: TimeStep
) -> tuple[Any, TimeStep]:
    """(state, timestep) of one step that continues into the next episode where it ended one:
    where `timestep.done`, the state is `reset_state` and the observation, action mask, alive
    flags and global state are `first`'s (the new episode's), while reward, done and won stay
    those of the transition taken. `next_state` and `timestep` come from the step within the
    episode, `reset_state` and `first` from a reset."""
    done = timestep.done
    state = jax.tree.map(lambda r, s: jnp.where(done, r, s), reset_state, next_state)
    return state, timestep._replace(
        obs=jnp.where(done, first.obs, timestep.obs),
        action_mask=jnp.where(done, first.action_mask, timestep.action_mask),
        alive=jnp.where(done, first.alive, timestep.alive),
        global_state=jnp.where(done, first.global_state, timestep.global_state),
    )
