"""A learned dispatch policy's decisions made conflict-free: matched decoding.

The environment gives an order that several vehicles claim to one of them and counts the other
claims as conflicts, whose vehicles stay idle for the minute (`cmat.envs.dispatch.env`). That
count measures how well a policy coordinates; an operator deploying one wants no conflicting
claims at all. The CMAT authors' ride-sharing code turned the policy's scores into one order
per vehicle with `scipy.optimize.linear_sum_assignment`; `matched_plan` does that with the
policy's own probabilities. Of the joint actions in which no order goes to two vehicles, it
takes the one of highest joint log-probability Σ_i log π_i(a_i): for a policy whose vehicles
decide independently given the observations (`cmat.algorithms.base.Factorised`), the most
likely conflict-free joint action. Every vehicle's alternative to an order is its most likely
other action (stay or reposition), so the plan is a maximum-weight matching of vehicles to
orders with weights log π_i(take o) − log π_i(best other action), solved as a rectangular
assignment with one zero-cost "no order" column per vehicle.

`cmat eval --run DIR --actions matched` evaluates a run's policy this way
(`evaluate_matched`); in a user's loop, `matched_plan(policy.log_probs(obs, mask), mask,
candidates)` per episode (`candidates`: the state's `candidates`, the order slot behind each
vehicle's take actions 1..K).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import linear_sum_assignment

from cmat.envs.dispatch.baselines import rollout
from cmat.envs.dispatch.env import DispatchEnv, DispatchState


def matched_plan(
    log_probs: np.ndarray, action_mask: np.ndarray, candidates: np.ndarray
) -> np.ndarray:
    """The conflict-free joint action [n] of highest Σ_i log_probs[i, a_i] (module docstring)
    for one episode's fleet: `log_probs` [n, A] (`cmat.Policy.log_probs`), `action_mask`
    [n, A] bool (True: available), `candidates` [n, K] the order slot that take action 1 + k
    of vehicle i claims. Actions 0 and above K are not claims (stay, reposition)."""
    k_max = candidates.shape[1]
    log_probs = np.where(action_mask, log_probs, -np.inf)
    other = log_probs.copy()
    other[:, 1:1 + k_max] = -np.inf
    actions: np.ndarray = other.argmax(axis=1).astype(np.int32)
    vehicle, k = np.nonzero(np.isfinite(log_probs[:, 1:1 + k_max]))
    if vehicle.size == 0:
        return actions
    gain = log_probs[vehicle, 1 + k] - other[vehicle, actions[vehicle]]
    ascending = np.argsort(gain, kind="stable")  # a vehicle listing one order twice: the
    vehicle, k, gain = vehicle[ascending], k[ascending], gain[ascending]  # larger gain wins
    rows, row_of = np.unique(vehicle, return_inverse=True)
    orders, column_of = np.unique(candidates[vehicle, k], return_inverse=True)
    cost = np.zeros((rows.size, orders.size + rows.size))
    cost[row_of, column_of] = -gain
    choice = np.full((rows.size, orders.size), -1)
    choice[row_of, column_of] = k
    matched_rows, matched_columns = linear_sum_assignment(cost)
    is_order = matched_columns < orders.size
    matched_rows, matched_columns = matched_rows[is_order], matched_columns[is_order]
    taken = choice[matched_rows, matched_columns]
    claim = taken >= 0
    actions[rows[matched_rows[claim]]] = 1 + taken[claim]
    return actions


def evaluate_matched(
    env: DispatchEnv, log_probs: Callable[[jax.Array, jax.Array], jax.Array], episodes: int,
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """`episodes` episodes of a policy decoded by `matched_plan` at every step, from keys of
    `seed` (the same episodes `cmat.envs.dispatch.baselines.evaluate` plays with that seed):
    per episode the return and the operator's metrics, arrays [episodes]. `log_probs(obs
    [E, n, obs_dim], action_mask [E, n, A])` gives the policy's per-vehicle log-probabilities
    [E, n, A] (`cmat.Policy.log_probs`, which raises CmatError for a policy without per-agent
    distributions)."""

    def decide(state: DispatchState, timestep: Any, key: jax.Array) -> jax.Array:
        fleets = np.asarray(log_probs(timestep.obs, timestep.action_mask))
        masks, candidates = np.asarray(timestep.action_mask), np.asarray(state.candidates)
        return jnp.asarray(np.stack([matched_plan(*fleet) for fleet in
                                     zip(fleets, masks, candidates)]))

    return rollout(env, decide, episodes, seed)
