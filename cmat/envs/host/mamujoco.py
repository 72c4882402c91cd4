"""`mamujoco:SCENARIO-CONF`: Multi-Agent MuJoCo through gymnasium-robotics (extra `[mujoco]`).

CONF is one of gymnasium-robotics' built-in factorizations of SCENARIO (`HalfCheetah-6x1`,
`Ant-2x4d`, `Humanoid-9|8`, ...), `Kx1` with K the scenario's number of joints (one joint per
agent, built here from `get_parts_and_edges`: the paper's `Ant-8x1` and `Walker2d-6x1`), or NxM
for the ManySegment scenarios. The env is a PettingZoo ParallelEnv, so the PettingZoo adapter
does the rest: observations (different sizes per agent) zero-padded to the largest, actions
mapped from [-1, 1] onto each joint's Box bounds (±0.4 for HalfCheetah), the shared reward as
the team reward, 1000-step episodes, no win rate.
Keyword arguments go to `mamujoco_v1.parallel_env` (e.g. `agent_obsk`).
"""

from __future__ import annotations

import contextlib
import io
import logging
import re
import warnings
from collections.abc import Callable
from typing import Any

from cmat.envs.host.pettingzoo_env import PettingZooEnv
from cmat.errors import CmatError, SuiteUnavailable

BUILT_IN: dict[str, tuple[str, ...]] = {
    "HalfCheetah": ("2x3", "6x1"),
    "Ant": ("2x4", "2x4d", "4x2"),
    "Hopper": ("3x1",),
    "Humanoid": ("9|8",),
    "HumanoidStandup": ("9|8",),
    "Reacher": ("2x1",),
    "Pusher": ("3p",),
    "Swimmer": ("2x1",),
    "Walker2d": ("2x3",),
}
"""gymnasium-robotics 1.4's factorizations of each scenario (its `get_parts_and_edges`).
CoupledHalfCheetah is left out: its observation fails to build under MuJoCo 3 (IndexError in
gymnasium-robotics 1.4.2's tendon Jacobian read)."""

JOINTS = {
    "HalfCheetah": 6, "Ant": 8, "Hopper": 3, "Humanoid": 17, "HumanoidStandup": 17,
    "Reacher": 2, "Pusher": 7, "Swimmer": 2, "Walker2d": 6,
}
"""Actuated joints of each scenario: `Kx1` with this K gives one joint per agent."""

MANY_SEGMENT = ("ManySegmentSwimmer", "ManySegmentAnt")
"""Scenarios whose CONF is NxM: N agents of M segments each."""

SCENARIOS = (*BUILT_IN, *MANY_SEGMENT)

log = logging.getLogger("cmat.host")


def factorizations(scenario: str) -> list[str]:
    """Every CONF accepted for `scenario` (ManySegment scenarios take any NxM)."""
    if scenario in MANY_SEGMENT:
        return ["NxM"]
    one_per_joint = f"{JOINTS[scenario]}x1"
    built_in = list(BUILT_IN[scenario])
    return built_in if one_per_joint in built_in else [*built_in, one_per_joint]


def parse(env_id: str, name: str) -> tuple[str, str]:
    """SCENARIO and CONF of `mamujoco:SCENARIO-CONF`, checked (CmatError otherwise)."""
    scenario, _, conf = name.partition("-")
    if scenario not in SCENARIOS:
        raise CmatError(
            f"unknown MaMuJoCo scenario {scenario!r} in {env_id!r} (ids are "
            f"mamujoco:SCENARIO-CONF); available: {', '.join(SCENARIOS)}"
        )
    if scenario in MANY_SEGMENT:
        match = re.fullmatch(r"(\d+)x(\d+)", conf)
        if match is None or int(match[1]) < 1 or int(match[2]) < 1:
            raise CmatError(
                f"unknown MaMuJoCo factorization {conf!r} for {scenario}; expected NxM "
                f"(N agents of M segments, e.g. {scenario}-2x3)"
            )
        return scenario, conf
    if not conf:
        raise CmatError(
            f"no factorization in {env_id!r} (ids are mamujoco:SCENARIO-CONF); available for "
            f"{scenario}: {', '.join(factorizations(scenario))}"
        )
    if conf not in factorizations(scenario):
        raise CmatError(
            f"unknown MaMuJoCo factorization {conf!r} for {scenario}; available: "
            f"{', '.join(factorizations(scenario))}"
        )
    return scenario, conf


def one_joint_per_agent(scenario: str) -> dict[str, Any]:
    """A custom factorization: every actuated joint of `scenario` is one agent, with the graph
    edges and global nodes of the scenario's built-in factorization."""
    from gymnasium_robotics.envs.multiagent_mujoco.obsk import get_parts_and_edges

    parts, edges, global_nodes = get_parts_and_edges(scenario, BUILT_IN[scenario][0])
    joints = [node for part in parts for node in part]
    return {"partition": [(joint,) for joint in joints], "edges": edges, "globals": global_nodes}


def import_mamujoco() -> Any:
    """gymnasium-robotics' `mamujoco_v1`, or a CmatError saying how to install it."""
    try:
        import mujoco

        # its import prints a notice about Adroit hand rewards to stderr: irrelevant here
        with warnings.catch_warnings(), contextlib.redirect_stderr(io.StringIO()):
            warnings.simplefilter("ignore")
            from gymnasium_robotics import mamujoco_v1
    except ImportError as error:
        raise SuiteUnavailable(
            f"MaMuJoCo needs gymnasium-robotics and mujoco ({error}); install them with "
            f"pip install -e '.[mujoco]'"
        ) from None
    # MuJoCo's own warning handler appends to MUJOCO_LOG.TXT in the working directory (the
    # HalfCheetah model warns on every load that `settotalmass` is deprecated): log them instead.
    mujoco.set_mju_user_warning(lambda message: log.debug("MuJoCo: %s", message))
    return mamujoco_v1


def make_mamujoco_env(env_id: str, name: str, **kwargs: Any) -> PettingZooEnv:
    """The MaMuJoCo env `name` (SCENARIO-CONF) behind the host protocol."""
    scenario, conf = parse(env_id, name)
    mamujoco_v1 = import_mamujoco()
    if scenario not in MANY_SEGMENT and conf not in BUILT_IN[scenario]:
        kwargs = {**kwargs, "agent_factorization": one_joint_per_agent(scenario)}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            env = mamujoco_v1.parallel_env(scenario, conf, **kwargs)
    except TypeError as error:
        raise CmatError(f"bad option for {env_id}: {error}") from None
    limit = getattr(getattr(env.single_agent_env, "spec", None), "max_episode_steps", None)
    return PettingZooEnv(env, env_id, max_episode_steps=limit or 1000)


def build(env_id: str, name: str) -> tuple[Callable[..., PettingZooEnv], None]:
    """The mamujoco suite's builder (cmat.envs.suites.Builder); the simulator is seeded at
    reset, so the factory leaves `seed` alone."""
    return lambda seed, **options: make_mamujoco_env(env_id, name, **options), None
