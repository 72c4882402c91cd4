"""`jax:package.module:factory`: a user's own environment written in JAX, stepped inside the
jitted training program as SMAX is (no host round trip per step).

`factory(**env_kwargs)` returns one of:
- a cmat `MarlEnv` (`cmat.envs.protocol`): `spec` (an `EnvSpec`), `reset(key)` and
  `step(key, state, actions)` returning `(state, TimeStep)`, `step` resetting automatically.
  It is used as it is.
- a JaxMARL `MultiAgentEnv` (`agents`, `observation_space(agent)`, `action_space(agent)`,
  `reset`, `step_env`, `max_steps`), adapted by `JaxMarlUserEnv` as cmat's own JaxMARL suites
  are: agents in `env.agents` order; each observation flattened and zero-padded to the largest
  agent's; all `Discrete` actions (different sizes: the missing actions masked out) or all
  `Box` actions with finite bounds (the policy acts in [-1, 1], mapped affinely onto each
  dimension's [low, high]; different sizes: an agent reads the first entries of the padded
  vector); masks from `get_avail_actions(state)` where the class implements it; team reward =
  the mean of the agents' rewards (a shared reward passes through unchanged, as
  `cmat.envs.jaxmarl_envs.JaxMarlEnv` and the PettingZoo adapter do); done =
  `dones["__all__"]`, an agent whose own `dones[agent]` is set is inactive until the episode
  ends; global state = `obs["world_state"]` where `reset` returns one; win rate where
  `step_env`'s infos hold a `"won"` entry (any agent's True counts, read when the episode ends).

Either way the environment is checked before anything runs: `reset` and `step` are traced
abstractly (`jax.eval_shape`: no computation, no compilation) and every array of their returns
is compared with the spec, and `step`'s state with `reset`'s (the rollout's `lax.scan` carries
it); a JaxMARL env's `step_env` observations must keep `reset`'s agents and sizes (and its
world state), and `get_avail_actions` must give each agent one entry per action. A mismatch,
or an exception raised while tracing the user's code, is a one-line `CmatError` naming the id,
the function and what was found.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Callable
from functools import partial
from typing import Any, cast

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np

from cmat.envs.factory import load_factory
from cmat.envs.jaxmarl_envs import JaxMarlEnv, stack_padded
from cmat.envs.protocol import EnvSpec, MarlEnv, TimeStep
from cmat.errors import CmatError

# isort: split
# After cmat.envs.jaxmarl_envs, which imports JaxMARL with its import-time prints silenced.
from jaxmarl.environments.multi_agent_env import MultiAgentEnv
from jaxmarl.environments.spaces import Box, Discrete

DEFAULT_MAX_STEPS = 1000
"""The evaluation's episode limit where a JaxMARL environment names no `max_steps`."""


def make_user_env(env_id: str, target: str, **kwargs: Any) -> MarlEnv:
    """Call the factory named by `target` (`package.module:factory`) with `kwargs`; adapt a
    JaxMARL environment, check either kind (module docstring). Raises CmatError (or
    SuiteUnavailable where the module cannot be imported)."""
    factory = load_factory(env_id, target)
    if jnp.zeros(()).dtype == jnp.float64:
        raise CmatError(
            f"{env_id}: 64-bit JAX is on (jax_enable_x64, e.g. set by the environment's module "
            f"when imported); cmat trains in float32: leave jax_enable_x64 off")
    try:
        built = factory(**kwargs)
    except Exception as error:  # the user's factory: any error is a bad id or bad options
        raise CmatError(f"{env_id}: the factory raised {type(error).__name__}: {error}") from None
    if _is_jaxmarl(built):
        env: MarlEnv = JaxMarlUserEnv(env_id, built)
    elif all(callable(getattr(built, name, None)) for name in ("reset", "step")) and hasattr(
        built, "spec"
    ):
        env = cast(MarlEnv, built)
    else:
        raise CmatError(
            f"{env_id}: the factory must return a cmat MarlEnv (spec, reset, step) or a JaxMARL "
            f"MultiAgentEnv, got {type(built).__name__}"
        )
    check_marl_env(env, env_id)
    return env


