"""The compiled training program for in-graph (JAX) environments.

One update = rollout (`lax.scan` over steps, `vmap` over environments) → target-critic values →
GAE → PPO epochs × minibatches → soft update of the target critic (Algorithm 1). A chunk of
updates is one `lax.scan`, `vmap`ped over seeds and jitted as a single program; `make_train`
gives the whole run as one pure function, PureJaxRL style.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any, NamedTuple

import flax.serialization
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from cmat.algorithms import build_algorithm
from cmat.algorithms import ppo as ppo_lib
from cmat.algorithms.base import Algorithm, Batch, Params
from cmat.algorithms.sgd import finetune_optimizer
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
    alive: jax.Array
    """[n] agents active in `obs`."""
    global_state: jax.Array
    """[state_dim] the environment's global state at `obs`."""
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
    algorithm = build_algorithm(config.algo, config.network, env.spec, config.ppo)
    return TrainSetup(config, env, algorithm, build_optimizer(config, algorithm))


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
    """Actions as sent to the environment: continuous ones clipped to the spec's action range
    (host adapters then map it onto each agent's Box; the stored log-probability stays that of
    the unclipped sample)."""
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
        acted = jax.vmap(setup.algorithm.act, in_axes=(None, 0, 0, 0, 0))(
            state.params, observed.obs, observed.action_mask, act_keys, observed.global_state
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
            alive=observed.alive,
            global_state=observed.global_state,
            extras=acted.extras,
        )
        state = dataclasses.replace(
            state,
            env_state=env_state,
            timestep=timestep,
            episode_return=jnp.where(timestep.done, 0.0, running),
        )
        return state, transition

    rng, rollout_key = jax.random.split(state.rng)
    step_keys = jax.random.split(rollout_key, setup.config.rollout_length)
    state, rollout = jax.lax.scan(env_step, state, step_keys)
    return dataclasses.replace(state, rng=rng), rollout


def critic_values(
    setup: TrainSetup, params: Params, obs: jax.Array, global_state: jax.Array
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
    setup: TrainSetup, norm: ppo_lib.ValueNormState, v: jax.Array
) -> jax.Array:
    return ppo_lib.value_norm_denormalize(norm, v) if setup.config.ppo.value_norm else v


def make_batch(
    setup: TrainSetup, state: TrainerState, rollout: Transition
) -> tuple[ppo_lib.ValueNormState, Batch]:
    """GAE with the target critic V_φ- (Algorithm 1) and normalised value targets.

    Team values [T, envs] give one advantage per step; per-agent values [T, envs, n] (MAT's
    per-agent GAE) give one per agent, from the shared team reward and episode ends. With
    `ppo.active_masks` the advantages are normalised over active agents only (the reference
    MAT and MAPPO set inactive entries to NaN and take nanmean / nanstd)."""
    ppo = setup.config.ppo
    all_obs = jnp.concatenate([rollout.obs, state.timestep.obs[None]], axis=0)
    all_states = jnp.concatenate([rollout.global_state, state.timestep.global_state[None]], axis=0)
    target_values = value_to_returns_space(
        setup, state.value_norm, critic_values(setup, state.target_params, all_obs, all_states)
    )
    agent_axes = target_values.ndim - rollout.reward.ndim
    rewards = rollout.reward.reshape(*rollout.reward.shape, *(1,) * agent_axes)
    dones = rollout.done.reshape(*rollout.done.shape, *(1,) * agent_axes)
    advantages, returns = ppo_lib.generalized_advantages(
        rewards, target_values[:-1], dones, target_values[-1], ppo.gamma, ppo.gae_lambda,
    )
    value_norm = state.value_norm
    targets = returns
    if ppo.value_norm:
        value_norm = ppo_lib.value_norm_update(value_norm, returns)
        targets = ppo_lib.value_norm_normalize(value_norm, returns)
    if ppo.normalize_advantages:
        if ppo.active_masks:
            per_agent = advantages if agent_axes else advantages[..., None]
            statistics = jnp.broadcast_to(per_agent, rollout.alive.shape)
            normalised = ppo_lib.normalize(statistics, rollout.alive)
            advantages = normalised if agent_axes else normalised[..., 0]
        else:
            advantages = ppo_lib.normalize(advantages)

    def flat(x: jax.Array) -> jax.Array:
        return x.reshape(x.shape[0] * x.shape[1], *x.shape[2:])

    batch = Batch(
        obs=flat(rollout.obs),
        action_mask=flat(rollout.action_mask),
        actions=flat(rollout.actions),
        log_probs=flat(rollout.log_probs),
        values=flat(rollout.value),
        advantages=flat(advantages),
        targets=flat(targets),
        alive=flat(rollout.alive),
        global_state=flat(rollout.global_state),
        extras=jax.tree.map(flat, rollout.extras),
    )
    return value_norm, batch


