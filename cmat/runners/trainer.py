"""The compiled training program for in-graph (JAX) environments.

One update = rollout (`lax.scan` over steps, `vmap` over environments) → target-critic values →
GAE → PPO epochs × minibatches → soft update of the target critic (Algorithm 1). A chunk of
updates is one `lax.scan`, `vmap`ped over seeds and jitted as a single program; `make_train`
gives the whole run as one pure function, PureJaxRL style.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

import flax.serialization
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from cmat.algorithms import build_algorithm
from cmat.algorithms.base import Batch, Params, Algorithm
from cmat.algorithms.cmat_blocks import masked_optimizer
from cmat.algorithms import ppo as ppo_lib
from cmat.config import TrainConfig
from cmat.envs import make_env
from cmat.envs.protocol import EnvSpec, MarlEnv, TimeStep
from cmat.errors import CmatError

@flax.struct.dataclass
class TrainerState:
    """Everything one seed's run carries from update to update (a checkpoint)."""

    params: Params
    target_params: Params
    opt_state: Any
    value_norm: ppo_lib.ValueNormState
    env_state: Any
    timestep: TimeStep
    episode_return: jax.Array
    """[envs] return so far of each environment's running episode."""
    rng: jax.Array
    update_step: jax.Array


class Transition(NamedTuple):
    """One step of every environment, stacked to [T, envs, ...] by the rollout scan."""

    obs: jax.Array
    action_mask: jax.Array
    actions: jax.Array
    log_probs: jax.Array
    value: jax.Array
    reward: jax.Array
    done: jax.Array
    won: jax.Array
    finished_return: jax.Array
    """Return of the episode this step ended (0 where it ended none)."""
    extras: Any


@dataclass(frozen=True)
class TrainSetup:
    """The static parts of the program: closed over, never traced."""

    config: TrainConfig
    env: MarlEnv
    algorithm: Algorithm
    optimizer: optax.GradientTransformation

    @property
    def spec(self) -> EnvSpec:
        return self.env.spec


def build_setup(config: TrainConfig, env: MarlEnv | None = None) -> TrainSetup:
    """The setup of `config`; `env` replaces the registry's environment (the host runner passes
    one that holds only its `spec`, since it steps its environments outside the program)."""
    env = env if env is not None else make_env(config.env, **config.env_kwargs)
    algorithm = build_algorithm(config.algo, config.network, env.spec)
    return TrainSetup(config, env, algorithm, build_optimizer(config))


def build_optimizer(config: TrainConfig) -> optax.GradientTransformation:
    """Adam after global-norm clipping; a fine-tuning run (`config.finetune`) applies it only to
    the blocks its stage trains and zero updates to the frozen ones (cmat_blocks)."""
    optimizer = optax.chain(
        optax.clip_by_global_norm(config.ppo.max_grad_norm),
        optax.adam(config.ppo.lr, eps=config.ppo.adam_eps),
    )
    if config.finetune is None:
        return optimizer
    return masked_optimizer(optimizer, config.finetune)


def init_state(setup: TrainSetup, rng: jax.Array) -> TrainerState:
    """A fresh state; the environment state is made strongly typed, as a step returns it, so
    the chunk program compiles once (SMAX's reset yields weakly typed leaves)."""
    rng, init_key, reset_key = jax.random.split(rng, 3)
    env_state, timestep = jax.vmap(setup.env.reset)(
        jax.random.split(reset_key, setup.config.num_envs)
    )
    params = setup.algorithm.init(init_key, timestep.obs[0], timestep.action_mask[0])
    env_state = jax.tree.map(lambda x: jnp.asarray(x, dtype=x.dtype), env_state)
    return TrainerState(
        params=params,
        target_params=params,
        opt_state=setup.optimizer.init(params),
        value_norm=ppo_lib.value_norm_init(),
        env_state=env_state,
        timestep=timestep,
        episode_return=jnp.zeros(setup.config.num_envs),
        rng=rng,
        update_step=jnp.zeros((), jnp.int32),
    )


def env_actions(spec: EnvSpec, actions: jax.Array) -> jax.Array:
    """Actions as sent to the simulator: continuous ones clipped to the Box bounds (the stored
    log-probability stays that of the unclipped sample)."""
    if spec.discrete:
        return actions
    return jnp.clip(actions, spec.action_low, spec.action_high)