def _is_jaxmarl(env: Any) -> bool:
    return all(hasattr(env, name) for name in ("agents", "step_env", "action_space")) and not (
        isinstance(getattr(env, "spec", None), EnvSpec)
    )


def _traced(env_id: str, call: str, function: Any, *args: Any) -> Any:
    """`jax.eval_shape(function, *args)`, with the user's exceptions as one CmatError."""
    try:
        return jax.eval_shape(function, *args)
    except CmatError:
        raise
    except Exception as error:  # the user's reset or step, traced
        message = str(error).strip().splitlines()
        raise CmatError(f"{env_id}: {call} raised {type(error).__name__}: "
                        f"{message[0] if message else ''}") from None


def check_marl_env(env: MarlEnv, env_id: str) -> None:
    """Trace `env.reset` and `env.step` abstractly and compare their returns with `env.spec`
    (`TimeStep` field shapes and dtypes; `step`'s state with `reset`'s). Raises CmatError."""
    spec = env.spec
    if not isinstance(spec, EnvSpec):
        raise CmatError(f"{env_id}: the env's spec must be a cmat.envs.EnvSpec, got "
                        f"{type(spec).__name__}")
    check_spec_types(spec, env_id)
    if spec.num_agents < 1 or spec.obs_dim < 1 or spec.action_dim < 1 or (
        spec.max_episode_steps < 1
    ):
        raise CmatError(f"{env_id}: the spec's num_agents, obs_dim, action_dim and "
                        f"max_episode_steps must all be >= 1, got {spec}")
    key = jax.random.PRNGKey(0)
    reset_state, first = _traced(env_id, "reset(key)", env.reset, key)
    _check_timestep(env_id, "reset", first, spec)
    actions = (jnp.zeros(spec.num_agents, jnp.int32) if spec.discrete
               else jnp.zeros((spec.num_agents, spec.action_dim), jnp.float32))
    state, timestep = _traced(env_id, "step(key, state, actions)", env.step, key, reset_state,
                              actions)
    _check_timestep(env_id, "step", timestep, spec)
    structure: Any = jax.tree.structure(state)
    if structure != jax.tree.structure(reset_state) or any(
        (a.shape, a.dtype) != (b.shape, b.dtype)
        for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(reset_state))
    ):
        raise CmatError(f"{env_id}: step returns a state unlike reset's (its structure, shapes "
                        f"or dtypes differ); the rollout carries one fixed state type")
    _check_checkpointable(env_id, reset_state)


def _check_checkpointable(env_id: str, state: Any) -> None:
    """CmatError where a state of `state`'s abstract shapes (zeros) does not survive a
    checkpoint's round trip (`cmat.runners.base.state_to_bytes`: flax serialization to
    msgpack and back): a run saves its environments' states after every chunk. States whose
    dtypes numpy cannot hold (typed PRNG keys) are left to the save itself."""
    try:
        zeros = jax.tree.map(lambda leaf: np.zeros(leaf.shape, leaf.dtype), state)
    except TypeError:
        return
    try:
        data = flax.serialization.msgpack_serialize(flax.serialization.to_state_dict(zeros))
        restored = flax.serialization.from_state_dict(
            zeros, flax.serialization.msgpack_restore(data))
        structure: Any = jax.tree.structure(restored)
        survived = structure == jax.tree.structure(zeros)
        problem = "" if survived else "it comes back with another structure"
    except Exception as error:  # flax on the user's state type: any failure is the finding
        problem = f"{type(error).__name__}: {str(error).strip().splitlines()[0]}"
    if problem:
        raise CmatError(f"{env_id}: the env's state ({type(state).__name__}) cannot be saved in a "
                        f"checkpoint ({problem}); use a flax.struct.dataclass, a NamedTuple, a "
                        f"dict or arrays")


SPEC_FIELD_KINDS: dict[str, tuple[type | tuple[type, ...], str]] = {
    "str": (str, "text"), "int": (numbers.Integral, "a whole number"),
    "bool": ((bool, np.bool_), "True or False"), "float": (numbers.Real, "a number"),
    "tuple[str, ...]": (tuple, "a tuple of names"),
}
"""Per annotation of an EnvSpec field: the accepted types and their name in errors."""


