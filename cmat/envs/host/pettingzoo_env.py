"""`pettingzoo:package.module:factory`: any PettingZoo `ParallelEnv` behind the host protocol.

How a ParallelEnv maps onto the protocol (docs/own-environment.md):
- Agents are `possible_agents` in their order. The live set is `env.agents`, read after every
  reset and step: agents may leave, join after `reset`, or come back. An agent outside it, or
  in it without an observation this step, is inactive exactly as a dead one: zero observation,
  (discrete) only action 0 available, so its forced action adds 0 to the joint log-ratio, and
  `alive` False. Actions are sent to the agents of `env.agents` only.
- Observations: each agent's space is flattened (`gymnasium.spaces.flatten`; a Dict holding
  "observation" and "action_mask" contributes its "observation") and zero-padded at the end to the
  largest agent's size. An observation whose shape is not its space's is a `CmatError` naming
  the agent, the step and both shapes.
- Actions: all agents Discrete (sizes may differ: the missing actions are masked out) or all Box
  (sizes may differ: an agent uses the first entries of the padded vector, and the rest are sampled
  but ignored). The policy acts in a normalised range: every Box dimension with finite bounds
  maps [-1, 1] affinely onto [low, high] (after clipping to [-1, 1]), so any finite Box is
  reached whatever its offset and scale; a dimension with an infinite bound is sent as sampled,
  clipped to its finite side. The stored log-probability is that of the policy's own sample:
  the map is fixed and affine, so the ratio of two policies' densities (each agent's r_i, and
  the joint ratio Π_i r_i) is the same in either space.
- Action masks: `obs[agent]["action_mask"]` or `info[agent]["action_mask"]` where the env gives
  them; otherwise every action is available. A live agent whose mask allows no action is a
  `CmatError`.
- Team reward: the mean of the rewards of the agents that got one this step (a shared reward
  passes through unchanged; a sum would scale with the team size). Every agent that acted must
  get one. A reward may be a number, a NumPy scalar or a size-1 array; any other shape is a
  `CmatError`.
- Global state: `env.state()` flattened, where the env implements it (its size from
  `state_space` or one probing reset); otherwise none, and centralised critics read the
  concatenated observations. MaMuJoCo's `state()` is the single-agent environment's observation.
- Done: `env.agents` is empty (where the env keeps no `agents`, every agent terminated or
  truncated), or `max_episode_steps` transitions elapsed. Won: any agent's info says
  `"won": True` at the end; the win rate is reported only where the env's
  `metadata["has_win_rate"]` is true.
- Crashes: an exception inside the env's own `reset`, `step` or `state` is a `SimulatorCrash`
  (the pools restart the env); a malformed return value is a `CmatError` (the run stops).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from cmat.envs.factory import load_factory
from cmat.envs.host.protocol import AutoReset, simulator_call
from cmat.envs.protocol import EnvSpec
from cmat.errors import CmatError

DEFAULT_MAX_EPISODE_STEPS = 1000
"""Time limit where the env names none (`max_episode_steps`, `max_cycles` or its metadata)."""


def make_pettingzoo_env(env_id: str, target: str, **kwargs: Any) -> PettingZooEnv:
    """Call the factory named by `target` with `kwargs` and adapt the ParallelEnv it returns."""
    factory = load_factory(env_id, target)
    try:
        env = factory(**kwargs)
    except Exception as error:  # the user's factory: any error is a bad id or bad options
        raise CmatError(f"{env_id}: the factory raised {type(error).__name__}: {error}") from None
    return PettingZooEnv(env, env_id)


def implements_state(env: Any) -> bool:
    """Whether the env's class overrides `ParallelEnv.state` (whose base raises
    NotImplementedError), so no probing reset is spent on envs without one."""
    try:
        from pettingzoo import ParallelEnv
    except ImportError:
        return True
    return getattr(type(env), "state", None) is not ParallelEnv.state


def probe_state_dim(env: Any) -> int:
    """The size of `env.state()`: from `state_space` where the env declares one, else from one
    call after a probing reset; 0 where `state()` is not implemented."""
    import gymnasium.spaces as spaces

    space = getattr(env, "state_space", None)
    if isinstance(space, spaces.Space):
        return int(spaces.flatdim(space))
    if not callable(getattr(env, "state", None)) or not implements_state(env):
        return 0
    try:
        env.reset(seed=None)
        return int(np.asarray(env.state(), np.float32).size)
    except (NotImplementedError, AttributeError):
        return 0


def agent_space(env: Any, env_id: str, kind: str, agent: str) -> Any:
    """`env.observation_space(agent)` (`kind` "observation") or `env.action_space(agent)`;
    CmatError where the env has no such space or it is not a gymnasium Space."""
    import gymnasium.spaces as spaces

    call = f"{kind}_space({agent!r})"
    try:
        space = getattr(env, f"{kind}_space")(agent)
    except AttributeError as error:
        if error.name not in (f"{kind}_space", f"{kind}_spaces"):
            raise CmatError(f"{env_id}: {call} raised AttributeError: {error}") from None
        raise CmatError(f"{env_id}: the env has no {kind}_space(agent) method or "
                        f"{kind}_spaces dict") from None
    except Exception as error:  # the user's space method
        raise CmatError(f"{env_id}: {call} raised {type(error).__name__}: {error}") from None
    if not isinstance(space, spaces.Space):
        got = "None" if space is None else f"a {type(space).__name__}"
        raise CmatError(f"{env_id}: {call} returned {got}, expected a gymnasium Space")
    return space


class PettingZooEnv(AutoReset):
    """A PettingZoo ParallelEnv adapted to `HostEnv` (see the module docstring)."""

    def __init__(self, env: Any, env_id: str, max_episode_steps: int | None = None) -> None:
        import gymnasium.spaces as spaces

        aec = hasattr(env, "agent_iter")
        if aec or not all(hasattr(env, name) for name in ("possible_agents", "reset", "step")):
            hint = (" (an AEC env: convert it with pettingzoo.utils.aec_to_parallel)" if aec
                    else " (a cmat MarlEnv or JaxMARL env: use jax:MODULE:FACTORY)"
                    if hasattr(env, "step_env") or hasattr(env, "spec") else "")
            raise CmatError(
                f"{env_id}: the factory must return a PettingZoo ParallelEnv, got "
                f"{type(env).__name__}{hint}"
            )
        self.env = env
        self.agents: list[str] = list(env.possible_agents)
        if not self.agents:
            raise CmatError(f"{env_id}: the env has no agents")
        self._obs_spaces = []
        for agent in self.agents:
            space = agent_space(env, env_id, "observation", agent)
            if isinstance(space, spaces.Dict) and "observation" in space.spaces:
                space = space["observation"]
            self._obs_spaces.append(space)
        self._obs_sizes = [int(spaces.flatdim(space)) for space in self._obs_spaces]
        action_spaces = [agent_space(env, env_id, "action", agent) for agent in self.agents]
        self._action_spaces = action_spaces
        if all(isinstance(space, spaces.Discrete) for space in action_spaces):
            discrete = True
            self._action_sizes = [int(space.n) for space in action_spaces]
            self._action_starts = [int(space.start) for space in action_spaces]
            low, high = -1.0, 1.0
        elif all(isinstance(space, spaces.Box) for space in action_spaces):
            discrete = False
            self._action_sizes = [int(np.prod(space.shape)) for space in action_spaces]
            self._lows = [space.low.reshape(-1).astype(np.float64) for space in action_spaces]
            self._highs = [space.high.reshape(-1).astype(np.float64) for space in action_spaces]
            self._mapped = [np.isfinite(lo) & np.isfinite(hi)
                            for lo, hi in zip(self._lows, self._highs)]
            self._shapes = [space.shape for space in action_spaces]
            self._dtypes = [space.dtype for space in action_spaces]
            every_mapped = all(mapped.all() for mapped in self._mapped)
            low, high = (-1.0, 1.0) if every_mapped else (-np.inf, np.inf)
        else:
            kinds = sorted({type(space).__name__ for space in action_spaces})
            raise CmatError(
                f"{env_id}: action spaces must be all Discrete or all Box, got {', '.join(kinds)}"
            )
        metadata = getattr(env, "metadata", None) or {}
        limit = (
            max_episode_steps
            or getattr(env, "max_episode_steps", None)
            or getattr(env, "max_cycles", None)
            or metadata.get("max_episode_steps")
            or DEFAULT_MAX_EPISODE_STEPS
        )
        self.spec = EnvSpec(
            env_id=env_id,
            num_agents=len(self.agents),
            obs_dim=max(self._obs_sizes),
            action_dim=max(self._action_sizes),
            discrete=discrete,
            max_episode_steps=int(limit),
            has_win_rate=bool(metadata.get("has_win_rate", False)),
            action_low=low,
            action_high=high,
            state_dim=probe_state_dim(env),
        )
        self._index = {agent: index for index, agent in enumerate(self.agents)}
        self._live: set[str] = set()
        """`env.agents` after the last reset or step: the agents actions go to."""
        self._active_now = np.zeros(len(self.agents), bool)
        """Agents in `_live` with an observation in the last reset or step."""

    def description(self) -> dict[str, Any]:
        """The spec's fields, the agents and each agent's observation and action space."""
        return {
            "agents": self.agents,
            **{f"observation_space({agent!r})": space
               for agent, space in zip(self.agents, self._obs_spaces)},
            **{f"action_space({agent!r})": space
               for agent, space in zip(self.agents, self._action_spaces)},
            **super().description(),
        }

    def close(self) -> None:
        """Close the PettingZoo env."""
        close = getattr(self.env, "close", None)
        if close is not None:
            close()

    def agent_name(self, index: int) -> str:
        return self.agents[index]

    def _reset(self, seed: int | None) -> tuple[np.ndarray, np.ndarray]:
        with simulator_call(self.spec.env_id, "reset"):
            result = self.env.reset(seed=seed)
        obs, infos = result if isinstance(result, tuple) and len(result) == 2 else (result, {})
        obs, infos = self._mapping(obs, "observations"), self._mapping(infos or {}, "infos")
        self._live = self._live_agents(obs, {}, {})
        return self._encode(obs, infos)

    def _step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, bool, bool]:
        joint = {agent: self._env_action(self._index[agent], actions[self._index[agent]])
                 for agent in self.agents if agent in self._live}
        with simulator_call(self.spec.env_id, "step"):
            result = self.env.step(joint)
        if not isinstance(result, tuple) or len(result) != 5:
            got = (f"a tuple of {len(result)} items" if isinstance(result, tuple)
                   else type(result).__name__)
            gym = "; a Gym-style (obs, reward, done, info)?" if got == "a tuple of 4 items" else ""
            raise CmatError(f"{self.spec.env_id}: step must return (observations, rewards, "
                            f"terminations, truncations, infos), got {got}{gym}")
        obs, rewards, terminations, truncations, infos = (
            self._mapping(part, name) for part, name in zip(
                result, ("observations", "rewards", "terminations", "truncations", "infos")
            )
        )
        unrewarded = [agent for agent in joint if agent not in rewards]
        if unrewarded:
            raise CmatError(f"{self.spec.env_id}: rewards {self.at_step} has no reward for "
                            f"agent(s) {', '.join(map(repr, unrewarded))}, which acted")
        self._live = self._live_agents(obs, terminations, truncations)
        done = not self._live or self.episode_step >= self.spec.max_episode_steps
        team = [self._reward(agent, value) for agent, value in rewards.items()
                if agent in self._index]
        reward = float(np.mean(team)) if team else 0.0
        won = any(bool(info.get("won", False)) for info in infos.values()
                  if isinstance(info, dict))
        obs_array, mask = self._encode(obs, infos)
        return obs_array, mask, reward, done, won

    def _mapping(self, value: Any, name: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise CmatError(
                f"{self.spec.env_id}: {name} {self.at_step} must be a dict keyed by agent, "
                f"got {type(value).__name__}"
            )
        return value

    def _live_agents(self, obs: dict[str, Any], terminations: dict[str, Any],
                     truncations: dict[str, Any]) -> set[str]:
        """`env.agents` (checked against `possible_agents`), or where the env keeps none, the
        agents with an observation that did not terminate or truncate."""
        live = getattr(self.env, "agents", None)
        if live is None:
            return {agent for agent in obs if agent in self._index
                    and not terminations.get(agent, False) and not truncations.get(agent, False)}
        unknown = [agent for agent in live if agent not in self._index]
        if unknown:
            raise CmatError(f"{self.spec.env_id}: env.agents holds {unknown[0]!r} {self.at_step}, "
                            f"which is not in possible_agents")
        return set(live)

    def _reward(self, agent: str, value: Any) -> float:
        """A reward as a float: a number, a NumPy scalar or a size-1 array (CmatError else)."""
        try:
            array = np.asarray(value, np.float64)
        except (TypeError, ValueError):
            raise CmatError(f"{self.spec.env_id}: reward of agent {agent!r} {self.at_step} is "
                            f"not a number: {value!r}") from None
        if array.size != 1:
            raise CmatError(f"{self.spec.env_id}: reward of agent {agent!r} {self.at_step} has "
                            f"shape {array.shape}; expected a scalar or a size-1 array")
        return float(self._finite(array.reshape(()), "reward", self._index[agent]))

    def _global_state(self) -> np.ndarray:
        if self.spec.state_dim == 0:
            return np.zeros(0, np.float32)
        with simulator_call(self.spec.env_id, "state"):
            state = np.asarray(self.env.state(), np.float32).reshape(-1)
        if state.size != self.spec.state_dim:
            raise CmatError(
                f"{self.spec.env_id}: state() returned {state.size} values {self.at_step}, "
                f"expected {self.spec.state_dim}"
            )
        return state

    def _active(self) -> np.ndarray:
        """The live agents with an observation (`possible_agents` order)."""
        return self._active_now.copy()

    def _env_action(self, index: int, action: np.ndarray) -> Any:
        if self.spec.discrete:
            return int(action) + self._action_starts[index]
        size = self._action_sizes[index]
        own = np.asarray(action, np.float64)[:size]
        low, high, mapped = self._lows[index], self._highs[index], self._mapped[index]
        unit = (np.clip(own, -1.0, 1.0) + 1.0) / 2.0
        start, span = np.where(mapped, low, 0.0), np.where(mapped, high - low, 0.0)
        sent = np.where(mapped, start + unit * span, own)
        return np.clip(sent, low, high).reshape(self._shapes[index]).astype(self._dtypes[index])

    def _encode(self, obs: dict[str, Any], infos: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        spec = self.spec
        obs_array = np.zeros((spec.num_agents, spec.obs_dim), np.float32)
        mask = np.zeros((spec.num_agents, spec.action_dim), bool)
        self._active_now[:] = False
        for index, agent in enumerate(self.agents):
            size = self._action_sizes[index]
            if agent not in self._live or agent not in obs:
                mask[index, 0 if spec.discrete else slice(None)] = True
                continue
            self._active_now[index] = True
            value = obs[agent]
            agent_mask = None
            if isinstance(value, dict) and "observation" in value:
                agent_mask = value.get("action_mask")
                value = value["observation"]
            info = infos.get(agent)
            if agent_mask is None and isinstance(info, dict):
                agent_mask = info.get("action_mask")
            obs_array[index, : self._obs_sizes[index]] = self._flat_observation(index, value)
            if not spec.discrete:
                mask[index] = True
            elif agent_mask is None:
                mask[index, :size] = True
            else:
                flat = np.asarray(agent_mask).reshape(-1)
                if flat.size != size:
                    raise CmatError(f"{spec.env_id}: the action mask of agent {agent!r} "
                                    f"{self.at_step} has {flat.size} entries, but its action "
                                    f"space has {size} actions")
                mask[index, :size] = flat.astype(bool)
                if not mask[index].any():
                    raise CmatError(f"{spec.env_id}: the action mask of live agent {agent!r} "
                                    f"{self.at_step} allows no action; an agent with nothing to "
                                    f"do must leave env.agents")
        return obs_array, mask

    def _flat_observation(self, index: int, value: Any) -> np.ndarray:
        """Agent `index`'s observation flattened by its space; CmatError where it does not fit
        the space's shape."""
        import gymnasium.spaces as spaces

        space, agent = self._obs_spaces[index], self.agents[index]
        where = f"{self.spec.env_id}: observation of agent {agent!r} {self.at_step}"
        if isinstance(space, spaces.Box):
            shape = np.shape(value)
            if shape != space.shape:
                raise CmatError(f"{where} has shape {shape}, but its observation space declares "
                                f"{space.shape}")
        try:
            flat = np.asarray(spaces.flatten(space, value), np.float32).reshape(-1)
        except Exception as error:  # the space's own flatten rejecting a malformed value
            raise CmatError(f"{where} does not fit its space {space}: "
                            f"{type(error).__name__}: {error}") from None
        if flat.size != self._obs_sizes[index]:
            raise CmatError(f"{where} flattens to {flat.size} values, but its observation space "
                            f"declares {self._obs_sizes[index]}")
        return flat


def build(env_id: str, name: str) -> tuple[Callable[..., PettingZooEnv], None]:
    """The pettingzoo suite's builder (cmat.envs.suites.Builder): NAME is
    `package.module:factory`; environments are seeded at reset, so `seed` is left alone."""
    return lambda seed, **options: make_pettingzoo_env(env_id, name, **options), None
