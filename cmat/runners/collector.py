"""The in-graph collector: JAX environments stepped inside the training program.

`collect_rollout` acts in every environment for `rollout_length` steps (`lax.scan` over steps,
`vmap` over environments) with given parameters and hands back a `Rollout` for the learner
(`cmat.runners.learner.learn`); its state is the environments' own (`EnvsState`). The host
collector of `cmat.runners.host` produces the same `Rollout` from simulators stepped in Python.
Both report each rollout's episodes and the environment's faults with `rollout_report`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp

from cmat.algorithms.base import Algorithm, Params, initial_memories, with_memory
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
                with_memory(self.algorithm).act_with_memory, in_axes=(None, 0, 0, 0, 0, 0, 0)
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


ENV_FAULTS = (
    "non-finite environment reward", "non-finite environment observation",
    "non-finite environment global state",
    "an action mask that allows no action to a live agent (one with nothing to do must be "
    "marked not alive)",
)
"""What a rollout's `env_fault` k > 0 names: ENV_FAULTS[k - 1]."""


def all_finite(tree: Any) -> jax.Array:
    """[] bool: every leaf of `tree` is finite (True for a tree without leaves)."""
    leaves = [jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(tree)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.bool_(True)


def rollout_report(steps: Transition) -> dict[str, jax.Array]:
    """What one seed's rollout ([T, envs, ...], from either collector) says of its episodes and
    its environment: the episodes that ended in it, the sum of their returns and their wins,
    and `env_fault`: 0 if its rewards, observations and global states are finite and every
    live agent had an action to take, else 1 + the index in `ENV_FAULTS` of the first check
    that failed. A closed mask would otherwise train silently: the masked policy falls back to
    a uniform draw over actions the environment said were not available."""
    live_can_act = jnp.all(~steps.alive | jnp.any(steps.action_mask, axis=-1))
    checks = jnp.stack([all_finite(steps.reward), all_finite(steps.obs),
                        all_finite(steps.global_state), live_can_act])
    return {
        "episodes": jnp.sum(steps.done),
        "return_sum": jnp.sum(steps.finished_return),
        "win_sum": jnp.sum(steps.won & steps.done),
        "env_fault": jnp.where(jnp.all(checks), 0, 1 + jnp.argmin(checks)).astype(jnp.int32),
    }


def env_actions(spec: EnvSpec, actions: jax.Array) -> jax.Array:
    """Actions as sent to the environment: continuous ones clipped to the spec's action range
    (host adapters then map it onto each agent's Box; the stored log-probability stays that of
    the unclipped sample)."""
    if spec.discrete:
        return actions
    return jnp.clip(actions, spec.action_low, spec.action_high)
