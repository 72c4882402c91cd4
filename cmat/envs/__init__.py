"""Environment registry: `make_env("PREFIX:NAME", **options)` builds any supported `MarlEnv`.

Each suite is one entry of the registry (cmat.envs.suites), whose builder is imported on first
use, so matrix games never pay for importing JaxMARL, and JAX itself is first imported when an
environment is built: config and spec errors are reported without it.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

from cmat.envs.protocol import EnvSpec, MarlEnv, TimeStep
from cmat.envs.suites import is_host_env, suite_of
from cmat.errors import CmatError, SuiteUnavailable

if TYPE_CHECKING:
    import jax

__all__ = [
    "AgentIdWrapper", "EnvSpec", "MarlEnv", "TimeStep", "make_env", "probe_env",
]


class AgentIdWrapper:
    """Appends each agent's one-hot id to its observation."""

    def __init__(self, env: MarlEnv) -> None:
        self.env = env
        self.spec = dataclasses.replace(
            env.spec, obs_dim=env.spec.obs_dim + env.spec.num_agents, agent_id=True
        )

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]:
        """Start an episode."""
        state, timestep = self.env.reset(key)
        return state, self._with_id(timestep)

    def step(self, key: jax.Array, state: Any, actions: jax.Array) -> tuple[Any, TimeStep]:
        """Step the wrapped environment."""
        state, timestep = self.env.step(key, state, actions)
        return state, self._with_id(timestep)

    def _with_id(self, timestep: TimeStep) -> TimeStep:
        import jax.numpy as jnp

        ids = jnp.eye(self.env.spec.num_agents, dtype=timestep.obs.dtype)
        return timestep._replace(obs=jnp.concatenate([timestep.obs, ids], axis=-1))


def make_env(env_id: str, agent_id: bool = False, **kwargs: Any) -> MarlEnv:
    """Build the in-graph environment `env_id` (PREFIX:NAME) of any suite in the registry
    (cmat.envs.suites: `matrix:NAME`, `smax:SCENARIO`, `mpe:NAME`, `jumanji:TASK`,
    `mabrax:TASK`, `dispatch:CITY-N-LEVEL`, a user's `jax:package.module:factory`, and the
    suites installed packages add) with the options `kwargs`; `agent_id` appends one-hot agent
    ids.

    Raises CmatError for an unknown prefix, name or option and for a host suite's id,
    SuiteUnavailable where the suite needs a package that is not installed."""
    suite = suite_of(env_id)
    if suite.host:
        raise CmatError(
            f"{env_id} is a host environment: build it with cmat.envs.host.make_host_env "
            f"(the CLI's trainer does); make_env builds in-graph JAX environments only"
        )
    factory, options = suite.build(env_id)
    if options is not None:
        unknown = sorted(set(kwargs) - set(options))
        if unknown:
            raise CmatError(
                f"unknown option {unknown[0]!r} for {env_id}; accepted: "
                f"{', '.join(['agent_id', *options])}"
            )
    env: MarlEnv = factory(**kwargs)
    return AgentIdWrapper(env) if agent_id else env


def probe_env(env_id: str, env_kwargs: dict[str, Any]) -> tuple[int | None, str | None]:
    """(number of agents, None) where `env_id` builds here (a JAX or a host environment, closed
    again), or (None, why not) where its suite cannot be built on this machine
    (`SuiteUnavailable`, or a suite's own import or build failure).

    Raises CmatError for an id, option or option value that is wrong on any machine (an unknown
    scenario, a typo), so that an experiment stops on it rather than skipping the task."""
    try:
        if is_host_env(env_id):
            from cmat.envs.host import make_host_env

            env: Any = make_host_env(env_id, **env_kwargs)
        else:
            env = make_env(env_id, **env_kwargs)
        num_agents = int(env.spec.num_agents)
        close = getattr(env, "close", None)
        if callable(close):
            close()
        return num_agents, None
    except SuiteUnavailable as error:
        return None, str(error)
    except CmatError:
        raise
    except Exception as error:  # a suite's own import or build failure: report, don't crash
        return None, f"{type(error).__name__}: {error}".splitlines()[0]
