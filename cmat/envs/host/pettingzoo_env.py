"""`pettingzoo:package.module:factory`: any PettingZoo `ParallelEnv` behind the host protocol.

How a ParallelEnv maps onto the protocol (README, "Host environments"):
- Agents are `possible_agents` in their order. An agent that terminated while others go on is
  dead until the episode ends: zero observation, and (discrete) only action 0 available, so its
  forced action adds 0 to the joint log-ratio; what it is sent is nothing (it is not stepped).
- Observations: each agent's space is flattened (`gymnasium.spaces.flatten`; a Dict holding
  "observation" and "action_mask" contributes its "observation") and zero-padded at the end to the
  largest agent's size.
- Actions: all agents Discrete (sizes may differ: the missing actions are masked out) or all Box
  (sizes may differ: an agent uses the first entries of the padded vector, and the rest are sampled
  but ignored). Box actions are clipped to each agent's own bounds before stepping (clip, not a
  tanh squash: the policy's log-probability is that of the unclipped sample, as in MAT).
- Action masks: `obs[agent]["action_mask"]` or `info[agent]["action_mask"]` where the env gives
  them; otherwise every action is available.
- Team reward: the mean of the rewards of the agents that got one this step (a shared reward
  passes through unchanged; a sum would scale with the team size).
- Global state: `env.state()` flattened, where the env implements it (its size from
  `state_space` or one probing reset); otherwise none, and centralised critics read the
  concatenated observations. MaMuJoCo's `state()` is the single-agent environment's observation.
- Active agents (`alive`): the agents still in the episode.
- Done: every agent terminated or truncated (or `env.agents` is empty), or `max_episode_steps`
  transitions elapsed. Won: any agent's info says `"won": True` at the end; the win rate is
  reported only where the env's `metadata["has_win_rate"]` is true.
"""

from __future__ import annotations

import importlib
from typing import Any, Callable

import numpy as np

from cmat.envs.host.protocol import AutoReset
from cmat.envs.protocol import EnvSpec
from cmat.errors import CmatError

DEFAULT_MAX_EPISODE_STEPS = 1000
"""Time limit where the env names none (`max_episode_steps`, `max_cycles` or its metadata)."""


def load_factory(env_id: str, target: str) -> Callable[..., Any]:
    """The callable named by `package.module:factory` (the factory may be dotted: `Class.make`)."""
    module_name, _, attribute = target.rpartition(":")
    if not module_name or not attribute:
        raise CmatError(
            f"PettingZoo id {env_id!r} must look like pettingzoo:package.module:factory"
        )
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise CmatError(f"{env_id}: cannot import {module_name!r} ({error})") from None
    factory: Any = module
    for part in attribute.split("."):
        if not hasattr(factory, part):
            raise CmatError(f"{env_id}: module {module_name!r} has no {attribute!r}")
        factory = getattr(factory, part)
    if not callable(factory):
        raise CmatError(f"{env_id}: {attribute!r} is not callable")
    return factory


def make_pettingzoo_env(env_id: str, target: str, **kwargs: Any) -> PettingZooEnv:
    """Call the factory named by `target` with `kwargs` and adapt the ParallelEnv it returns."""
    factory = load_factory(env_id, target)
    try:
        env = factory(**kwargs)
    except Exception as error:  # the user's factory: any error is a bad id or bad options
        raise CmatError(f"{env_id}: the factory raised {type(error).__name__}: {error}") from None
    return PettingZooEnv(env, env_id)


def probe_state_dim(env: Any, env_id: str) -> int:
    """The size of `env.state()`: from `state_space` where the env declares one, else from one
    call after a probing reset; 0 where `state()` is not implemented."""
    import gymnasium.spaces as spaces

    space = getattr(env, "state_space", None)
    if isinstance(space, spaces.Space):
        return int(spaces.flatdim(space))
    if not callable(getattr(env, "state", None)):
        return 0
    try:
        env.reset(seed=None)
        return int(np.asarray(env.state(), np.float32).size)
    except (NotImplementedError, AttributeError):
        return 0


