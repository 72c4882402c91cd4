"""Host environments: simulators stepped in Python, behind `cmat.envs.host.protocol.HostEnv`.

`make_host_env("PREFIX:NAME", **options)` builds one of
- `pettingzoo:package.module:factory`: any PettingZoo ParallelEnv the factory returns,
- `mamujoco:SCENARIO-CONF`: Multi-Agent MuJoCo (gymnasium-robotics; extra `[mujoco]`),
- `grf:SCENARIO`: Google Research Football academy scenarios (gfootball; scripts/install_grf.sh).

They do not satisfy the in-graph `MarlEnv` protocol: `cmat.runners.host.HostTrainer` steps them
(`cmat.envs.host.pool`) and runs the same jitted policy and update as the in-graph trainer.
Suites are imported on first use.
"""

from __future__ import annotations

from typing import Any

from cmat.config import NONFINITE_POLICIES
from cmat.envs.host.protocol import AutoReset, HostAgentIdWrapper, HostEnv, HostTimeStep
from cmat.envs.suites import is_host_env, registry, suite_of
from cmat.errors import CmatError

__all__ = [
    "DEFAULT_WORKERS", "HostEnv", "HostTimeStep", "is_host_env", "make_host_env",
]


DEFAULT_WORKERS = {"pettingzoo": 0, "mamujoco": 0, "grf": 0}
"""Worker processes per suite when the config leaves `host_workers` unset (0: in-process),
picked by benchmarks/host_throughput.py on this project's 2-core machines (docs/speed.md,
"Host environments"): in-process was as fast or faster for HalfCheetah 6x1 and GRF 3 vs 1, because
the workers compete with XLA for the same two cores. With spare cores, GRF (7 ms a step) gains
from `host_workers`."""


def make_host_env(
    env_id: str, agent_id: bool = False, seed: int | None = None, nonfinite: str = "error",
    **kwargs: Any
) -> HostEnv:
    """Build the host env `env_id` of any host suite in the registry (cmat.envs.suites);
    `agent_id` appends one-hot agent ids to observations; `seed` seeds simulators that take
    their seed when built (GRF; others seed at `reset`); `nonfinite` ("error" or "warn",
    `TrainConfig.host_nonfinite`) says what a NaN or infinite observation, reward or state does
    (`cmat.envs.host.protocol.AutoReset`).

    Raises CmatError for an unknown prefix, an in-graph suite's id or a `nonfinite` value."""
    if nonfinite not in NONFINITE_POLICIES:
        raise CmatError(f"nonfinite must be one of {', '.join(NONFINITE_POLICIES)}, "
                        f"got {nonfinite!r}")
    suite = suite_of(env_id)
    if not suite.host:
        hosts = [prefix for prefix, entry in registry().items() if entry.host]
        raise CmatError(f"{env_id} is not a host environment; host suites: {', '.join(hosts)}")
    factory, _ = suite.build(env_id)
    env: AutoReset = factory(seed=seed or 0, **kwargs)
    env.nonfinite = nonfinite
    return HostAgentIdWrapper(env) if agent_id else env


def default_workers(env_id: str) -> int:
    """The measured default number of worker processes for `env_id`'s suite."""
    return DEFAULT_WORKERS.get(env_id.partition(":")[0], 0)
