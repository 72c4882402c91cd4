"""The host-environment protocol: `cmat.envs.protocol` with numpy arrays and Python stepping.

A host environment is a simulator that runs in Python (MuJoCo, GRF, any PettingZoo env), one
instance per environment slot. It has the `EnvSpec` and the auto-reset semantics of the in-graph
`MarlEnv`: when `done` is True, `obs` and `action_mask` already belong to the first step of the
next episode, while `reward`, `done` and `won` describe the transition that ended the last one.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple, Protocol

import numpy as np

from cmat.envs.protocol import EnvSpec


class HostTimeStep(NamedTuple):
    """`cmat.envs.protocol.TimeStep` as numpy arrays of one environment."""

    obs: np.ndarray
    """[n_agents, obs_dim] float32 (per-agent observations zero-padded to the largest)."""
    action_mask: np.ndarray
    """[n_agents, action_dim] bool; True = available. All True for continuous actions."""
    reward: float
    """Team reward of the transition just taken (0 after reset)."""
    done: bool
    """The transition just taken ended the episode (terminal, time limit or a fault)."""
    won: bool
    """The episode that just ended was won (False where undefined or not done)."""
    alive: np.ndarray
    """[n_agents] bool: agents active in `obs` (False: left the episode, or not in it yet)."""
    global_state: np.ndarray
    """[state_dim] float32 global state; shape [0] (host environments provide none yet)."""


class HostEnv(Protocol):
    """One host simulator behind the protocol; `step` resets automatically."""

    spec: EnvSpec

    def reset(self, seed: int | None = None) -> HostTimeStep: ...

    def step(self, actions: np.ndarray) -> HostTimeStep:
        """`actions`: [n_agents] ints, or [n_agents, action_dim] floats already inside the Box
        bounds of `spec` (adapters clip again to each agent's exact bounds)."""
        ...

    def close(self) -> None: ...


class AutoReset:
    """Base of the adapters: `_reset` and `_step` of one episode, auto-reset on `done`."""

    spec: EnvSpec

    def reset(self, seed: int | None = None) -> HostTimeStep:
        """Start an episode (seeded where `seed` is given)."""
        obs, mask = self._reset(seed)
        return HostTimeStep(obs, mask, 0.0, False, False, self._active(), self._global_state())

    def step(self, actions: np.ndarray) -> HostTimeStep:
        """Step; when the episode ends, the next one starts and its first observation returns."""
        obs, mask, reward, done, won = self._step(actions)
        if done:
            obs, mask = self._reset(None)
        return HostTimeStep(
            obs, mask, float(reward), bool(done), bool(won and done), self._active(),
            self._global_state(),
        )

    def close(self) -> None:
        """Release the simulator."""

    def _reset(self, seed: int | None) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _active(self) -> np.ndarray:
        """[n_agents] bool: the agents active in the current observation (all, by default)."""
        return np.ones(self.spec.num_agents, bool)

    def _global_state(self) -> np.ndarray:
        return np.zeros(self.spec.state_dim, np.float32)

    def _step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, bool, bool]:
        raise NotImplementedError


class HostAgentIdWrapper:
    """Appends each agent's one-hot id to its observation (the host `AgentIdWrapper`)."""

    def __init__(self, env: HostEnv) -> None:
        self.env = env
        self.spec = dataclasses.replace(env.spec, obs_dim=env.spec.obs_dim + env.spec.num_agents)
        self._ids = np.eye(env.spec.num_agents, dtype=np.float32)

    def reset(self, seed: int | None = None) -> HostTimeStep:
        """Start an episode."""
        return self._with_id(self.env.reset(seed))

    def step(self, actions: np.ndarray) -> HostTimeStep:
        """Step the wrapped environment."""
        return self._with_id(self.env.step(actions))

    def close(self) -> None:
        """Close the wrapped environment."""
        self.env.close()

    def _with_id(self, timestep: HostTimeStep) -> HostTimeStep:
        return timestep._replace(obs=np.concatenate([timestep.obs, self._ids], axis=-1))
