"""Random legal play: the environment-only baseline every throughput figure is compared with."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from cmat.envs.protocol import MarlEnv, TimeStep


def random_legal_actions(key: jax.Array, state: Any, timestep: TimeStep) -> jax.Array:
    """Uniformly random available actions [..., n] for timestep.action_mask [..., n, A]
    (`state` unused: the signature of `cmat.envs.smax_healer.first_episode_wins`'s policies)."""
    return jax.random.categorical(key, jnp.where(timestep.action_mask, 0.0, -jnp.inf))


def random_rollout(env: MarlEnv, num_envs: int, num_steps: int) -> Callable[[jax.Array], Any]:
    """A function running `num_steps` uniformly random legal joint actions in `num_envs` envs.

    It returns the final carry and the episode count, so XLA cannot drop any of the work.
    """

    def one_step(carry: tuple[Any, TimeStep], key: jax.Array) -> tuple[Any, jax.Array]:
        state, timestep = carry
        action_key, step_key = jax.random.split(key)
        actions = random_legal_actions(action_key, state, timestep)
        state, timestep = jax.vmap(env.step)(jax.random.split(step_key, num_envs), state, actions)
        return (state, timestep), timestep.done

    def run(key: jax.Array) -> tuple[Any, jax.Array]:
        reset_key, scan_key = jax.random.split(key)
        carry = jax.vmap(env.reset)(jax.random.split(reset_key, num_envs))
        carry, dones = jax.lax.scan(one_step, carry, jax.random.split(scan_key, num_steps))
        return carry, dones.sum()

    return run
