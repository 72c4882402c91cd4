"""The one environment protocol every suite is adapted to.

All arrays are per environment (no batch axis); the trainer `vmap`s over environments.
Agents are always the leading axis of per-agent arrays.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

if TYPE_CHECKING:
    import jax


@dataclass(frozen=True)
class EnvSpec:
    """Static facts about an environment, known before it runs."""

    env_id: str
    num_agents: int
    obs_dim: int
    action_dim: int
    """Number of discrete actions, or the size of a continuous action vector."""
    discrete: bool
    max_episode_steps: int
    has_win_rate: bool
    action_low: float = -1.0
    """Lower Box bound of continuous actions (actions are clipped to it before stepping)."""
    action_high: float = 1.0
    state_dim: int = 0
    """Size of the environment's global state (`TimeStep.global_state`); 0 where it has none,
    and centralised critics that want one then read all agents' observations concatenated."""
    episode_metrics: tuple[str, ...] = ()
    """Names of the per-episode metrics the environment reports in `TimeStep.metrics` beside
    the return (dispatch: service rate, revenue, waits, …); evaluation averages each over the
    episodes it counts and metrics.csv gets a column for each."""
    agent_id: bool = False
    """Each observation ends with its agent's one-hot id [n] (`AgentIdWrapper`,
    `env_kwargs.agent_id`), so a network shared by the agents need not append one."""


class TimeStep(NamedTuple):
    """What an agent team sees after `reset` or `step`."""

    obs: jax.Array
    """[n_agents, obs_dim] float32."""
    action_mask: jax.Array
    """[n_agents, action_dim] bool; True = available. All True for continuous actions."""
    reward: jax.Array
    """[] float32 team reward of the transition just taken (0 after reset)."""
    done: jax.Array
    """[] bool: the transition just taken ended the episode (terminal or time limit)."""
    won: jax.Array
    """[] bool: the episode that just ended was won (False where undefined or not done)."""
    alive: jax.Array
    """[n_agents] bool: which agents are active in `obs` (a dead SMAX unit, a PettingZoo agent
    that left or has not joined: False). Inactive agents still get a forced action; the
    reference MAT, MAPPO and HAPPO leave them out of their loss means (active masks)."""
    global_state: jax.Array
    """[state_dim] float32: the environment's global state (SMAX: JaxMARL's world state);
    shape [0] where the environment has none."""
    metrics: jax.Array | None = None
    """[len(spec.episode_metrics)] float32: the values of the episode that the transition just
    taken ended (read only where `done`); None where the spec declares no episode metrics."""


class MarlEnv(Protocol):
    """A cooperative multi-agent environment written in JAX.

    `step` resets automatically: when `done` is True, `obs` and `action_mask` already belong to
    the first step of the next episode, while `reward`, `done` and `won` describe the transition
    that ended the previous one.
    """

    spec: EnvSpec

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]: ...

    def step(self, key: jax.Array, state: Any, actions: jax.Array) -> tuple[Any, TimeStep]: ...
