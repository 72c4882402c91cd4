"""The host-environment protocol: `cmat.envs.protocol` with numpy arrays and Python stepping.

A host environment is a simulator that runs in Python (MuJoCo, GRF, any PettingZoo env), one
instance per environment slot. It has the `EnvSpec` and the auto-reset semantics of the in-graph
`MarlEnv`: when `done` is True, `obs` and `action_mask` already belong to the first step of the
next episode, while `reward`, `done` and `won` describe the transition that ended the last one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, Generic, NamedTuple, Protocol, TypeVar, overload

import numpy as np

from cmat.envs.protocol import EnvSpec
from cmat.errors import CmatError


class SimulatorCrash(Exception):
    """An exception raised inside a simulator's own `reset` or `step` (not in cmat's code):
    the pools restart that environment (`cmat.envs.host.pool`)."""


@contextmanager
def simulator_call(env_id: str, what: str) -> Iterator[None]:
    """Run a call into the simulator; any exception it raises becomes a `SimulatorCrash`."""
    try:
        yield
    except Exception as error:
        raise SimulatorCrash(f"{env_id}: {what} raised {type(error).__name__}: {error}") from error


_Reward = TypeVar("_Reward")
_Flag = TypeVar("_Flag")


class HostTimeStep(NamedTuple, Generic[_Reward, _Flag]):
    """`cmat.envs.protocol.TimeStep` as numpy arrays of one environment (`HostStep`); the pools
    give batches of them, every field with a leading environment axis (`HostBatch`)."""

    obs: np.ndarray
    """[n_agents, obs_dim] float32 (per-agent observations zero-padded to the largest)."""
    action_mask: np.ndarray
    """[n_agents, action_dim] bool; True = available. All True for continuous actions."""
    reward: _Reward
    """Team reward of the transition just taken (0 after reset)."""
    done: _Flag
    """The transition just taken ended the episode (terminal, time limit or a fault)."""
    won: _Flag
    """The episode that just ended was won (False where undefined or not done)."""
    alive: np.ndarray
    """[n_agents] bool: agents active in `obs` (False: left the episode, or not in it yet)."""
    global_state: np.ndarray
    """[state_dim] float32 global state: a PettingZoo env's `state()` where it implements one
    (MaMuJoCo: the single-agent observation); shape [0] where the env has none (GRF)."""


HostStep = HostTimeStep[float, bool]
"""One environment's timestep."""
HostBatch = HostTimeStep[np.ndarray, np.ndarray]
"""A pool's timestep: every field [E, ...] with a leading environment axis."""


class HostEnv(Protocol):
    """One host simulator behind the protocol; `step` resets automatically."""

    spec: EnvSpec

    @property
    def nonfinite(self) -> str:
        """"error" or "warn" (`cmat.config.NONFINITE_POLICIES`)."""
        ...

    @property
    def nonfinite_replaced(self) -> int:
        """Non-finite values replaced by 0 so far (`nonfinite` "warn")."""
        ...

    def reset(self, seed: int | None = None) -> HostStep: ...

    def step(self, actions: np.ndarray, reset: bool = True) -> HostStep:
        """`actions`: [n_agents] ints, or [n_agents, action_dim] floats in the range of
        `spec.action_low/high` (the PettingZoo adapter maps [-1, 1] onto each agent's Box).
        With `reset` False an episode that ends is not followed by the next one: the simulator
        rests (later steps return its last observation, reward 0, not done, and call nothing)
        until `reset`; an evaluation ends its last episode of a slot this way."""
        ...

    def description(self) -> dict[str, Any]:
        """What every instance built for one environment id must share (the pools compare each
        instance they build with the first): the spec's fields, and where the adapter has them,
        the agents and their spaces."""
        ...

    def close(self) -> None: ...