class PettingZooEnv(AutoReset):
    """A PettingZoo ParallelEnv adapted to `HostEnv` (see the module docstring)."""

    def __init__(self, env: Any, env_id: str, max_episode_steps: int | None = None) -> None:
        import gymnasium.spaces as spaces

        if not all(hasattr(env, name) for name in ("possible_agents", "reset", "step")) or hasattr(
            env, "agent_iter"
        ):
            raise CmatError(
                f"{env_id}: the factory must return a PettingZoo ParallelEnv, got "
                f"{type(env).__name__} (an AEC env converts with pettingzoo.utils.aec_to_parallel)"
            )
        self.env = env
        self.agents: list[str] = list(env.possible_agents)
        if not self.agents:
            raise CmatError(f"{env_id}: the env has no agents")
        self._obs_spaces = []
        for agent in self.agents:
            space = env.observation_space(agent)
            if isinstance(space, spaces.Dict) and "observation" in space.spaces:
                space = space["observation"]
            self._obs_spaces.append(space)
        self._obs_sizes = [int(spaces.flatdim(space)) for space in self._obs_spaces]
        action_spaces = [env.action_space(agent) for agent in self.agents]
        if all(isinstance(space, spaces.Discrete) for space in action_spaces):
            discrete = True
            self._action_sizes = [int(space.n) for space in action_spaces]
            self._action_starts = [int(space.start) for space in action_spaces]
            low, high = -1.0, 1.0
        elif all(isinstance(space, spaces.Box) for space in action_spaces):
            discrete = False
            self._action_sizes = [int(np.prod(space.shape)) for space in action_spaces]
            self._lows = [space.low.reshape(-1).astype(np.float32) for space in action_spaces]
            self._highs = [space.high.reshape(-1).astype(np.float32) for space in action_spaces]
            self._shapes = [space.shape for space in action_spaces]
            self._dtypes = [space.dtype for space in action_spaces]
            low = float(min(np.min(x) for x in self._lows))
            high = float(max(np.max(x) for x in self._highs))
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
            state_dim=probe_state_dim(env, env_id),
        )
        self._alive: set[str] = set()
        self._steps = 0

    def close(self) -> None:
        """Close the PettingZoo env."""
        close = getattr(self.env, "close", None)
        if close is not None:
            close()

    def _reset(self, seed: int | None) -> tuple[np.ndarray, np.ndarray]:
        result = self.env.reset(seed=seed)
        obs, infos = result if isinstance(result, tuple) else (result, {})
        self._alive = set(getattr(self.env, "agents", None) or self.agents)
        self._steps = 0
        return self._encode(obs, infos or {})

    def _step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, bool, bool]:
        joint = {
            agent: self._env_action(index, actions[index])
            for index, agent in enumerate(self.agents)
            if agent in self._alive
        }
        obs, rewards, terminations, truncations, infos = self.env.step(joint)
        self._steps += 1
        for agent in list(self._alive):
            if terminations.get(agent, False) or truncations.get(agent, False):
                self._alive.discard(agent)
        live = getattr(self.env, "agents", None)
        done = not self._alive or (live is not None and len(live) == 0)
        done = done or self._steps >= self.spec.max_episode_steps
        reward = float(np.mean([float(r) for r in rewards.values()])) if rewards else 0.0
        won = any(bool(info.get("won", False)) for info in (infos or {}).values()
                  if isinstance(info, dict))
        obs_array, mask = self._encode(obs, infos or {})
        return obs_array, mask, reward, done, won

    def _global_state(self) -> np.ndarray:
        if self.spec.state_dim == 0:
            return np.zeros(0, np.float32)
        state = np.asarray(self.env.state(), np.float32).reshape(-1)
        if state.size != self.spec.state_dim:
            raise CmatError(
                f"{self.spec.env_id}: state() returned {state.size} values, expected "
                f"{self.spec.state_dim}"
            )
        return state

    def _active(self) -> np.ndarray:
        """The agents still in the episode (`possible_agents` order)."""
        return np.array([agent in self._alive for agent in self.agents], bool)

    def _env_action(self, index: int, action: np.ndarray) -> Any:
        if self.spec.discrete:
            return int(action) + self._action_starts[index]
        size = self._action_sizes[index]
        own = np.asarray(action, np.float32)[:size]
        clipped = np.clip(own, self._lows[index], self._highs[index])
        return clipped.reshape(self._shapes[index]).astype(self._dtypes[index])

    def _encode(self, obs: dict[str, Any], infos: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        import gymnasium.spaces as spaces

        spec = self.spec
        obs_array = np.zeros((spec.num_agents, spec.obs_dim), np.float32)
        mask = np.zeros((spec.num_agents, spec.action_dim), bool)
        for index, agent in enumerate(self.agents):
            size = self._action_sizes[index]
            if agent not in self._alive or agent not in obs:
                mask[index, 0 if spec.discrete else slice(None)] = True
                continue
            value = obs[agent]
            agent_mask = None
            if isinstance(value, dict) and "observation" in value:
                agent_mask = value.get("action_mask")
                value = value["observation"]
            info = infos.get(agent)
            if agent_mask is None and isinstance(info, dict):
                agent_mask = info.get("action_mask")
            flat = spaces.flatten(self._obs_spaces[index], value)
            obs_array[index, : self._obs_sizes[index]] = flat
            if not spec.discrete:
                mask[index] = True
            elif agent_mask is None:
                mask[index, :size] = True
            else:
                mask[index, :size] = np.asarray(agent_mask, bool).reshape(-1)[:size]
                if not mask[index].any():
                    mask[index, 0] = True
        return obs_array, mask