def optimise(
    setup: TrainSetup, params: Params, opt_state: Any, batch: Batch, rng: jax.Array
) -> tuple[Params, Any, dict[str, jax.Array]]:
    """The algorithm's `update` of one rollout's batch with the run's optimiser and PPO config
    (for the shared PPO: `cmat.algorithms.sgd.minibatch_sgd` on its loss)."""
    return setup.algorithm.update(
        setup.optimizer, params, opt_state, batch, rng, setup.config.ppo
    )


def update_step(
    setup: TrainSetup, state: TrainerState
) -> tuple[TrainerState, dict[str, jax.Array]]:
    """One PPO update of one seed: collect, estimate, optimise, soft-update the target critic."""
    state, rollout = collect_rollout(setup, state)
    return learn(setup, state, rollout)


NONFINITE_QUANTITIES = ("loss", "gradient norm", "parameters")
"""What `nonfinite_code` k > 0 names: NONFINITE_QUANTITIES[k - 1]."""


def nonfinite_code(metrics: dict[str, jax.Array], params: Params) -> jax.Array:
    """0 if the update's loss, gradient norm and new parameters are all finite; else 1 + the
    index in `NONFINITE_QUANTITIES` of the first that is not (the loss and gradient norm are
    means over the update's minibatch steps, so one bad step makes them non-finite)."""
    params_finite = jnp.all(jnp.stack(
        [jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(params)]
    ))
    finite = jnp.stack([
        jnp.isfinite(metrics["loss"]), jnp.isfinite(metrics["grad_norm"]), params_finite
    ])
    return jnp.where(jnp.all(finite), 0, 1 + jnp.argmin(finite)).astype(jnp.int32)


def learn(
    setup: TrainSetup, state: TrainerState, rollout: Transition
) -> tuple[TrainerState, dict[str, jax.Array]]:
    """Everything of an update after collection: GAE from the target critic (bootstrapped from
    `state.timestep`, the observation after the rollout), the algorithm's `update`, the target
    critic's soft update and the rollout's episode sums. The host runner calls it on rollouts it
    collected outside the program."""
    value_norm, batch = make_batch(setup, state, rollout)
    rng, update_key = jax.random.split(state.rng)
    params, opt_state, metrics = optimise(setup, state.params, state.opt_state, batch, update_key)
    target_params = optax.incremental_update(
        params, state.target_params, setup.config.ppo.target_tau
    )
    rollout_metrics = {
        "explained_variance": ppo_lib.explained_variance(batch.values, batch.targets),
        "episodes": jnp.sum(rollout.done),
        "return_sum": jnp.sum(rollout.finished_return),
        "win_sum": jnp.sum(rollout.won & rollout.done),
        "nonfinite": nonfinite_code(metrics, params),
    }
    state = dataclasses.replace(
        state, params=params, target_params=target_params, opt_state=opt_state,
        value_norm=value_norm, rng=rng, update_step=state.update_step + 1,
    )
    return state, {**metrics, **rollout_metrics}


def run_updates(
    setup: TrainSetup, state: TrainerState, max_updates: int, updates: jax.Array
) -> tuple[TrainerState, dict[str, jax.Array]]:
    """`updates` (≤ `max_updates`, traced) updates in one scan of `max_updates` steps: the
    steps past `updates` leave the state as it is, so one compiled program also runs a run's
    shorter last chunk. Episode statistics are pooled over the updates done."""

    def step(state: TrainerState, index: jax.Array) -> tuple[TrainerState, dict[str, jax.Array]]:
        shapes = jax.eval_shape(lambda s: update_step(setup, s)[1], state)
        skipped = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)
        state, metrics = jax.lax.cond(
            index < updates, lambda s: update_step(setup, s), lambda s: (s, skipped), state
        )
        return state, {**metrics, "performed": index < updates}

    state, per_update = jax.lax.scan(step, state, jnp.arange(max_updates))
    return state, summarise_updates(setup, per_update)