def check_spec_types(spec: EnvSpec, env_id: str) -> None:
    """CmatError naming the first EnvSpec field whose value is not of its annotated kind (a
    bool is not taken for a number, nor a number for a bool)."""
    for field in dataclasses.fields(EnvSpec):
        accepted, wanted = SPEC_FIELD_KINDS[str(field.type)]
        value = getattr(spec, field.name)
        is_bool = isinstance(value, (bool, np.bool_))
        if not isinstance(value, accepted) or (is_bool and field.type != "bool"):
            raise CmatError(f"{env_id}: the spec's {field.name} must be {wanted}, got "
                            f"{value!r}")


def _check_timestep(env_id: str, call: str, timestep: Any, spec: EnvSpec) -> None:
    if not isinstance(timestep, TimeStep):
        raise CmatError(f"{env_id}: {call} must return (state, cmat.envs.TimeStep), got "
                        f"{type(timestep).__name__} as the second item")
    n = spec.num_agents
    expected = {
        "obs": ((n, spec.obs_dim), "floating"), "action_mask": ((n, spec.action_dim), "bool"),
        "reward": ((), "floating"), "done": ((), "bool"), "won": ((), "bool"),
        "alive": ((n,), "bool"), "global_state": ((spec.state_dim,), "floating"),
        **({"metrics": ((len(spec.episode_metrics),), "floating")}
           if spec.episode_metrics else {}),
    }
    for name, (shape, kind) in expected.items():
        value = getattr(timestep, name)
        got = (tuple(value.shape), value.dtype) if hasattr(value, "shape") else None
        dtype_ok = got is not None and (
            got[1] == jnp.bool_ if kind == "bool" else jnp.issubdtype(got[1], jnp.floating)
        )
        if got is None or got[0] != shape or not dtype_ok:
            found = f"{got[0]} {got[1]}" if got else type(value).__name__
            raise CmatError(f"{env_id}: {call}'s TimeStep.{name} is {found}, but the spec "
                            f"needs shape {shape} ({kind})")