def collect_rollout(setup: TrainSetup, state: TrainerState) -> tuple[TrainerState, Transition]:
    """Act in all environments for `rollout_length` steps with the current parameters.

    The keys of a step's actions and environment steps come from one split of that step's key
    (one random-bits call per step on CPU, where each costs a small loop)."""
    num_envs = setup.config.num_envs

    def env_step(state: TrainerState, key: jax.Array) -> tuple[TrainerState, Transition]:
        act_keys, step_keys = jnp.split(jax.random.split(key, 2 * num_envs), 2)
        observed = state.timestep
        acted = jax.vmap(setup.algorithm.act, in_axes=(None, 0, 0, 0))(
            state.params, observed.obs, observed.action_mask, act_keys
        )
        env_state, timestep = jax.vmap(setup.env.step)(
            step_keys, state.env_state, env_actions(setup.spec, acted.actions)
        )
        running = state.episode_return + timestep.reward
        transition = Transition(
            obs=observed.obs,
            action_mask=observed.action_mask,
            actions=acted.actions,
            log_probs=acted.log_probs,
            value=acted.value,
            reward=timestep.reward,
            done=timestep.done,
            won=timestep.won,
            finished_return=jnp.where(timestep.done, running, 0.0),
            extras=acted.extras,
        )
        state = state.replace(
            env_state=env_state,
            timestep=timestep,
            episode_return=jnp.where(timestep.done, 0.0, running),
        )
        return state, transition

    rng, rollout_key = jax.random.split(state.rng)
    step_keys = jax.random.split(rollout_key, setup.config.rollout_length)
    state, rollout = jax.lax.scan(env_step, state, step_keys)
    return state.replace(rng=rng), rollout


def team_values(setup: TrainSetup, params: Params, obs: jax.Array) -> jax.Array:
    """V(O) for observations with any leading axes, one batched network call."""
    lead = obs.shape[:-2]
    flat = obs.reshape(-1, *obs.shape[-2:])
    return jax.vmap(setup.algorithm.value, in_axes=(None, 0))(params, flat).reshape(lead)


def value_to_returns_space(setup: TrainSetup, norm: ppo_lib.ValueNormState, v: jax.Array) -> jax.Array:
    return ppo_lib.value_norm_denormalize(norm, v) if setup.config.ppo.value_norm else v


def make_batch(
    setup: TrainSetup, state: TrainerState, rollout: Transition
) -> tuple[ppo_lib.ValueNormState, Batch]:
    """GAE with the target critic V_φ- (Algorithm 1) and normalised value targets."""
    ppo = setup.config.ppo
    all_obs = jnp.concatenate([rollout.obs, state.timestep.obs[None]], axis=0)
    target_values = value_to_returns_space(
        setup, state.value_norm, team_values(setup, state.target_params, all_obs)
    )
    advantages, returns = ppo_lib.generalized_advantages(
        rollout.reward, target_values[:-1], rollout.done, target_values[-1],
        ppo.gamma, ppo.gae_lambda,
    )
    value_norm = state.value_norm
    targets = returns
    if ppo.value_norm:
        value_norm = ppo_lib.value_norm_update(value_norm, returns)
        targets = ppo_lib.value_norm_normalize(value_norm, returns)
    if ppo.normalize_advantages:
        advantages = ppo_lib.normalize(advantages)

    def flat(x: jax.Array) -> jax.Array:
        return x.reshape(-1, *x.shape[2:])

    batch = Batch(
        obs=flat(rollout.obs),
        action_mask=flat(rollout.action_mask),
        actions=flat(rollout.actions),
        log_probs=flat(rollout.log_probs),
        values=flat(rollout.value),
        advantages=flat(advantages),
        targets=flat(targets),
        extras=jax.tree.map(flat, rollout.extras),
    )
    return value_norm, batch


def optimise(
    setup: TrainSetup, params: Params, opt_state: Any, batch: Batch, rng: jax.Array
) -> tuple[Params, Any, dict[str, jax.Array]]:
    """PPO epochs over shuffled minibatches; returns the loss metrics averaged over steps."""
    ppo = setup.config.ppo
    grad_fn = jax.value_and_grad(setup.algorithm.loss, has_aux=True)

    def minibatch_step(carry: tuple[Params, Any], minibatch: Batch) -> tuple[tuple[Params, Any], dict]:
        params, opt_state = carry
        (loss, metrics), grads = grad_fn(params, minibatch, ppo)
        updates, opt_state = setup.optimizer.update(grads, opt_state, params)
        metrics = {**metrics, "loss": loss, "grad_norm": optax.tree.norm(grads)}
        return (optax.apply_updates(params, updates), opt_state), metrics

    def epoch(carry: tuple[Params, Any], key: jax.Array) -> tuple[tuple[Params, Any], dict]:
        size = batch.advantages.shape[0]
        order = jax.random.permutation(key, size)
        minibatches = jax.tree.map(
            lambda x: x[order].reshape(ppo.num_minibatches, -1, *x.shape[1:]), batch
        )
        return jax.lax.scan(minibatch_step, carry, minibatches)

    (params, opt_state), metrics = jax.lax.scan(
        epoch, (params, opt_state), jax.random.split(rng, ppo.epochs)
    )
    return params, opt_state, jax.tree.map(jnp.mean, metrics)


