"""JaxMARL environments (SMAX, MPE simple_spread) adapted to the `MarlEnv` protocol.

Per-agent dicts become arrays stacked in `env.agents` order, and the team reward is the mean of
the agents' rewards: SMAX gives every ally the same reward, so the mean is that reward;
simple_spread mixes a shared coverage reward with per-agent collision penalties (`local_ratio`).
The adapters call `step_env` and reset automatically themselves, so `won` is read from the
terminal state before it is replaced by the next episode's first state.

JaxMARL ends an episode on the transition taken at `step == max_steps`, so episodes last up to
`max_steps + 1` transitions; `EnvSpec.max_episode_steps` is that true length.
"""

from __future__ import annotations

import contextlib
import inspect
import io
import re
import sys
from collections.abc import Callable, Iterable
from functools import partial
from typing import Any, cast
from unittest import mock

import jax
import jax.numpy as jnp

from cmat.envs.autoreset import auto_reset
from cmat.envs.protocol import EnvSpec, TimeStep
from cmat.envs.suites import choose

# JaxMARL prints while importing, after its brax probe rebinds sys.stdout/stderr to
# sys.__stdout__/__stderr__; patching those keeps the prints quiet and the streams as they were.
with (
    contextlib.redirect_stdout(io.StringIO()) as _quiet,
    mock.patch.multiple(sys, __stdout__=_quiet, __stderr__=sys.stderr),
):
    from jaxmarl.environments.mpe import SimpleSpreadMPE
    from jaxmarl.environments.multi_agent_env import MultiAgentEnv
    from jaxmarl.environments.smax import SMAX, HeuristicEnemySMAX, map_name_to_scenario
    from jaxmarl.environments.smax.smax_env import MAP_NAME_TO_SCENARIO, Scenario

    from cmat.envs import smax_healer

SMAX_SCENARIOS = (*MAP_NAME_TO_SCENARIO, *smax_healer.SCENARIOS)
"""Every scenario JaxMARL's SMAX defines, and the healer scenarios of `cmat.envs.smax_healer`."""

MARINE_TEAM = re.compile(r"([1-9][0-9]{0,2})m")
"""`Nm` beyond SMAX's own maps: N marines against N (N ≤ 999), built with SMAX's scenario API
as its 3m, 8m and 25m are, e.g. for measuring how training scales with the team
(benchmarks/agent_scaling.py)."""


def smax_scenario(name: str) -> Any:
    """SMAX's scenario `name`, or a marine team `Nm` (`MARINE_TEAM`); None for neither."""
    if name in MAP_NAME_TO_SCENARIO:
        return map_name_to_scenario(name)
    match = MARINE_TEAM.fullmatch(name)
    return None if match is None else marine_team(int(match.group(1)))


def marine_team(n: int) -> Any:
    """N marines (SMAX unit type 0) against N, as SMAX builds 3m, 8m and 25m."""
    return Scenario(jnp.zeros((2 * n,), dtype=jnp.uint8), n, n, False, False)

_SMAX_FIXED = {
    "env_kwargs", "scenario", "num_allies", "num_enemies", "action_type",
    "smacv2_position_generation", "smacv2_unit_type_generation",
}
SMAX_OPTIONS = tuple(sorted(
    (inspect.signature(SMAX).parameters.keys() | inspect.signature(HeuristicEnemySMAX).parameters)
    - _SMAX_FIXED
))
"""Keyword arguments passed through to `HeuristicEnemySMAX` (those the scenario or the discrete
action interface fix are left out)."""

MPE_OPTIONS = ("num_agents", "num_landmarks", "local_ratio", "max_steps", "dt")
"""Keyword arguments passed through to `SimpleSpreadMPE`."""


def stack_padded(per_agent: dict[str, jax.Array], agents: list[str], sizes: list[int]) -> jax.Array:
    """[n_agents, max(sizes)] float32: each agent's array flattened (`sizes[i]` entries) and
    zero-padded to the largest."""
    width = max(sizes)
    return jnp.stack([
        jnp.pad(jnp.ravel(per_agent[agent]).astype(jnp.float32), (0, width - size))
        for agent, size in zip(agents, sizes)
    ])


