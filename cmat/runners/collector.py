"""The in-graph collector: JAX environments stepped inside the training program.

`collect_rollout` acts in every environment for `rollout_length` steps (`lax.scan` over steps,
`vmap` over environments) with given parameters and hands back a `Rollout` for the learner
(`cmat.runners.learner.learn`); its state is the environments' own (`EnvsState`). The host
collector of `cmat.runners.host` produces the same `Rollout` from simulators stepped in Python.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp

from cmat.algorithms.base import Algorithm, Params, initial_memories
from cmat.envs.protocol import EnvSpec, MarlEnv, TimeStep
from cmat.runners.types import Rollout, Transition


@flax.struct.dataclass
class EnvsState:
    """One seed's environments between rollouts."""

    env_state: Any
    timestep: TimeStep
    episode_return: jax.Array
    """[envs] return so far of each environment's running episode."""
    memory: Any = ()
    """[envs, ...] a recurrent algorithm's state after the last step (() otherwise)."""


@dataclass(frozen=True)
class InGraphCollector:
    """The static parts of collection: closed over, never traced."""

    env: MarlEnv
    algorithm: Algorithm
    num_envs: int
    rollout_length: int

    def reset(self, key: jax.Array) -> EnvsState:
        """Every environment reset; the state is made strongly typed, as a step returns it, so
        the chunk program compiles once (SMAX's reset yields weakly typed leaves)."""
        env_state, timestep = jax.vmap(self.env.reset)(jax.random.split(key, self.num_envs))
        env_state = jax.tree.map(lambda x: jnp.asarray(x, dtype=x.dtype), env_state)
        memory = initial_memories(self.algorithm, self.num_envs)
        return EnvsState(env_state, timestep, jnp.zeros(self.num_envs), memory)

    def collect(
        self, params: Params, envs: EnvsState, key: jax.Array
    ) -> tuple[EnvsState, Rollout]:
        """Act in all environments for `rollout_length` steps with `params`.

        The keys of a step's actions and environment steps come from one split of that step's
        key (one random-bits call per step on CPU, where each costs a small loop)."""
        num_envs, spec = self.num_envs, self.env.spec

        def env_step(envs: EnvsState, key: jax.Array) -> tuple[EnvsState, Transition]:
            act_keys, step_keys = jnp.split(jax.random.split(key, 2 * num_envs), 2)
            observed = envs.timestep
            acted, memory = jax.vmap(
                self.algorithm.act_with_memory, in_axes=(None, 0, 0, 0, 0, 0, 0)
            )(params, envs.memory, observed.obs, observed.action_mask, act_keys,
              observed.global_state, observed.done)
            env_state, timestep = jax.vmap(self.env.step)(
                step_keys, envs.env_state, env_actions(spec, acted.actions)
            )
            running = envs.episode_return + timestep.reward
            transition = Transition(
                obs=observed.obs,
                action_mask=observed.action_mask,
                actions=acted.actions,
                log_probs=acted.log_probs,
                value=acted.value,
                reward=timestep.reward,
                done=timestep.done,
                won=timestep.won,
                finished_return=jnp.where(timestep.done, running, 0.0),
                alive=observed.alive,
                global_state=observed.global_state,
                extras=acted.extras,
                start=observed.done,
            )
            envs = EnvsState(env_state, timestep, jnp.where(timestep.done, 0.0, running), memory)
            return envs, transition

        first_memory = envs.memory
        envs, steps = jax.lax.scan(env_step, envs, jax.random.split(key, self.rollout_length))
        return envs, Rollout(steps, envs.timestep.obs, envs.timestep.global_state, first_memory)


def env_actions(spec: EnvSpec, actions: jax.Array) -> jax.Array:
    """Actions as sent to the environment: continuous ones clipped to the spec's action range
    (host adapters then map it onto each agent's Box; the stored log-probability stays that of
    the unclipped sample)."""
    if spec.discrete:
        return actions
    return jnp.clip(actions, spec.action_low, spec.action_high)