def summarise_updates(
    setup: TrainSetup, per_update: dict[str, jax.Array]
) -> dict[str, jax.Array]:
    """Metrics of updates stacked on a leading axis: losses averaged over the updates performed
    (`performed`, all where absent), episode sums pooled into the mean return and win rate of
    the episodes that ended in the span (NaN where none did). `nonfinite_update` is the index of
    the first update whose loss, gradient norm or parameters were not finite (-1 if none) and
    `nonfinite_code` what was (`nonfinite_code`)."""
    per_update = dict(per_update)
    codes = per_update.pop("nonfinite")
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
    metrics["win_rate"] = win_rate if setup.spec.has_win_rate else jnp.full_like(win_rate, jnp.nan)
    bad = performed & (codes > 0)
    first = jnp.argmax(bad)
    metrics["nonfinite_update"] = jnp.where(jnp.any(bad), first, -1)
    metrics["nonfinite_code"] = jnp.where(jnp.any(bad), codes[first], 0)
    return metrics


def evaluate_greedy(
    setup: TrainSetup, params: Params, rng: jax.Array, episodes: int
) -> dict[str, jax.Array]:
    """Greedy episodes run in parallel; each environment's first episode is scored."""
    spec = setup.spec
    reset_key, rng = jax.random.split(rng)
    env_state, timestep = jax.vmap(setup.env.reset)(jax.random.split(reset_key, episodes))
    greedy = jax.vmap(setup.algorithm.greedy, in_axes=(None, 0, 0))

    Carry = tuple[Any, TimeStep, jax.Array, jax.Array, jax.Array]

    def step(carry: Carry, key: jax.Array) -> tuple[Carry, None]:
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


def make_train(
    config: TrainConfig,
) -> Callable[[jax.Array], tuple[TrainerState, dict[str, jax.Array]]]:
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
            jax.vmap(
                lambda state, updates: run_updates(self.setup, state, chunk, updates),
                in_axes=(0, None),
            ),
            donate_argnums=0,
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
        stacked: TrainerState = jax.tree.map(lambda *leaves: jnp.stack(leaves), *states)
        return stacked

    def train_chunk(
        self, state: TrainerState, updates: int | None = None
    ) -> tuple[TrainerState, dict[str, np.ndarray]]:
        """`updates` (default and at most `updates_per_log`) updates of every seed."""
        updates = self.config.updates_per_log if updates is None else updates
        if not 0 < updates <= self.config.updates_per_log:
            raise ValueError(f"updates must be in 1..{self.config.updates_per_log}, got {updates}")
        state, metrics = self._chunk(state, jnp.asarray(updates, jnp.int32))
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


ADDED_TIMESTEP_FIELDS = {"alive": True, "global_state": 0.0}
"""`TimeStep` fields newer than the first checkpoint format, with the value a checkpoint
without them gets: every agent active, a zero global state. They describe only the
observation in progress when the checkpoint was written, so a resumed run's first step at most
sees them wrong; everything learned is restored exactly."""


def fill_added_timestep_fields(raw: Any, template: TrainerState) -> None:
    """Add `ADDED_TIMESTEP_FIELDS` to a restored state dict that lacks them (in place)."""
    if not isinstance(raw, dict) or not isinstance(raw.get("timestep"), dict):
        return
    for name, value in ADDED_TIMESTEP_FIELDS.items():
        if name not in raw["timestep"]:
            shape = getattr(template.timestep, name)
            raw["timestep"][name] = np.full(shape.shape, value, shape.dtype)


def restore_state(template: TrainerState, seeds: int, data: bytes) -> TrainerState:
    """The all-seeds state serialised in `data`, checked against one seed's `template` (shapes
    and dtypes, e.g. from `jax.eval_shape`)."""
    template = jax.tree.map(lambda x: jax.ShapeDtypeStruct((seeds, *x.shape), x.dtype), template)
    try:
        raw = flax.serialization.msgpack_restore(data)
        fill_added_timestep_fields(raw, template)
        restored = flax.serialization.from_state_dict(template, raw)
    except Exception as error:  # msgpack and flax raise many types for bad bytes
        raise CmatError(f"corrupt or incompatible checkpoint ({type(error).__name__})") from None
    expected = jax.tree.map(lambda x: (x.shape, x.dtype), template)
    found = jax.tree.map(lambda x: (np.shape(x), np.asarray(x).dtype), restored)
    if expected != found:
        raise CmatError("checkpoint does not match this run's config (shapes differ)")
    state: TrainerState = jax.tree.map(jnp.asarray, restored)
    return state