def update_step(setup: TrainSetup, state: TrainerState) -> tuple[TrainerState, dict[str, jax.Array]]:
    """One PPO update of one seed: collect, estimate, optimise, soft-update the target critic."""
    state, rollout = collect_rollout(setup, state)
    return learn(setup, state, rollout)


def learn(
    setup: TrainSetup, state: TrainerState, rollout: Transition
) -> tuple[TrainerState, dict[str, jax.Array]]:
    """Everything of an update after collection: GAE from the target critic (bootstrapped from
    `state.timestep`, the observation after the rollout), PPO (or the algorithm's own
    `optimise`), the target critic's soft update and the rollout's episode sums. The host runner
    calls it on rollouts it collected outside the program."""
    value_norm, batch = make_batch(setup, state, rollout)
    rng, update_key = jax.random.split(state.rng)
    optimise_fn = getattr(setup.algorithm, "optimise", optimise)
    params, opt_state, metrics = optimise_fn(setup, state.params, state.opt_state, batch, update_key)
    target_params = optax.incremental_update(
        params, state.target_params, setup.config.ppo.target_tau
    )
    episodes = {
        "episodes": jnp.sum(rollout.done),
        "return_sum": jnp.sum(rollout.finished_return),
        "win_sum": jnp.sum(rollout.won & rollout.done),
    }
    state = state.replace(
        params=params, target_params=target_params, opt_state=opt_state,
        value_norm=value_norm, rng=rng, update_step=state.update_step + 1,
    )
    return state, {**metrics, **episodes}


def run_updates(
    setup: TrainSetup, state: TrainerState, num_updates: int
) -> tuple[TrainerState, dict[str, jax.Array]]:
    """`num_updates` updates in one scan; episode statistics pooled over the whole span."""
    state, per_update = jax.lax.scan(
        lambda s, _: update_step(setup, s), state, None, num_updates
    )
    return state, summarise_updates(setup, per_update)


def summarise_updates(setup: TrainSetup, per_update: dict[str, jax.Array]) -> dict[str, jax.Array]:
    """Metrics of updates stacked on a leading axis: losses averaged, episode sums pooled into
    the mean return and win rate of the episodes that ended in the span (NaN where none did)."""
    per_update = dict(per_update)
    episodes = jnp.sum(per_update.pop("episodes"))
    return_sum = jnp.sum(per_update.pop("return_sum"))
    win_sum = jnp.sum(per_update.pop("win_sum"))
    metrics = jax.tree.map(jnp.mean, per_update)
    metrics["episode_return"] = jnp.where(episodes > 0, return_sum / jnp.maximum(episodes, 1), jnp.nan)
    win_rate = jnp.where(episodes > 0, win_sum / jnp.maximum(episodes, 1), jnp.nan)
    metrics["win_rate"] = win_rate if setup.spec.has_win_rate else jnp.full_like(win_rate, jnp.nan)
    return metrics


def evaluate_greedy(
    setup: TrainSetup, params: Params, rng: jax.Array, episodes: int
) -> dict[str, jax.Array]:
    """Greedy episodes run in parallel; each environment's first episode is scored."""
    spec = setup.spec
    reset_key, rng = jax.random.split(rng)
    env_state, timestep = jax.vmap(setup.env.reset)(jax.random.split(reset_key, episodes))
    greedy = jax.vmap(setup.algorithm.greedy, in_axes=(None, 0, 0))

    def step(carry: tuple, key: jax.Array) -> tuple[tuple, None]:
        env_state, timestep, returns, won, finished = carry
        actions = env_actions(spec, greedy(params, timestep.obs, timestep.action_mask))
        env_state, timestep = jax.vmap(setup.env.step)(
            jax.random.split(key, episodes), env_state, actions
        )
        returns = returns + jnp.where(finished, 0.0, timestep.reward)
        won = jnp.where(finished, won, timestep.won & timestep.done)
        return (env_state, timestep, returns, won, finished | timestep.done), None

    zeros = jnp.zeros(episodes)
    carry = (env_state, timestep, zeros, zeros.astype(bool), zeros.astype(bool))
    (_, _, returns, won, _), _ = jax.lax.scan(
        step, carry, jax.random.split(rng, spec.max_episode_steps)
    )
    win_rate = jnp.mean(won.astype(jnp.float32))
    return {
        "episode_return": jnp.mean(returns),
        "win_rate": win_rate if spec.has_win_rate else jnp.full_like(win_rate, jnp.nan),
    }