class AutoReset:
    """Base of the adapters: `_reset` and `_step` of one episode, auto-reset on `done`.

    Every observation, reward and global state is checked for NaN and infinities: with
    `nonfinite` "error" (the default) one is a `CmatError` naming the environment, the agent and
    the step; with "warn" it is replaced by 0 and counted in `nonfinite_replaced`."""

    spec: EnvSpec
    nonfinite: str = "error"
    nonfinite_replaced: int = 0
    """Values replaced by 0 so far (`nonfinite` "warn")."""
    episode_step: int = 0
    """Transitions taken in the current episode (0 at its reset)."""
    resting: HostStep | None = None
    """After an episode that ended with `step(..., reset=False)`: what later steps return."""

    def reset(self, seed: int | None = None) -> HostStep:
        """Start an episode (seeded where `seed` is given)."""
        self.episode_step = 0
        self.resting = None
        obs, mask = self._reset(seed)
        return self._checked(obs, mask, 0.0, False, False)

    def step(self, actions: np.ndarray, reset: bool = True) -> HostStep:
        """Step; when the episode ends, the next one starts and its first observation returns
        (with `reset` False: the simulator rests, `HostEnv.step`)."""
        if self.resting is not None:
            return self.resting
        self.episode_step += 1
        obs, mask, reward, done, won = self._step(actions)
        finite_reward = self._finite(np.float32(reward), "reward", None)
        if done and reset:
            self.episode_step = 0
            obs, mask = self._reset(None)
        timestep = self._checked(obs, mask, float(finite_reward), bool(done), bool(won and done))
        if done and not reset:
            self.resting = timestep._replace(reward=0.0, done=False, won=False)
        return timestep

    def _checked(self, obs: np.ndarray, mask: np.ndarray, reward: float, done: bool,
                 won: bool) -> HostStep:
        if not np.isfinite(obs).all():
            for index in range(obs.shape[0]):
                obs[index] = self._finite(obs[index], "observation", index)
        state = self._finite(self._global_state(), "global state", None)
        return HostTimeStep(obs, mask, reward, done, won, self._active(), state)

    @overload
    def _finite(self, values: np.ndarray, what: str, agent: int | None) -> np.ndarray: ...

    @overload
    def _finite(
        self, values: np.floating[Any], what: str, agent: int | None
    ) -> np.floating[Any] | np.ndarray: ...

    def _finite(
        self, values: np.ndarray | np.floating[Any], what: str, agent: int | None
    ) -> np.ndarray | np.floating[Any]:
        """`values`, or a CmatError / zeros in place of NaN and infinities (`nonfinite`)."""
        bad = ~np.isfinite(values)
        if not bad.any():
            return values
        if self.nonfinite == "warn":
            self.nonfinite_replaced += int(bad.sum())
            return np.where(bad, 0, values).astype(values.dtype)
        who = "" if agent is None else f" of agent {self.agent_name(agent)!r}"
        raise CmatError(
            f"{self.spec.env_id}: non-finite {what}{who} {self.at_step} "
            f"({np.asarray(values).reshape(-1)[np.flatnonzero(bad)[0]]}); fix the "
            f"environment or set host_nonfinite=warn to replace such values by 0"
        )

    @property
    def at_step(self) -> str:
        """Where in the episode the adapter is, for error messages."""
        return f"at step {self.episode_step} of an episode"

    def agent_name(self, index: int) -> str:
        """The environment's name for agent `index`."""
        return str(index)

    def description(self) -> dict[str, Any]:
        """The spec's fields (`HostEnv.description`)."""
        return dataclasses.asdict(self.spec)

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
        self.spec = dataclasses.replace(
            env.spec, obs_dim=env.spec.obs_dim + env.spec.num_agents, agent_id=True
        )
        self._ids = np.eye(env.spec.num_agents, dtype=np.float32)

    @property
    def nonfinite(self) -> str:
        return self.env.nonfinite

    @property
    def nonfinite_replaced(self) -> int:
        return self.env.nonfinite_replaced

    def reset(self, seed: int | None = None) -> HostStep:
        """Start an episode."""
        return self._with_id(self.env.reset(seed))

    def step(self, actions: np.ndarray, reset: bool = True) -> HostStep:
        """Step the wrapped environment."""
        return self._with_id(self.env.step(actions, reset))

    def description(self) -> dict[str, Any]:
        """The wrapped environment's description."""
        return self.env.description()

    def close(self) -> None:
        """Close the wrapped environment."""
        self.env.close()

    def _with_id(self, timestep: HostStep) -> HostStep:
        return timestep._replace(obs=np.concatenate([timestep.obs, self._ids], axis=-1))