class JaxMarlEnv:
    """A discrete-action JaxMARL environment with every action always available and no win.

    Subclasses adapt other JaxMARL environments by overriding the conversions: `_obs`,
    `_agent_actions`, `_action_mask`, `_won`, `_alive` and `_global_state`; `reset`, `step`
    (with its automatic reset) and `step_in_episode` stay as they are."""

    def __init__(
        self,
        env_id: str,
        env: MultiAgentEnv,
        has_win_rate: bool = False,
        has_global_state: bool = False,
    ) -> None:
        self.env = env
        agent = env.agents[0]
        self.has_global_state = has_global_state
        state_dim = 0
        if has_global_state:
            obs_shapes, _ = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
            state_dim = int(obs_shapes["world_state"].shape[-1])
        self.spec = EnvSpec(
            env_id=env_id,
            num_agents=len(env.agents),
            obs_dim=env.observation_spaces[agent].shape[0],
            action_dim=env.action_spaces[agent].n,
            discrete=True,
            # every JaxMARL environment sets max_steps; MultiAgentEnv does not declare it
            max_episode_steps=cast(Any, env).max_steps + 1,
            has_win_rate=has_win_rate,
            state_dim=state_dim,
        )

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]:
        """Start an episode."""
        obs, state = self.env.reset(key)
        false = jnp.asarray(False)
        return state, TimeStep(
            self._obs(obs), self._action_mask(state), jnp.float32(0.0), false, false,
            self._alive(state, None), self._global_state(obs, state),
        )

    def step(self, key: jax.Array, state: Any, actions: jax.Array) -> tuple[Any, TimeStep]:
        """Take joint `actions` [n_agents]; on `done`, return the next episode's first state."""
        step_key, reset_key = jax.random.split(key)
        return auto_reset(*self.step_in_episode(step_key, state, actions), *self.reset(reset_key))

    def step_in_episode(
        self, key: jax.Array, state: Any, actions: jax.Array
    ) -> tuple[Any, TimeStep]:
        """`step` without the automatic reset: after the last step of an episode, the state and
        observation are its terminal ones (what a renderer draws last)."""
        obs, next_state, rewards, dones, infos = self.env.step_env(
            key, state, self._agent_actions(actions)
        )
        done = jnp.asarray(dones["__all__"], bool)
        reward = jnp.mean(self._stack(rewards)).astype(jnp.float32)
        return next_state, TimeStep(
            self._obs(obs), self._action_mask(next_state), reward, done,
            done & self._won(next_state, infos), self._alive(next_state, dones),
            self._global_state(obs, next_state),
        )

    def _agent_actions(self, actions: jax.Array) -> dict[str, jax.Array]:
        return {agent: actions[i] for i, agent in enumerate(self.env.agents)}

    def _stack(self, per_agent: dict[str, jax.Array]) -> jax.Array:
        return jnp.stack([per_agent[agent] for agent in self.env.agents])

    def _obs(self, per_agent: dict[str, jax.Array]) -> jax.Array:
        return self._stack(per_agent).astype(jnp.float32)

    def _action_mask(self, state: Any) -> jax.Array:
        return jnp.ones((self.spec.num_agents, self.spec.action_dim), dtype=bool)

    def _won(self, state: Any, infos: dict[str, Any]) -> jax.Array:
        """Whether the episode that ends in `state` is won (`infos`: `step_env`'s)."""
        return jnp.asarray(False)

    def _alive(self, state: Any, dones: dict[str, jax.Array] | None) -> jax.Array:
        """[n_agents] bool: which agents act in `state` (`dones`: `step_env`'s, None at reset)."""
        return jnp.ones(self.spec.num_agents, dtype=bool)

    def _global_state(self, obs: dict[str, jax.Array], state: Any) -> jax.Array:
        if not self.has_global_state:
            return jnp.zeros(0, jnp.float32)
        return jnp.ravel(obs["world_state"]).astype(jnp.float32)


class SmaxEnv(JaxMarlEnv):
    """SMAX against JaxMARL's heuristic enemy; `won` is SMAX's won-battle condition.

    The global state is SMAX's world state (every unit's features, `get_world_state`), the input
    of JaxMARL's own MAPPO critic on SMAX (`baselines/MAPPO/mappo_rnn_smax.py`); `alive` is
    `unit_alive` of the allies.

    A battle is won when every enemy is dead and at least one ally is alive (all dead is a draw),
    exactly when SMAX pays its `won_battle_bonus`. Dead allies may only take the stop action.
    """

    env: HeuristicEnemySMAX

    def __init__(self, scenario: str, **kwargs: Any) -> None:
        env: HeuristicEnemySMAX
        if scenario in smax_healer.SCENARIOS:
            env = smax_healer.HeuristicEnemyHealerSMAX(
                scenario=smax_healer.SCENARIOS[scenario], **kwargs
            )
        else:
            env = HeuristicEnemySMAX(scenario=smax_scenario(scenario), **kwargs)
        super().__init__(f"smax:{scenario}", env, has_win_rate=True, has_global_state=True)

    def _action_mask(self, state: Any) -> jax.Array:
        return self._stack(self.env.get_avail_actions(state)).astype(bool)

    def _alive(self, state: Any, dones: dict[str, jax.Array] | None) -> jax.Array:
        alive: jax.Array = state.state.unit_alive
        return alive[: self.env.num_allies]

    def _won(self, state: Any, infos: dict[str, Any]) -> jax.Array:
        alive, n_allies = state.state.unit_alive, self.env.num_allies
        return jnp.any(alive[:n_allies]) & ~jnp.any(alive[n_allies:])


def simple_spread(**kwargs: Any) -> JaxMarlEnv:
    """MPE simple_spread (v3) with discrete actions."""
    return JaxMarlEnv("mpe:simple_spread", SimpleSpreadMPE(**kwargs))


MPE_ENVS = {"simple_spread": simple_spread}
"""MPE environment name → factory."""


def build_smax(env_id: str, name: str) -> tuple[Callable[..., JaxMarlEnv], Iterable[str]]:
    """The smax suite's builder (cmat.envs.suites.Builder): a SMAX scenario or an `Nm` team."""
    scenario = (name if MARINE_TEAM.fullmatch(name)
                else choose("SMAX scenario", name, SMAX_SCENARIOS,
                            also="Nm (N marines a side, 1 <= N <= 999)"))
    return partial(SmaxEnv, scenario), SMAX_OPTIONS


def build_mpe(env_id: str, name: str) -> tuple[Callable[..., JaxMarlEnv], Iterable[str]]:
    """The mpe suite's builder (cmat.envs.suites.Builder)."""
    return MPE_ENVS[choose("MPE environment", name, MPE_ENVS)], MPE_OPTIONS