class JaxMarlUserEnv(JaxMarlEnv):
    """A user's JaxMARL `MultiAgentEnv` behind the `MarlEnv` protocol (module docstring).

    `obs_sizes[i]` and `action_sizes[i]` are agent i's flat observation size and number of
    actions (or action entries) before padding; `action_low` and `action_high` are the Box
    bounds, [n_agents, action_dim], padded with -1 and 1. `reset`, `step` and
    `step_in_episode` are `JaxMarlEnv`'s; the spec is built here from the traced returns rather
    than from `JaxMarlEnv`'s equal-sized spaces."""

    def __init__(self, env_id: str, env: Any) -> None:
        self.env = env
        self.agents: list[str] = list(env.agents)
        if not self.agents:
            raise CmatError(f"{env_id}: the env has no agents")
        named = next((agent for agent in self.agents if not isinstance(agent, str)), None)
        if named is not None:
            raise CmatError(f"{env_id}: env.agents must be names (str), as JaxMARL's envs use "
                            f"them to key observations, actions, rewards and dones; got "
                            f"{named!r} ({type(named).__name__})")
        key = jax.random.PRNGKey(0)
        obs, _ = _traced(env_id, "reset(key)", env.reset, key)
        if not isinstance(obs, dict) or any(agent not in obs for agent in self.agents):
            raise CmatError(f"{env_id}: reset must return (observations keyed by agent, state); "
                            f"got observations {_keys(obs)} for agents {self.agents}")
        self.obs_sizes = [math.prod(obs[agent].shape) for agent in self.agents]
        spaces = [self._space(env_id, agent) for agent in self.agents]
        discrete = all(isinstance(space, Discrete) for space in spaces)
        boxes = all(isinstance(space, Box) for space in spaces)
        if not (discrete or boxes):
            kinds = sorted({type(space).__name__ for space in spaces})
            raise CmatError(f"{env_id}: action spaces must be all Discrete or all Box, got "
                            f"{', '.join(kinds)}")
        self.discrete = discrete
        if discrete:
            self.action_sizes = [int(space.n) for space in spaces]
        else:
            self.action_sizes = [math.prod(space.shape) for space in spaces]
        self.action_shapes = [getattr(space, "shape", ()) for space in spaces]
        action_dim = max(self.action_sizes)
        low = np.full((len(self.agents), action_dim), -1.0, np.float32)
        high = np.ones((len(self.agents), action_dim), np.float32)
        if not discrete:
            for i, (agent, space, size) in enumerate(zip(self.agents, spaces, self.action_sizes)):
                low[i, :size] = np.broadcast_to(np.asarray(space.low, np.float32), space.shape)
                high[i, :size] = np.broadcast_to(np.asarray(space.high, np.float32), space.shape)
                if not (np.all(np.isfinite(low[i])) and np.all(np.isfinite(high[i]))):
                    raise CmatError(f"{env_id}: agent {agent!r}'s Box has an infinite bound; "
                                    f"cmat maps [-1, 1] onto finite bounds")
        self.action_low, self.action_high = jnp.asarray(low), jnp.asarray(high)
        self.has_global_state = "world_state" in obs
        self.implements_masks = _overrides(env, "get_avail_actions")
        actions = (jnp.zeros(len(self.agents), jnp.int32) if discrete
                   else jnp.zeros((len(self.agents), action_dim), jnp.float32))
        step_returns = _traced(
            env_id, "step_env(key, state, actions)",
            lambda key: env.step_env(key, env.reset(key)[1], self._agent_actions(actions)), key,
        )
        if not (isinstance(step_returns, tuple) and len(step_returns) == 5):
            raise CmatError(f"{env_id}: step_env must return (obs, state, rewards, dones, "
                            f"infos), got {type(step_returns).__name__}")
        _check_step_observations(env_id, self.agents, obs, step_returns[0])
        if self.implements_masks and discrete:
            self._check_mask_sizes(env_id, key)
        rewards, dones = step_returns[2], step_returns[3]
        for name, value in (("rewards", rewards), ("dones", dones)):
            if not isinstance(value, dict):
                raise CmatError(f"{env_id}: step_env's {name} must be a dict keyed by agent name"
                                f"{' (and __all__)' if name == 'dones' else ''}, got "
                                f"{_described(value)}")
        if "__all__" not in dones:
            raise CmatError(f"{env_id}: step_env's dones must hold '__all__', got "
                            f"{_keys(dones)}")
        missing = [agent for agent in self.agents
                   if agent not in rewards or agent not in dones]
        if missing:
            raise CmatError(f"{env_id}: step_env's rewards and dones must hold every agent; "
                            f"{missing[0]!r} is missing from {_keys(rewards)} or {_keys(dones)}")
        vector = next((agent for agent in self.agents
                       if math.prod(getattr(rewards[agent], "shape", ())) != 1), None)
        if vector is not None:
            raise CmatError(f"{env_id}: step_env's reward of agent {vector!r} has shape "
                            f"{tuple(rewards[vector].shape)}; expected one number per agent")
        self.has_win = isinstance(step_returns[4], dict) and "won" in step_returns[4]
        max_steps = getattr(env, "max_steps", None)
        self.spec = EnvSpec(
            env_id=env_id,
            num_agents=len(self.agents),
            obs_dim=max(self.obs_sizes),
            action_dim=action_dim,
            discrete=discrete,
            max_episode_steps=int(max_steps) + 1 if max_steps else DEFAULT_MAX_STEPS,
            has_win_rate=self.has_win,
            state_dim=math.prod(obs["world_state"].shape) if self.has_global_state else 0,
        )

    def _check_mask_sizes(self, env_id: str, key: jax.Array) -> None:
        """CmatError where `get_avail_actions` gives an agent other than one entry per action of
        its `Discrete` space (traced on reset's state; step's state has its type)."""
        available = _traced(env_id, "get_avail_actions(state)",
                            lambda key: self.env.get_avail_actions(self.env.reset(key)[1]), key)
        for agent, size in zip(self.agents, self.action_sizes):
            shape = getattr(available.get(agent) if isinstance(available, dict) else None,
                            "shape", None)
            entries = math.prod(shape) if shape is not None else None
            if entries != size:
                found = f"{entries} entries" if entries is not None else "no entry"
                raise CmatError(f"{env_id}: get_avail_actions gives agent {agent!r} {found}, "
                                f"but its action space has {size} actions")

    def _space(self, env_id: str, agent: str) -> Any:
        try:
            return self.env.action_space(agent)
        except Exception as error:  # the user's space method
            raise CmatError(f"{env_id}: action_space({agent!r}) raised "
                            f"{type(error).__name__}: {error}") from None

    def _agent_actions(self, actions: jax.Array) -> dict[str, jax.Array]:
        """`actions` [n_agents] discrete, or [n_agents, action_dim] in [-1, 1] mapped onto each
        agent's Box."""
        agent_actions = {}
        for i, (agent, size) in enumerate(zip(self.agents, self.action_sizes)):
            if self.discrete:
                agent_actions[agent] = actions[i]
            else:
                unit = (jnp.clip(actions[i, :size], -1.0, 1.0) + 1.0) / 2.0
                low, high = self.action_low[i, :size], self.action_high[i, :size]
                agent_actions[agent] = (low + unit * (high - low)).reshape(self.action_shapes[i])
        return agent_actions

    def _obs(self, per_agent: dict[str, jax.Array]) -> jax.Array:
        return stack_padded(per_agent, self.agents, self.obs_sizes)

    def _action_mask(self, state: Any) -> jax.Array:
        width = max(self.action_sizes)
        if not self.discrete:
            return jnp.ones((len(self.agents), width), bool)
        if self.implements_masks:
            available = self.env.get_avail_actions(state)
            rows = [jnp.asarray(available[agent], bool) for agent in self.agents]
        else:
            rows = [jnp.ones(size, bool) for size in self.action_sizes]
        return jnp.stack([
            jnp.pad(row, (0, width - size)) for row, size in zip(rows, self.action_sizes)
        ])

    def _won(self, state: Any, infos: dict[str, Any]) -> jax.Array:
        if not self.has_win:
            return jnp.asarray(False)
        return jnp.any(jnp.asarray(infos["won"], bool))

    def _alive(self, state: Any, dones: dict[str, jax.Array] | None) -> jax.Array:
        if dones is None:
            return jnp.ones(len(self.agents), bool)
        return ~jnp.stack([jnp.asarray(dones[agent], bool) for agent in self.agents])


