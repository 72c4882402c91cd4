"""The learner: everything of an update after collection, knowing nothing of environments.

`learn(setup, learner, rollout)` takes a rollout from any collector (the in-graph scan of
`cmat.runners.collector`, the host pool of `cmat.runners.host`): GAE from the target critic
V_φ- bootstrapped from the observation after the rollout, the algorithm's `update` (epochs ×
minibatches of PPO, `cmat.algorithms.sgd`) and the target critic's soft update (Algorithm 1),
with a check that the update stayed finite; the rollout's episode sums and the environment's
faults are the collector's (`cmat.runners.collector.rollout_report`). Its state is what a
checkpoint must hold of the learning itself: parameters, target critic, optimizer state, value
normaliser, random key and update count.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import optax

from cmat.algorithms import build_algorithm
from cmat.algorithms import ppo as ppo_lib
from cmat.algorithms.base import Algorithm, Batch, Params, is_recurrent, with_memory
from cmat.algorithms.sgd import finetune_optimizer
from cmat.config import TrainConfig
from cmat.envs.protocol import EnvSpec
from cmat.runners.collector import ENV_FAULTS, all_finite
from cmat.runners.types import Rollout


@flax.struct.dataclass
class LearnerState:
    """One seed's learning state, carried from update to update."""

    params: Params
    target_params: Params
    opt_state: Any
    value_norm: ppo_lib.ValueNormState
    rng: jax.Array
    update_step: jax.Array


@dataclass(frozen=True)
class LearnerSetup:
    """The static parts of learning: closed over, never traced."""

    config: TrainConfig
    spec: EnvSpec
    algorithm: Algorithm
    optimizer: optax.GradientTransformation


def build_learner(config: TrainConfig, spec: EnvSpec) -> LearnerSetup:
    """The algorithm of `config` for environments of `spec`, and its optimizer."""
    algorithm = build_algorithm(config.algo, config.network, spec, config.ppo, config.options)
    return LearnerSetup(config, spec, algorithm, build_optimizer(config, algorithm))


def build_optimizer(config: TrainConfig, algorithm: Algorithm) -> optax.GradientTransformation:
    """Adam after global-norm clipping; a fine-tuning run (`config.finetune`) applies it only to
    the parameters the algorithm's `finetune_labels` train in that stage, and zero updates to
    the frozen ones."""
    optimizer = optax.chain(
        optax.clip_by_global_norm(config.ppo.max_grad_norm),
        optax.adam(config.ppo.lr, eps=config.ppo.adam_eps),
    )
    if config.finetune is None:
        return optimizer
    return finetune_optimizer(optimizer, partial(algorithm.finetune_labels, mode=config.finetune))


def init_learner(
    setup: LearnerSetup, init_key: jax.Array, rng: jax.Array, obs: jax.Array, mask: jax.Array
) -> LearnerState:
    """Fresh parameters from `init_key` for one observation [n, obs_dim] and action mask
    [n, action_dim]; `rng` becomes the learner's key."""
    params = setup.algorithm.init(init_key, obs, mask)
    return LearnerState(
        params=params,
        target_params=params,
        opt_state=setup.optimizer.init(params),
        value_norm=ppo_lib.value_norm_init(),
        rng=rng,
        update_step=jnp.zeros((), jnp.int32),
    )


def critic_values(
    setup: LearnerSetup, params: Params, obs: jax.Array, global_state: jax.Array
) -> jax.Array:
    """The algorithm's values for observations [..., n, obs_dim] and global states
    [..., state_dim] with any leading axes, in one batched network call: [...] team values, or
    [..., n] per-agent ones."""
    lead = obs.shape[:-2]
    flat_obs = obs.reshape(-1, *obs.shape[-2:])
    flat_state = global_state.reshape(flat_obs.shape[0], global_state.shape[-1])
    values = jax.vmap(setup.algorithm.value, in_axes=(None, 0, 0))(params, flat_obs, flat_state)
    return values.reshape(*lead, *values.shape[1:])


def value_to_returns_space(
    setup: LearnerSetup, norm: ppo_lib.ValueNormState, v: jax.Array
) -> jax.Array:
    return ppo_lib.value_norm_denormalize(norm, v) if setup.config.ppo.value_norm else v


