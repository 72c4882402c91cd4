"""JaxMARL's multi-agent Brax tasks (MABrax) adapted to the `MarlEnv` protocol: `mabrax:TASK`.

Needs brax (`pip install 'cmat[mabrax]'`), which JaxMARL 0.2.0 leaves optional and marks
deprecated; JaxMARL's MABrax steps Brax's `positional` pipeline by default, as Mava does.

Every agent drives its own joints (JaxMARL's `jaxmarl/environments/mabrax/mappings.py`) and sees
its own slice of Brax's observation. Agents' slices differ in size, so observations are
zero-padded to the largest and actions to the most joints, the padding ignored: JaxMARL's
`homogenisation_method="max"` (Mava's `mava/configs/env/mabrax.yaml`) without its one-hot agent
index, which jaxmarl 0.2.0 writes at index i and follows with the observation from index i + 1,
so that the same feature sits at a different position for every agent; one-hot ids come from
`make_env(..., agent_id=True)` instead (the suite's default). The global state is Brax's whole
observation, as in Mava's `MabraxWrapper.get_global_state` (`mava/wrappers/jaxmarl.py`). All
agents get Brax's reward, which is the team reward. Actions are continuous in [-1, 1].

An episode ends when Brax's environment terminates (the body is unhealthy) or after
`episode_length` simulation steps, `ceil(episode_length / action_repeat)` transitions (Brax's
`EpisodeWrapper`; Mava's 1000 steps). JaxMARL's own automatic reset (Brax's `AutoResetWrapper`,
which returns to one fixed first state) is off, and `step` resets as `JaxMarlEnv` does, to a
freshly drawn first state.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import jax
import jax.numpy as jnp

from cmat.envs.jaxmarl_envs import JaxMarlEnv
from cmat.envs.protocol import EnvSpec, TimeStep

# isort: split
# After cmat.envs.jaxmarl_envs, which imports JaxMARL with its import-time prints silenced.
from jaxmarl.environments.mabrax import MABraxEnv

TASKS = ("ant_4x2", "halfcheetah_6x1", "hopper_3x1", "humanoid_9|8", "walker2d_2x3")
"""The MABrax tasks JaxMARL 0.2.0 registers (`jaxmarl/registration.py`)."""

OPTIONS = ("episode_length", "action_repeat", "backend")
"""Keyword arguments passed through to JaxMARL's `MABraxEnv`."""


class MabraxEnv(JaxMarlEnv):
    """A MABrax task with padded observations and actions and Brax's observation as global
    state; `JaxMarlEnv.step` resets it.

    `obs_sizes[i]` and `action_sizes[i]` are agent i's observation size and number of joints
    before padding."""

    env: MABraxEnv

    def __init__(
        self, task: str, episode_length: int = 1000, action_repeat: int = 1,
        backend: str = "positional",
    ) -> None:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "MABrax is deprecated", DeprecationWarning)
            warnings.filterwarnings("ignore", "Brax System", UserWarning)
            self.env = MABraxEnv(
                task, episode_length=episode_length, action_repeat=action_repeat,
                auto_reset=False, backend=backend,
            )
        self.has_global_state = True
        self.obs_sizes = [self.env.agent_obs_mapping[agent].size for agent in self.env.agents]
        self.action_sizes = [
            self.env.agent_action_mapping[agent].size for agent in self.env.agents
        ]
        self.spec = EnvSpec(
            env_id=f"mabrax:{task}",
            num_agents=len(self.env.agents),
            obs_dim=max(self.obs_sizes),
            action_dim=max(self.action_sizes),
            discrete=False,
            max_episode_steps=math.ceil(episode_length / action_repeat),
            has_win_rate=False,
            action_low=-1.0,
            action_high=1.0,
            state_dim=self.env.env.observation_size,
        )

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]:
        """Start an episode."""
        obs, state = self.env.reset(key)
        false = jnp.asarray(False)
        return state, TimeStep(
            self._obs(obs), self._action_mask(state), jnp.float32(0.0), false, false,
            self._alive(state), state.obs.astype(jnp.float32),
        )

    def step_in_episode(
        self, key: jax.Array, state: Any, actions: jax.Array
    ) -> tuple[Any, TimeStep]:
        """`step` without the automatic reset: `actions` [n_agents, action_dim], each agent's
        first `action_sizes[i]` entries drive its joints."""
        agent_actions = {
            agent: actions[i, :size]
            for i, (agent, size) in enumerate(zip(self.env.agents, self.action_sizes))
        }
        obs, next_state, rewards, dones, _ = self.env.step_env(key, state, agent_actions)
        return next_state, TimeStep(
            self._obs(obs), self._action_mask(next_state),
            jnp.mean(self._stack(rewards)).astype(jnp.float32), dones["__all__"],
            jnp.asarray(False), self._alive(next_state), next_state.obs.astype(jnp.float32),
        )

    def _obs(self, per_agent: dict[str, jax.Array]) -> jax.Array:
        return jnp.stack([
            jnp.pad(per_agent[agent], (0, self.spec.obs_dim - size))
            for agent, size in zip(self.env.agents, self.obs_sizes)
        ]).astype(jnp.float32)