def _check_step_observations(
    env_id: str, agents: list[str], reset_obs: dict[str, Any], step_obs: Any
) -> None:
    """CmatError where `step_env`'s observations miss an agent, change an agent's size (or the
    world state's) from `reset`'s, or drop or add a world state: the adapter pads every agent to
    one fixed width taken from `reset`."""
    names = [*agents, *(["world_state"] if "world_state" in reset_obs else [])]
    if not isinstance(step_obs, dict) or any(name not in step_obs for name in names):
        raise CmatError(f"{env_id}: step_env must return observations of every agent"
                        f"{' and the world_state' if 'world_state' in reset_obs else ''} as reset"
                        f" does; got {_keys(step_obs)}")
    if "world_state" in step_obs and "world_state" not in reset_obs:
        raise CmatError(f"{env_id}: step_env returns a world_state that reset does not; cmat "
                        f"reads the global state from reset's observations")
    for name in names:
        before, after = reset_obs[name].shape, getattr(step_obs[name], "shape", None)
        if after is None or math.prod(after) != math.prod(before):
            shown = f"shape {tuple(after)}" if after is not None else type(step_obs[name]).__name__
            raise CmatError(f"{env_id}: step_env's observation {name!r} has {shown}, but "
                            f"reset's has shape {tuple(before)}; each must keep its size")


def _overrides(env: Any, method: str) -> bool:
    """Whether the env's class implements `method` beyond JaxMARL's `MultiAgentEnv`."""
    return getattr(type(env), method, None) not in (None, getattr(MultiAgentEnv, method, None))


def _described(value: Any) -> str:
    """`value` for an error: an array as its shape and dtype, anything else as its type."""
    if hasattr(value, "shape") and hasattr(value, "dtype"):
        return f"an array of shape {tuple(value.shape)} ({value.dtype})"
    return type(value).__name__


def _keys(value: Any) -> str:
    return str(sorted(value)) if isinstance(value, dict) else type(value).__name__


def build(env_id: str, name: str) -> tuple[Callable[..., MarlEnv], None]:
    """The jax suite's builder (cmat.envs.suites.Builder): NAME is `package.module:factory`,
    which takes any option it takes (`make_user_env` checks them)."""
    return partial(make_user_env, env_id, name), None