def make_batch(
    setup: LearnerSetup, learner: LearnerState, rollout: Rollout
) -> tuple[ppo_lib.ValueNormState, Batch]:
    """GAE with the target critic V_φ- (Algorithm 1) and normalised value targets: a batch of
    T·envs samples, or for a recurrent algorithm of `envs` sequences of T steps with the state
    each starts from (values then come from its `sequence_values`).

    Team values [T, envs] give one advantage per step; per-agent values [T, envs, n] (MAT's
    per-agent GAE) give one per agent, from the shared team reward and episode ends. With
    `ppo.active_masks` the advantages are normalised over active agents only (the reference
    MAT and MAPPO set inactive entries to NaN and take nanmean / nanstd)."""
    ppo = setup.config.ppo
    steps = rollout.steps
    all_obs = jnp.concatenate([steps.obs, rollout.next_obs[None]], axis=0)
    all_states = jnp.concatenate([steps.global_state, rollout.next_global_state[None]], axis=0)
    if is_recurrent(setup.algorithm):
        all_starts = jnp.concatenate([steps.start, steps.done[-1:]], axis=0)
        values = jax.vmap(
            with_memory(setup.algorithm).sequence_values, in_axes=(None, 0, 1, 1, 1), out_axes=1
        )(learner.target_params, rollout.memory, all_obs, all_states, all_starts)
    else:
        values = critic_values(setup, learner.target_params, all_obs, all_states)
    target_values = value_to_returns_space(setup, learner.value_norm, values)
    agent_axes = target_values.ndim - steps.reward.ndim
    rewards = steps.reward.reshape(*steps.reward.shape, *(1,) * agent_axes)
    dones = steps.done.reshape(*steps.done.shape, *(1,) * agent_axes)
    advantages, returns = ppo_lib.generalized_advantages(
        rewards, target_values[:-1], dones, target_values[-1], ppo.gamma, ppo.gae_lambda,
    )
    value_norm = learner.value_norm
    targets = returns
    if ppo.value_norm:
        value_norm = ppo_lib.value_norm_update(value_norm, returns)
        targets = ppo_lib.value_norm_normalize(value_norm, returns)
    if ppo.normalize_advantages:
        if ppo.active_masks:
            per_agent = advantages if agent_axes else advantages[..., None]
            statistics = jnp.broadcast_to(per_agent, steps.alive.shape)
            normalised = ppo_lib.normalize(statistics, steps.alive)
            advantages = normalised if agent_axes else normalised[..., 0]
        else:
            advantages = ppo_lib.normalize(advantages)

    recurrent = is_recurrent(setup.algorithm)

    def arrange(x: jax.Array) -> jax.Array:
        """[T, envs, ...] -> samples [T·envs, ...], or sequences [envs, T, ...]."""
        if recurrent:
            return jnp.swapaxes(x, 0, 1)
        return x.reshape(x.shape[0] * x.shape[1], *x.shape[2:])

    batch = Batch(
        obs=arrange(steps.obs),
        action_mask=arrange(steps.action_mask),
        actions=arrange(steps.actions),
        log_probs=arrange(steps.log_probs),
        values=arrange(steps.value),
        advantages=arrange(advantages),
        targets=arrange(targets),
        alive=arrange(steps.alive),
        global_state=arrange(steps.global_state),
        extras=jax.tree.map(arrange, steps.extras),
        starts=arrange(steps.start) if recurrent else None,
        memory=rollout.memory,
    )
    return value_norm, batch


def optimise(
    setup: LearnerSetup, params: Params, opt_state: Any, batch: Batch, rng: jax.Array
) -> tuple[Params, Any, dict[str, jax.Array]]:
    """The algorithm's `update` of one rollout's batch with the run's optimiser and PPO config
    (for the shared PPO: `cmat.algorithms.sgd.minibatch_sgd` on its loss)."""
    return setup.algorithm.update(
        setup.optimizer, params, opt_state, batch, rng, setup.config.ppo
    )


UPDATE_FAULTS = ("non-finite loss", "non-finite gradient norm", "non-finite parameters")
"""What `update_fault_code` k > 0 names: UPDATE_FAULTS[k - 1]."""

