"""JaxMARL's multi-agent Brax tasks (MABrax) adapted to the `MarlEnv` protocol: `mabrax:TASK`.

Needs brax (the `mabrax` extra), which JaxMARL 0.2.0 leaves optional and marks
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
from collections.abc import Callable, Iterable
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp

from cmat.envs.jaxmarl_envs import JaxMarlEnv, stack_padded
from cmat.envs.protocol import EnvSpec
from cmat.envs.suites import choose

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

    def _agent_actions(self, actions: jax.Array) -> dict[str, jax.Array]:
        """`actions` [n_agents, action_dim]: agent i's first `action_sizes[i]` entries drive
        its joints."""
        return {
            agent: actions[i, :size]
            for i, (agent, size) in enumerate(zip(self.env.agents, self.action_sizes))
        }

    def _obs(self, per_agent: dict[str, jax.Array]) -> jax.Array:
        return stack_padded(per_agent, self.env.agents, self.obs_sizes)

    def _global_state(self, obs: dict[str, jax.Array], state: Any) -> jax.Array:
        brax_obs: jax.Array = state.obs
        return brax_obs.astype(jnp.float32)


def build(env_id: str, name: str) -> tuple[Callable[..., MabraxEnv], Iterable[str]]:
    """The mabrax suite's builder (cmat.envs.suites.Builder)."""
    return partial(MabraxEnv, choose("MABrax task", name, TASKS)), OPTIONS
