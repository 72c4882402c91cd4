"""Jumanji's Robot Warehouse (RWARE) and Level-Based Foraging (LBF) adapted to the `MarlEnv`
protocol: `jumanji:rware-TASK` and `jumanji:lbf-TASK`.

The tasks are Mava's scenarios (instadeepai/Mava, `mava/configs/env/scenario/*.yaml`, the
generator parameters of each task, and `mava/configs/env/{rware,lbf}.yaml` for the time limits:
500 steps for RWARE, 100 for LBF), built the way Mava's `mava/utils/make_env.py`
(`make_jumanji_env`) builds them: Jumanji's `RandomGenerator` of the environment with the
scenario's parameters.

Each agent's observation is Jumanji's `agents_view` row flattened to float32 (RWARE: the
sensor-range view; LBF: the `VectorObserver` vector of agents' and foods' positions and levels),
and the action mask is Jumanji's own. The team reward is the sum of the agents' rewards, as in
Mava's `mava/wrappers/jumanji.py`: RWARE pays one shared reward, +1 per requested shelf
delivered, which `RwareWrapper` repeats to every agent; LBF pays each agent its share of the food
it helped load, which `LbfWrapper.aggregate_rewards` sums into one team reward (its default,
`use_individual_rewards: False`). Mava's `episode_return` (`mava/wrappers/episode_metrics.py`,
the mean over agents of those repeated team rewards) is then exactly cmat's episode return, the
metric of both suites; a mean over LBF's agents would divide it by the team size. Neither
environment has a win condition or a global state.

An episode ends when Jumanji's time step is the last one: the time limit (`time_limit`
transitions), a collision in RWARE or every food eaten in LBF. `step` then resets as
`cmat.envs.jaxmarl_envs.JaxMarlEnv` does: the next episode's first observation and action mask,
with the reward and `done` of the transition that ended the episode.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Iterable
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
from jumanji.env import Environment
from jumanji.environments.routing.lbf.env import LevelBasedForaging
from jumanji.environments.routing.lbf.generator import RandomGenerator as LbfGenerator
from jumanji.environments.routing.robot_warehouse.env import RobotWarehouse
from jumanji.environments.routing.robot_warehouse.generator import (
    RandomGenerator as RwareGenerator,
)
from jumanji.types import TimeStep as JumanjiTimeStep

from cmat.envs.autoreset import auto_reset
from cmat.envs.protocol import EnvSpec, TimeStep
from cmat.envs.suites import choose


def _rware(rows: int, columns: int, agents: int, queue: int) -> dict[str, int]:
    return {"column_height": 8, "shelf_rows": rows, "shelf_columns": columns,
            "num_agents": agents, "sensor_range": 1, "request_queue_size": queue}


def _lbf(grid: int, fov: int, agents: int, food: int, coop: bool) -> dict[str, Any]:
    return {"grid_size": grid, "fov": fov, "num_agents": agents, "num_food": food,
            "max_agent_level": 2, "force_coop": coop}


RWARE_SCENARIOS: dict[str, dict[str, int]] = {
    "tiny-2ag": _rware(1, 3, 2, 2),
    "tiny-2ag-hard": _rware(1, 3, 2, 1),
    "tiny-4ag": _rware(1, 3, 4, 4),
    "tiny-4ag-easy": _rware(1, 3, 4, 8),
    "tiny-4ag-hard": _rware(1, 3, 4, 2),
    "small-4ag": _rware(2, 3, 4, 4),
    "small-4ag-hard": _rware(2, 3, 4, 2),
    "medium-4ag": _rware(2, 5, 4, 4),
    "medium-4ag-hard": _rware(2, 5, 4, 2),
    "medium-6ag": _rware(2, 5, 6, 6),
    "large-4ag": _rware(3, 5, 4, 4),
    "large-4ag-hard": _rware(3, 5, 4, 2),
    "large-8ag": _rware(3, 5, 8, 8),
    "large-8ag-hard": _rware(3, 5, 8, 4),
    "xlarge-4ag": _rware(4, 5, 4, 4),
    "xlarge-4ag-hard": _rware(4, 5, 4, 2),
}
"""Mava's RWARE scenarios → Jumanji `RobotWarehouse` `RandomGenerator` parameters (column height
8 and sensor range 1 in all of them; shelf rows × columns: tiny 1×3, small 2×3, medium 2×5,
large 3×5, xlarge 4×5)."""

LBF_SCENARIOS: dict[str, dict[str, Any]] = {
    "2s-8x8-2p-2f-coop": _lbf(8, 2, 2, 2, True),
    "8x8-2p-2f-coop": _lbf(8, 8, 2, 2, True),
    "2s-10x10-3p-3f": _lbf(10, 2, 3, 3, False),
    "10x10-3p-3f": _lbf(10, 10, 3, 3, False),
    "15x15-3p-5f": _lbf(15, 15, 3, 5, False),
    "15x15-4p-3f": _lbf(15, 15, 4, 3, False),
    "15x15-4p-5f": _lbf(15, 15, 4, 5, False),
    "15x15-4p-5f-coop": _lbf(15, 15, 4, 5, True),
    "2s-15x15-4p-5f-coop": _lbf(15, 2, 4, 5, True),
    "20x20-3p-5f-coop": _lbf(20, 20, 3, 5, True),
    "2s-20x20-3p-5f-coop": _lbf(20, 2, 3, 5, True),
    "20x20-4p-5f-coop": _lbf(20, 20, 4, 5, True),
    "2s-20x20-4p-5f-coop": _lbf(20, 2, 4, 5, True),
}
"""Mava's LBF scenarios → Jumanji `LevelBasedForaging` `RandomGenerator` parameters: `2s` is a
field of view of 2 cells (else the whole grid), `NxN` the grid, `Pp` the agents, `Ff` the food,
`coop` that every food needs the whole team to load it; agents' levels go up to 2."""