def make_train(config: TrainConfig) -> Callable[[jax.Array], tuple[TrainerState, dict]]:
    """The whole run of one seed as one pure function of its key; `jax.jit` it.

    To train several seeds in one program, use `Trainer`: it vmaps the updates over seeds but
    initialises each seed on its own, because a vmapped orthogonal initialiser (batched QR)
    deadlocks XLA:CPU in jax 0.10.2 once a program holds about 16 of them.
    """
    setup = build_setup(config)

    def train(rng: jax.Array) -> tuple[TrainerState, dict[str, jax.Array]]:
        state = init_state(setup, rng)
        return jax.lax.scan(lambda s, _: update_step(setup, s), state, None, config.num_updates)

    return train


class Trainer:
    """The jitted programs of a run for all its seeds (leading axis of every state leaf)."""

    def __init__(self, config: TrainConfig) -> None:
        self.config = config
        self.setup = build_setup(config)
        self.env_spec = self.setup.spec
        chunk = config.updates_per_log
        self._init = jax.jit(lambda rng: init_state(self.setup, rng))
        self._chunk = jax.jit(
            jax.vmap(lambda state: run_updates(self.setup, state, chunk)), donate_argnums=0
        )
        self._evaluate = jax.jit(
            jax.vmap(
                lambda params, rng, episodes: evaluate_greedy(self.setup, params, rng, episodes),
                in_axes=(0, 0, None),
            ),
            static_argnums=2,
        )

    def seed_keys(self, offset: int = 0) -> jax.Array:
        seeds = self.config.seed + np.arange(self.config.seeds) + offset
        return jax.vmap(jax.random.PRNGKey)(jnp.asarray(seeds))

    def init(self) -> TrainerState:
        """Fresh state for every seed, initialised seed by seed (see `make_train`)."""
        states = [self._init(key) for key in self.seed_keys()]
        return jax.tree.map(lambda *leaves: jnp.stack(leaves), *states)

    def train_chunk(self, state: TrainerState) -> tuple[TrainerState, dict[str, np.ndarray]]:
        state, metrics = self._chunk(state)
        numbers = {key: np.asarray(value) for key, value in metrics.items()}
        numbers["env_steps"] = np.full(self.config.seeds, self.env_steps(state))
        return state, numbers

    def evaluate(self, state: TrainerState, episodes: int, seed: int = 0) -> dict[str, np.ndarray]:
        keys = self.seed_keys(offset=1_000_003 + seed)
        metrics = self._evaluate(state.params, keys, episodes)
        return {key: np.asarray(value) for key, value in metrics.items()}

    def env_steps(self, state: TrainerState) -> int:
        return int(np.asarray(state.update_step)[0]) * self.config.steps_per_update

    def to_bytes(self, state: TrainerState) -> bytes:
        return flax.serialization.to_bytes(state)

    def from_bytes(self, data: bytes) -> TrainerState:
        template = jax.eval_shape(self._init, self.seed_keys()[0])
        return restore_state(template, self.config.seeds, data)


def restore_state(template: TrainerState, seeds: int, data: bytes) -> TrainerState:
    """The all-seeds state serialised in `data`, checked against one seed's `template` (shapes
    and dtypes, e.g. from `jax.eval_shape`)."""
    template = jax.tree.map(lambda x: jax.ShapeDtypeStruct((seeds, *x.shape), x.dtype), template)
    try:
        restored = flax.serialization.from_bytes(template, data)
    except Exception as error:  # msgpack and flax raise many types for bad bytes
        raise CmatError(f"corrupt or incompatible checkpoint ({type(error).__name__})") from None
    expected = jax.tree.map(lambda x: (x.shape, x.dtype), template)
    found = jax.tree.map(lambda x: (np.shape(x), np.asarray(x).dtype), restored)
    if expected != found:
        raise CmatError("checkpoint does not match this run's config (shapes differ)")
    return jax.tree.map(jnp.asarray, restored)
