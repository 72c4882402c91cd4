"""Evaluation, with one episode semantics for in-graph and host runs.

`episodes` episodes per seed are played on `slots` environments, each slot playing its quota
(`split_evenly(episodes, slots)`) of whole episodes one after another. The score is the mean
return over the `episodes` episodes and the fraction of them won; a slot whose last counted
episode has not ended when the step limit (quota × the environment's episode limit) is reached
counts its running return. Episodes past a slot's quota are played but not counted, so short
episodes are not over-counted. In-graph runs use one slot per episode (every episode runs in
parallel inside the program) up to `EVAL_SLOTS` slots; host runs min(episodes, num_envs) slots,
since each slot is a simulator. The bookkeeping (`EpisodeTally`) is the same code in both, on
jax.numpy inside the program and on NumPy in the host loop.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cmat.algorithms.base import Algorithm, Params, initial_memories, with_memory
from cmat.envs.protocol import EnvSpec, MarlEnv, TimeStep
from cmat.runners.collector import env_actions


class EpisodeTally(NamedTuple):
    """Per slot [..., slots]: the return of the episode running, the summed return and wins of
    the counted episodes, how many episodes have ended, and, per episode metric
    (`EnvSpec.episode_metrics`) [..., slots, M], the sum of its values over the counted
    episodes that ended where it is defined (not NaN) and how many those are."""

    running: Any
    total: Any
    wins: Any
    finished: Any
    metrics: Any
    defined: Any


def split_evenly(total: int, parts: int) -> np.ndarray:
    """`parts` non-negative counts summing to `total`, as equal as possible."""
    return np.diff(np.linspace(0, total, parts + 1).round().astype(int))


def tally_start(shape: tuple[int, ...], spec: EnvSpec, xp: Any = np) -> EpisodeTally:
    zeros = xp.zeros(shape, xp.float32)
    metrics = xp.zeros((*shape, len(spec.episode_metrics)), xp.float32)
    return EpisodeTally(zeros, zeros, zeros, xp.zeros(shape, xp.int32), metrics, metrics)


def tally_step(
    tally: EpisodeTally, reward: Any, done: Any, won: Any, quota: Any, xp: Any = np,
    metrics: Any = None,
) -> EpisodeTally:
    """The tally after one step of every slot with these rewards, episode ends, wins and
    episode metrics ([..., slots, M]; None where the environment reports none)."""
    running = tally.running + reward
    counted = done & (tally.finished < quota)
    sums, defined = tally.metrics, tally.defined
    if metrics is not None:
        valid = counted[..., None] & ~xp.isnan(metrics)
        sums = (sums + xp.where(valid, metrics, 0.0)).astype(xp.float32)
        defined = (defined + valid).astype(xp.float32)
    return EpisodeTally(
        running=xp.where(done, 0.0, running).astype(xp.float32),
        total=(tally.total + xp.where(counted, running, 0.0)).astype(xp.float32),
        wins=(tally.wins + (counted & won)).astype(xp.float32),
        finished=tally.finished + done,
        metrics=sums,
        defined=defined,
    )


def tally_result(
    tally: EpisodeTally, quota: Any, episodes: int, spec: EnvSpec, xp: Any = np
) -> dict[str, Any]:
    """Mean return and win rate (NaN where the environment has none) over the last axis, and
    each episode metric's mean over the counted episodes that ended where it is defined (NaN
    where it is in none)."""
    total = tally.total + xp.where(tally.finished < quota, tally.running, 0.0)
    win_rate = tally.wins.sum(axis=-1) / episodes
    defined = tally.defined.sum(axis=-2)
    metrics = xp.where(defined > 0, tally.metrics.sum(axis=-2) / xp.maximum(defined, 1), xp.nan)
    return {
        "episode_return": (total.sum(axis=-1) / episodes).astype(xp.float32),
        "win_rate": (win_rate if spec.has_win_rate else xp.full_like(win_rate, xp.nan))
        .astype(xp.float32),
        **{name: metrics[..., index].astype(xp.float32)
           for index, name in enumerate(spec.episode_metrics)},
    }


EVAL_SLOTS = 1024
"""The most environments an in-graph evaluation steps at once; more episodes than this play
one after another in them (`evaluate_in_graph`), so memory stays bounded however many are
asked for."""


def evaluate_in_graph(
    env: MarlEnv, algorithm: Algorithm, params: Params, rng: jax.Array, episodes: int,
    sample: bool = False, max_slots: int = EVAL_SLOTS,
) -> dict[str, jax.Array]:
    """`episodes` episodes of one seed inside the program, acting greedily or, with `sample`,
    by sampling the policy (`TrainConfig.eval_actions`): one slot per episode up to
    `max_slots`, beyond that `max_slots` slots playing their quotas (module docstring)."""
    spec = env.spec
    slots = min(episodes, max_slots)
    reset_key, rng = jax.random.split(rng)
    env_state, timestep = jax.vmap(env.reset)(jax.random.split(reset_key, slots))
    stepper = with_memory(algorithm)
    greedy = jax.vmap(stepper.greedy_with_memory, in_axes=(None, 0, 0, 0, 0))
    act = jax.vmap(stepper.act_with_memory, in_axes=(None, 0, 0, 0, 0, 0, 0))
    memory = initial_memories(algorithm, slots)
    shares = split_evenly(episodes, slots)
    quota = jnp.asarray(shares, jnp.int32)

    Carry = tuple[Any, TimeStep, EpisodeTally, Any]

    def step(carry: Carry, key: jax.Array) -> tuple[Carry, None]:
        env_state, timestep, tally, memory = carry
        if sample:
            key, act_key = jax.random.split(key)
            acted, memory = act(params, memory, timestep.obs, timestep.action_mask,
                                jax.random.split(act_key, slots), timestep.global_state,
                                timestep.done)
            actions = acted.actions
        else:
            actions, memory = greedy(
                params, memory, timestep.obs, timestep.action_mask, timestep.done
            )
        env_state, timestep = jax.vmap(env.step)(
            jax.random.split(key, slots), env_state, env_actions(spec, actions)
        )
        tally = tally_step(tally, timestep.reward, timestep.done, timestep.won, quota, jnp,
                           timestep.metrics)
        return (env_state, timestep, tally, memory), None

    carry = (env_state, timestep, tally_start((slots,), spec, jnp), memory)
    (_, _, tally, _), _ = jax.lax.scan(
        step, carry, jax.random.split(rng, int(shares.max()) * spec.max_episode_steps)
    )
    return tally_result(tally, quota, episodes, spec, jnp)