class JumanjiEnv:
    """A Jumanji multi-agent environment whose observation holds `agents_view` [n_agents, ...]
    and `action_mask` [n_agents, n_actions] and whose reward is per agent or shared.

    The state is Jumanji's state as a flat {path: array} dict (`jax.tree_util.keystr` paths, e.g.
    `.agents.position.x`), which cmat's checkpoints (flax's msgpack state dicts) store; Jumanji's
    chex dataclasses are unknown to flax serialisation."""

    def __init__(self, env_id: str, env: Environment[Any, Any, Any], time_limit: int) -> None:
        self.env = env
        state, first = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
        paths, self._treedef = jax.tree_util.tree_flatten_with_path(state)
        self._paths = [jax.tree_util.keystr(path) for path, _ in paths]
        num_agents, *view = first.observation.agents_view.shape
        self.spec = EnvSpec(
            env_id=env_id,
            num_agents=num_agents,
            obs_dim=math.prod(view),
            action_dim=first.observation.action_mask.shape[-1],
            discrete=True,
            max_episode_steps=time_limit,
            has_win_rate=False,
        )

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]:
        """Start an episode."""
        state, timestep = self.env.reset(key)
        false = jnp.asarray(False)
        return self._flat(state), TimeStep(
            self._obs(timestep), self._action_mask(timestep), jnp.float32(0.0), false, false,
            self._alive(), jnp.zeros(0, jnp.float32),
        )

    def step(self, key: jax.Array, state: Any, actions: jax.Array) -> tuple[Any, TimeStep]:
        """Take joint `actions` [n_agents]; on `done`, return the next episode's first state.

        As in `JaxMarlEnv.step`, the second key of `jax.random.split(key)` draws the next
        episode (Jumanji's `step` takes no key: its randomness is in `state`)."""
        step_key, reset_key = jax.random.split(key)
        return auto_reset(*self.step_in_episode(step_key, state, actions), *self.reset(reset_key))

    def step_in_episode(
        self, key: jax.Array, state: Any, actions: jax.Array
    ) -> tuple[Any, TimeStep]:
        """`step` without the automatic reset (`key` unused: Jumanji's randomness is in the
        state)."""
        next_state, timestep = self.env.step(self.jumanji_state(state), actions.astype(jnp.int32))
        return self._flat(next_state), TimeStep(
            obs=self._obs(timestep),
            action_mask=self._action_mask(timestep),
            reward=jnp.sum(timestep.reward).astype(jnp.float32),
            done=timestep.last(),
            won=jnp.asarray(False),
            alive=self._alive(),
            global_state=jnp.zeros(0, jnp.float32),
        )

    def jumanji_state(self, state: dict[str, jax.Array]) -> Any:
        """Jumanji's own state (what its `step` and `render` take) from this adapter's state."""
        return jax.tree.unflatten(self._treedef, [state[path] for path in self._paths])

    def _flat(self, state: Any) -> dict[str, jax.Array]:
        return dict(zip(self._paths, jax.tree.leaves(state)))

    def _obs(self, timestep: JumanjiTimeStep[Any]) -> jax.Array:
        view: jax.Array = timestep.observation.agents_view
        return view.reshape(self.spec.num_agents, -1).astype(jnp.float32)

    def _action_mask(self, timestep: JumanjiTimeStep[Any]) -> jax.Array:
        mask: jax.Array = timestep.observation.action_mask
        return mask.astype(bool)

    def _alive(self) -> jax.Array:
        return jnp.ones(self.spec.num_agents, dtype=bool)


def rware(scenario: str, time_limit: int = 500) -> JumanjiEnv:
    """Robot Warehouse `scenario` (`RWARE_SCENARIOS`): observation [n_agents, 66] with sensor
    range 1, 5 actions (no-op, forward, left, right, toggle load)."""
    env = RobotWarehouse(RwareGenerator(**RWARE_SCENARIOS[scenario]), time_limit=time_limit)
    return JumanjiEnv(f"jumanji:rware-{scenario}", env, time_limit)


def lbf(
    scenario: str, time_limit: int = 100, normalize_reward: bool = True, penalty: float = 0.0
) -> JumanjiEnv:
    """Level-Based Foraging `scenario` (`LBF_SCENARIOS`): observation [n_agents, 3 × (food +
    agents)], 6 actions (no-op, up, down, left, right, load). With `normalize_reward` (Jumanji's
    and Mava's default) the team's return is the fraction of the food levels loaded, at most 1;
    `penalty` is taken from every agent's reward for each food that agents try to load but
    whose level exceeds theirs together."""
    env = LevelBasedForaging(
        LbfGenerator(**LBF_SCENARIOS[scenario]), time_limit=time_limit,
        normalize_reward=normalize_reward, penalty=penalty,
    )
    return JumanjiEnv(f"jumanji:lbf-{scenario}", env, time_limit)


TASKS: dict[str, Callable[..., JumanjiEnv]] = {
    **{f"rware-{name}": partial(rware, name) for name in RWARE_SCENARIOS},
    **{f"lbf-{name}": partial(lbf, name) for name in LBF_SCENARIOS},
}
"""Task name (the part of `jumanji:NAME` after the colon) → factory; its keyword arguments are the
options `make_env` accepts for it."""


def build(env_id: str, name: str) -> tuple[Callable[..., JumanjiEnv], Iterable[str]]:
    """The jumanji suite's builder (cmat.envs.suites.Builder)."""
    factory = TASKS[choose("Jumanji task", name, TASKS)]
    return factory, inspect.signature(factory).parameters
