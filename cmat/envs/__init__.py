"""Environment registry: `make_env("PREFIX:NAME", **options)` builds any supported `MarlEnv`.

Suites are imported on first use, so matrix games never pay for importing JaxMARL, and JAX
itself is first imported when an environment is built: config and spec errors are reported
without it.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import inspect
from collections.abc import Callable, Iterable
from functools import partial
from typing import TYPE_CHECKING, Any

from cmat.envs.protocol import EnvSpec, MarlEnv, TimeStep
from cmat.envs.suites import ENV_PREFIXES, HOST_PREFIXES
from cmat.errors import CmatError, SuiteUnavailable

if TYPE_CHECKING:
    import jax

__all__ = [
    "ENV_PREFIXES", "HOST_PREFIXES", "AgentIdWrapper", "EnvSpec", "MarlEnv", "TimeStep", "make_env",
    "probe_env",
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
    """Build `matrix:NAME`, `smax:SCENARIO`, `mpe:NAME`, `jumanji:TASK`, `mabrax:TASK`,
    `dispatch:CITY-N-LEVEL` (`cmat.envs.dispatch`) or a user's `jax:package.module:factory`
    (`cmat.envs.user_jax`, which takes any option its factory takes); `agent_id` appends one-hot
    agent ids."""
    prefix, _, name = env_id.partition(":")
    factory: Callable[..., MarlEnv]
    if prefix == "matrix":
        from cmat.envs import matrix

        factory = matrix.GAMES[_choose("matrix game", name, matrix.GAMES)]
        options: Iterable[str] = inspect.signature(factory).parameters
    elif prefix == "smax":
        from cmat.envs import jaxmarl_envs

        scenario = (name if jaxmarl_envs.MARINE_TEAM.fullmatch(name)
                    else _choose("SMAX scenario", name, jaxmarl_envs.SMAX_SCENARIOS,
                                 also="Nm (N marines a side, 1 <= N <= 999)"))
        factory = partial(jaxmarl_envs.SmaxEnv, scenario)
        options = jaxmarl_envs.SMAX_OPTIONS
    elif prefix == "mpe":
        from cmat.envs import jaxmarl_envs

        factory = jaxmarl_envs.MPE_ENVS[_choose("MPE environment", name, jaxmarl_envs.MPE_ENVS)]
        options = jaxmarl_envs.MPE_OPTIONS
    elif prefix == "jumanji":
        from cmat.envs import jumanji_envs

        factory = jumanji_envs.TASKS[_choose("Jumanji task", name, jumanji_envs.TASKS)]
        options = inspect.signature(factory).parameters
    elif prefix == "mabrax":
        if importlib.util.find_spec("brax") is None:
            raise SuiteUnavailable(
                f"{env_id} needs brax, which is not installed: "
                f"pip install 'brax>=0.14.2,<0.15' (cmat's mabrax extra)"
            )
        from cmat.envs import mabrax_envs

        factory = partial(mabrax_envs.MabraxEnv, _choose("MABrax task", name, mabrax_envs.TASKS))
        options = mabrax_envs.OPTIONS
    elif prefix == "dispatch":
        from cmat.envs import dispatch

        factory = partial(dispatch.make_task, name)
        options = dispatch.OPTIONS
    elif prefix == "jax":
        from cmat.envs.user_jax import make_user_env

        env = make_user_env(env_id, name, **kwargs)
        return AgentIdWrapper(env) if agent_id else env
    elif prefix in HOST_PREFIXES:
        raise CmatError(
            f"{env_id} is a host environment: build it with cmat.envs.host.make_host_env "
            f"(the CLI's trainer does); make_env builds in-graph JAX environments only"
        )
    else:
        raise CmatError(
            f"unknown environment prefix {prefix!r} in {env_id!r} (ids are PREFIX:NAME); "
            f"available: {', '.join(ENV_PREFIXES)}"
        )
    unknown = sorted(set(kwargs) - set(options))
    if unknown:
        raise CmatError(
            f"unknown option {unknown[0]!r} for {env_id}; accepted: "
            f"{', '.join(['agent_id', *options])}"
        )
    env = factory(**kwargs)
    return AgentIdWrapper(env) if agent_id else env


def _choose(kind: str, name: str, available: Iterable[str], also: str = "") -> str:
    if name not in available:
        listed = ", ".join([*available, *([also] if also else [])])
        raise CmatError(f"unknown {kind} {name!r}; available: {listed}")
    return name


def probe_env(env_id: str, env_kwargs: dict[str, Any]) -> tuple[int | None, str | None]:
    """(number of agents, None) where `env_id` builds here (a JAX or a host environment, closed
    again), or (None, why not) where its suite cannot be built on this machine
    (`SuiteUnavailable`, or a suite's own import or build failure).

    Raises CmatError for an id, option or option value that is wrong on any machine (an unknown
    scenario, a typo), so that an experiment stops on it rather than skipping the task."""
    try:
        if env_id.partition(":")[0] in HOST_PREFIXES:
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