ROLLOUT_FAULTS = (*ENV_FAULTS, *UPDATE_FAULTS)
"""What a `fault_code` of `summarise_updates` k > 0 names: ROLLOUT_FAULTS[k - 1]: the
collector's checks of the environment first (`cmat.runners.collector.ENV_FAULTS`), as a bad
value from it makes everything after it non-finite, then the update's."""


def update_fault_code(metrics: dict[str, jax.Array], params: Params) -> jax.Array:
    """0 if the update's loss, gradient norm and new parameters are finite, else 1 + the index
    in `UPDATE_FAULTS` of the first check that failed (the loss and gradient norm are means
    over the update's minibatch steps, so one bad step makes them non-finite)."""
    checks = jnp.stack([jnp.isfinite(metrics["loss"]), jnp.isfinite(metrics["grad_norm"]),
                        all_finite(params)])
    return jnp.where(jnp.all(checks), 0, 1 + jnp.argmin(checks)).astype(jnp.int32)


def learn(
    setup: LearnerSetup, learner: LearnerState, rollout: Rollout
) -> tuple[LearnerState, dict[str, jax.Array]]:
    """One update from one seed's rollout: GAE from the target critic, the algorithm's
    `update` and the target critic's soft update (τ = ppo.target_tau); its metrics with
    `update_fault` (`update_fault_code`). The rollout's own report (episodes, environment
    faults) is the collector's (`cmat.runners.collector.rollout_report`)."""
    value_norm, batch = make_batch(setup, learner, rollout)
    rng, update_key = jax.random.split(learner.rng)
    params, opt_state, metrics = optimise(
        setup, learner.params, learner.opt_state, batch, update_key
    )
    target_params = optax.incremental_update(
        params, learner.target_params, setup.config.ppo.target_tau
    )
    rollout_metrics = {
        "explained_variance": ppo_lib.explained_variance(batch.values, batch.targets),
        "update_fault": update_fault_code(metrics, params),
    }
    learner = LearnerState(
        params=params, target_params=target_params, opt_state=opt_state,
        value_norm=value_norm, rng=rng, update_step=learner.update_step + 1,
    )
    return learner, {**metrics, **rollout_metrics}


def summarise_updates(spec: EnvSpec, per_update: dict[str, jax.Array]) -> dict[str, jax.Array]:
    """Metrics of updates stacked on a leading axis, each update's with its rollout's report
    (`cmat.runners.collector.rollout_report`): losses averaged over the updates performed
    (`performed`, all where absent), episode sums pooled into the mean return and win rate of
    the episodes that ended in the span (NaN where none did). `fault_update` is the index of
    the first update whose rollout or update failed a check (-1 if none) and `fault_code`
    which one (`ROLLOUT_FAULTS`)."""
    per_update = dict(per_update)
    env_fault, update_fault = per_update.pop("env_fault"), per_update.pop("update_fault")
    codes = jnp.where(env_fault > 0, env_fault,
                      jnp.where(update_fault > 0, len(ENV_FAULTS) + update_fault, 0))
    performed = per_update.pop("performed", jnp.ones(codes.shape, bool))
    episodes = jnp.sum(per_update.pop("episodes"))
    return_sum = jnp.sum(per_update.pop("return_sum"))
    win_sum = jnp.sum(per_update.pop("win_sum"))
    weights = performed.astype(jnp.float32)
    metrics: dict[str, jax.Array] = jax.tree.map(
        lambda x: jnp.sum(jnp.where(performed, x, 0.0)) / jnp.maximum(jnp.sum(weights), 1.0),
        per_update,
    )
    metrics["episode_return"] = jnp.where(
        episodes > 0, return_sum / jnp.maximum(episodes, 1), jnp.nan
    )
    win_rate = jnp.where(episodes > 0, win_sum / jnp.maximum(episodes, 1), jnp.nan)
    metrics["win_rate"] = win_rate if spec.has_win_rate else jnp.full_like(win_rate, jnp.nan)
    bad = performed & (codes > 0)
    first = jnp.argmax(bad)
    metrics["fault_update"] = jnp.where(jnp.any(bad), first, -1)
    metrics["fault_code"] = jnp.where(jnp.any(bad), codes[first], 0)
    return metrics
