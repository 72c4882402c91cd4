"""The classical dispatch policies every dispatch team compares against, as functions of the
environment's state that return the fleet's actions [n] (stay 0, take candidate k as 1 + k).

- `random`: each vehicle draws uniformly among its legal actions (stay, take a feasible
  candidate, reposition).
- `greedy`: orders in arrival order (longest waiting first, then slot order) each go to the
  nearest idle vehicle that has them among its candidates and is still free (ties to the lower
  vehicle index); no repositioning.
- `hungarian`: per step, a maximum matching of idle vehicles to open orders with the least
  total pickup time among maximum matchings (`scipy.optimize.linear_sum_assignment` on the
  pickup minutes, infeasible pairs at a cost above any sum of feasible ones); no
  repositioning. A vehicle may only take one of its K candidates (the environment's action
  space), so the matching is over those pairs.

`greedy` and `hungarian` run on the host (NumPy, SciPy) between jitted environment steps;
`evaluate` steps a batch of episodes that way and returns the operator's metrics.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import linear_sum_assignment

from cmat.envs.dispatch.env import DispatchEnv, DispatchState, episode_metrics
from cmat.errors import CmatError

Candidates = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""One episode's (candidates [n, K] order slots, their pickup minutes [n, K], feasible
[n, K] bool, the order slots' minutes waited [O])."""


def greedy_plan(candidates: np.ndarray, pickup: np.ndarray, ok: np.ndarray,
                waited: np.ndarray) -> np.ndarray:
    """Greedy nearest-vehicle actions [n] for one episode's state (module docstring)."""
    vehicle, k = np.nonzero(ok)
    order = candidates[vehicle, k]
    ranked = np.lexsort((vehicle, pickup[vehicle, k], order, -waited[order]))
    actions = np.zeros(candidates.shape[0], np.int32)
    taken: set[int] = set()
    for index in ranked:
        v, o = vehicle[index], order[index]
        if actions[v] == 0 and o not in taken:
            actions[v] = 1 + k[index]
            taken.add(int(o))
    return actions


def hungarian_plan(candidates: np.ndarray, pickup: np.ndarray, ok: np.ndarray,
                   waited: np.ndarray) -> np.ndarray:
    """Hungarian actions [n] for one episode's state (module docstring)."""
    actions = np.zeros(candidates.shape[0], np.int32)
    vehicle, k = np.nonzero(ok)
    if vehicle.size == 0:
        return actions
    rows, row_of = np.unique(vehicle, return_inverse=True)
    columns, column_of = np.unique(candidates[vehicle, k], return_inverse=True)
    feasible_cost = pickup[vehicle, k].astype(np.float64)
    infeasible = feasible_cost.sum() + 1.0
    cost = np.full((rows.size, columns.size), infeasible)
    cost[row_of, column_of] = feasible_cost
    choice = np.full((rows.size, columns.size), -1)
    choice[row_of, column_of] = k
    matched_rows, matched_columns = linear_sum_assignment(cost)
    real = cost[matched_rows, matched_columns] < infeasible
    actions[rows[matched_rows[real]]] = 1 + choice[matched_rows[real], matched_columns[real]]
    return actions


HOST_POLICIES: dict[str, Callable[..., np.ndarray]] = {
    "greedy": greedy_plan, "hungarian": hungarian_plan,
}
POLICIES = ("random", *HOST_POLICIES)
"""Every baseline `evaluate` accepts."""


def evaluate(env: DispatchEnv, policy: str, episodes: int, seed: int = 0) -> dict[str, np.ndarray]:
    """`episodes` episodes of `policy` (`POLICIES`) from keys of `seed`: per episode, the return
    (`episode_return`) and the operator's metrics (`episode_metrics`), each an array
    [episodes]. Raises CmatError for an unknown policy or a number of episodes below 1."""
    if policy not in POLICIES:
        raise CmatError(f"unknown dispatch baseline {policy!r}; available: {', '.join(POLICIES)}")
    random_actions = jax.jit(lambda key, mask: jax.random.categorical(
        key, jnp.where(mask, 0.0, -jnp.inf)).astype(jnp.int32))

    def decide(state: DispatchState, timestep: Any, key: jax.Array) -> jax.Array:
        if policy == "random":
            actions: jax.Array = random_actions(key, timestep.action_mask)
            return actions
        return jnp.asarray(np.stack([HOST_POLICIES[policy](*view) for view in host_views(state)]))

    return rollout(env, decide, episodes, seed)


Decide = Callable[[DispatchState, Any, jax.Array], jax.Array]
"""A fleet's decision for a batch of episodes: (state, timestep, key) -> actions [episodes, n]."""


def rollout(
    env: DispatchEnv, decide: Decide, episodes: int, seed: int = 0
) -> dict[str, np.ndarray]:
    """`episodes` whole episodes from keys of `seed`, each step's actions from `decide` on the
    host between jitted environment steps: per episode the return (`episode_return`) and the
    operator's metrics (`episode_metrics`), each an array [episodes]. The episodes and the
    environment's draws depend on `seed` alone, so policies evaluated with one seed meet the
    same start states. Raises CmatError for a number of episodes below 1."""
    if episodes < 1:
        raise CmatError(f"episodes must be at least 1, got {episodes}")
    reset_keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
    state, timestep = jax.jit(jax.vmap(env.reset))(reset_keys)
    step = jax.jit(jax.vmap(env.step_in_episode))
    returns = np.zeros(episodes)
    key = jax.random.PRNGKey(seed + 1)
    for _ in range(env.episode_minutes):
        key, act_key, step_key = jax.random.split(key, 3)
        actions = decide(state, timestep, act_key)
        state, timestep = step(jax.random.split(step_key, episodes), state, actions)
        returns += np.asarray(timestep.reward)
    metrics = episode_metrics(state.stats, env.episode_minutes)
    return {"episode_return": returns, **{k: np.asarray(v) for k, v in metrics.items()}}


def means(result: dict[str, np.ndarray]) -> dict[str, float]:
    """Each figure of `rollout` averaged over the episodes that define it (NaN where none does,
    e.g. waits with no order served)."""
    return {name: float(values[~np.isnan(values)].mean()) if (~np.isnan(values)).any()
            else math.nan for name, values in result.items()}


def evaluate_means(
    env: DispatchEnv, policy: str, episodes: int, seed: int = 0
) -> dict[str, float]:
    """`evaluate`'s figures averaged over the episodes (`means`)."""
    return means(evaluate(env, policy, episodes, seed))


def baseline_env(env_id: str, env_kwargs: dict[str, Any]) -> DispatchEnv:
    """The dispatch environment `env_id` with `env_kwargs`; CmatError where `env_id` is not a
    dispatch task (only dispatch tasks have classical baselines)."""
    from cmat.envs import make_env

    env = make_env(env_id, **env_kwargs)
    if not isinstance(env, DispatchEnv):
        raise CmatError(f"baselines evaluate dispatch tasks only, not {env_id}")
    return env


def host_views(state: DispatchState) -> list[Candidates]:
    """Each episode's `Candidates` of a batched state, as NumPy arrays."""
    fields = [np.asarray(x) for x in (state.candidates, state.candidate_pickup,
                                      state.candidate_ok, state.order_waited)]
    return [(c, p, o, w) for c, p, o, w in zip(*fields)]
