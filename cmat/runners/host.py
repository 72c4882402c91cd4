"""Training on host environments (MuJoCo, GRF, PettingZoo): `HostTrainer`, `Trainer`'s twin.

Only the rollout loop differs from the in-graph trainer. Each step is one jitted call of the
algorithm's `act`, vmapped over every environment of every seed, then one `step` of the host
pool (`cmat.envs.host.pool`, in-process or in worker processes). The rollout, stacked to
[T, seeds, envs, ...], goes through the in-graph trainer's own `learn` (target-critic GAE, the
algorithm's `update`, target soft update), jitted and vmapped over seeds; metrics
are pooled by its `summarise_updates`. Greedy evaluation runs on a second pool, so training
episodes are not cut by it.

Seeds: seed k runs its own `num_envs` environments (env slot i of all seeds is i + k·num_envs in
the pool). Checkpoints hold what `Trainer`'s do; host simulator state cannot be saved, so a
resumed run starts fresh episodes (the ones running at the checkpoint are dropped).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import partial
from typing import Any

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np

from cmat.algorithms import ppo as ppo_lib
from cmat.algorithms.base import ActResult, Params
from cmat.config import TrainConfig
from cmat.envs.host import default_workers, make_host_env
from cmat.envs.host.pool import COUNTERS, InProcessPool, WorkerPool, make_pool
from cmat.envs.host.protocol import HostBatch
from cmat.envs.protocol import EnvSpec, TimeStep
from cmat.runners.trainer import (
    TrainerState,
    TrainSetup,
    Transition,
    build_setup,
    env_actions,
    learn,
    restore_state,
    summarise_updates,
)


@dataclass(frozen=True)
class SpecOnly:
    """The `env` of a host run's `TrainSetup`: `learn` reads only its spec."""

    spec: EnvSpec


def host_state(
    setup: TrainSetup, rng: jax.Array, obs: jax.Array, mask: jax.Array, alive: jax.Array,
    global_state: jax.Array,
) -> TrainerState:
    """A fresh state of one seed whose environments show `obs`, `mask`, `alive`,
    `global_state` [envs, ...]; no environment state lives in it (`env_state` is empty)."""
    rng, init_key = jax.random.split(rng)
    params = setup.algorithm.init(init_key, obs[0], mask[0])
    envs = obs.shape[0]
    zeros = jnp.zeros(envs, bool)
    return TrainerState(
        params=params,
        target_params=params,
        opt_state=setup.optimizer.init(params),
        value_norm=ppo_lib.value_norm_init(),
        env_state=(),
        timestep=TimeStep(obs, mask, jnp.zeros(envs), zeros, zeros, alive, global_state),
        episode_return=jnp.zeros(envs),
        rng=rng,
        update_step=jnp.zeros((), jnp.int32),
    )


def policy_step(
    setup: TrainSetup, params: Params, rng: jax.Array, obs: jax.Array, mask: jax.Array,
    global_state: jax.Array | None = None,
) -> tuple[jax.Array, ActResult, jax.Array]:
    """Sample actions for every environment of every seed ([seeds, envs, ...]); returns the
    seeds' next keys, what `act` returned, and the actions to send (`env_actions`).
    `global_state` [seeds, envs, state_dim] may be left out where the env has none."""
    envs = obs.shape[1]
    if global_state is None:
        global_state = jnp.zeros((*obs.shape[:2], 0))
    keys = jax.vmap(jax.random.split)(rng)
    act_keys = jax.vmap(lambda key: jax.random.split(key, envs))(keys[:, 1])
    act = jax.vmap(jax.vmap(setup.algorithm.act, in_axes=(None, 0, 0, 0, 0)))
    acted = act(params, obs, mask, act_keys, global_state)
    return keys[:, 0], acted, env_actions(setup.spec, acted.actions)


def greedy_step(setup: TrainSetup, params: Params, obs: jax.Array, mask: jax.Array) -> jax.Array:
    """Greedy actions to send for every environment of every seed."""
    greedy = jax.vmap(jax.vmap(setup.algorithm.greedy, in_axes=(None, 0, 0)))
    return env_actions(setup.spec, greedy(params, obs, mask))


def env_seeds(base: int, stream: int, count: int) -> list[int]:
    """`count` distinct simulator seeds for seed `base`; `stream` 0 trains, 1 evaluates."""
    return [int(s) for s in np.random.SeedSequence([base, stream]).generate_state(count)]


def split_evenly(total: int, parts: int) -> np.ndarray:
    """`parts` non-negative counts summing to `total`, as equal as possible."""
    return np.diff(np.linspace(0, total, parts + 1).round().astype(int))


class HostTrainer:
    """`Trainer`'s interface (init, train_chunk, evaluate, env_steps, to_bytes, from_bytes) for
    host environments; `run_training` and the CLI drive it unchanged."""

    def __init__(self, config: TrainConfig) -> None:
        self.config = config
        self.workers = (
            config.host_workers if config.host_workers is not None else default_workers(config.env)
        )
        probe = make_host_env(config.env, seed=config.seed, nonfinite=config.host_nonfinite,
                              **config.env_kwargs)
        self.env_spec = probe.spec
        self._spare = [probe]  # becomes the first environment of an in-process pool
        self.setup = build_setup(config, SpecOnly(self.env_spec))  # type: ignore[arg-type]
        self._init = jax.jit(partial(host_state, self.setup))
        self._policy = jax.jit(partial(policy_step, self.setup))
        self._greedy = jax.jit(partial(greedy_step, self.setup))
        self._learn = jax.jit(
            jax.vmap(partial(learn, self.setup), in_axes=(0, 1)), donate_argnums=0
        )
        self._summarise = jax.jit(jax.vmap(partial(summarise_updates, self.setup)))
        self._pool: InProcessPool | WorkerPool | None = None
        self._eval_pool: InProcessPool | WorkerPool | None = None
        self._eval_size = 0
        self._timestep: HostBatch | None = None
        self._episode_return = np.zeros((config.seeds, config.num_envs), np.float32)

    # ----------------------------------------------------------------------------- environments
    def _seeds(self, stream: int, per_seed: int) -> list[int]:
        config = self.config
        return [s for k in range(config.seeds)
                for s in env_seeds(config.seed + k, stream, per_seed)]

    def _new_pool(self, seeds: list[int]) -> InProcessPool | WorkerPool:
        spare, self._spare = self._spare, []
        config = self.config
        return make_pool(config.env, config.env_kwargs, seeds, self.workers, spare,
                         config.host_crash_limit, config.host_nonfinite)

    def _start_episodes(self) -> HostBatch:
        """Build the training pool if needed and start an episode in every environment."""
        if self._pool is None:
            self._pool = self._new_pool(self._seeds(0, self.config.num_envs))
        self._timestep = self._pool.reset()
        self._episode_return[:] = 0.0
        return self._timestep

    def _per_seed(self, batch: np.ndarray) -> np.ndarray:
        """[seeds·envs, ...] → [seeds, envs, ...]."""
        seeds = self.config.seeds
        return batch.reshape(seeds, batch.shape[0] // seeds, *batch.shape[1:])

    def _state_timestep(self, timestep: HostBatch) -> TimeStep:
        return TimeStep(*(jnp.asarray(self._per_seed(np.asarray(x))) for x in timestep))

    def close(self) -> None:
        """Stop the environments (worker processes included)."""
        for pool in (self._pool, self._eval_pool):
            if pool is not None:
                pool.close()
        self._pool = self._eval_pool = self._timestep = None
        for env in self._spare:
            env.close()
        self._spare = []

    def worker_pids(self) -> list[int]:
        """Process ids of the training pool's workers (empty in-process)."""
        return self._pool.worker_pids() if self._pool is not None else []

    def env_counters(self) -> dict[str, np.ndarray]:
        """Per seed, over its training environments so far: simulator restarts
        (`env_restarts`) and non-finite values replaced by 0 (`env_nonfinite`)."""
        if self._pool is None:
            return {name: np.zeros(self.config.seeds, np.int64) for name in COUNTERS}
        return {name: self._per_seed(values).sum(axis=1)
                for name, values in self._pool.counters().items()}

    # --------------------------------------------------------------------------------- training
    def seed_keys(self, offset: int = 0) -> jax.Array:
        seeds = self.config.seed + np.arange(self.config.seeds) + offset
        return jax.vmap(jax.random.PRNGKey)(jnp.asarray(seeds))

    def init(self) -> TrainerState:
        """Fresh state for every seed, initialised seed by seed (see `trainer.make_train`)."""
        timestep = self._start_episodes()
        obs, mask = self._per_seed(timestep.obs), self._per_seed(timestep.action_mask)
        alive, global_state = self._per_seed(timestep.alive), self._per_seed(timestep.global_state)
        states = [
            self._init(key, obs[k], mask[k], alive[k], global_state[k])
            for k, key in enumerate(self.seed_keys())
        ]
        stacked: TrainerState = jax.tree.map(lambda *leaves: jnp.stack(leaves), *states)
        return stacked

    def collect(self, state: TrainerState) -> tuple[TrainerState, Transition]:
        """`rollout_length` steps of every environment with the state's parameters; the state
        comes back with the last observation (for bootstrapping) and the advanced key."""
        assert self._pool is not None and self._timestep is not None
        timestep, rng = self._timestep, state.rng
        running = self._episode_return
        steps = []
        for _ in range(self.config.rollout_length):
            obs = self._per_seed(timestep.obs)
            mask = self._per_seed(timestep.action_mask)
            alive, global_state = (
                self._per_seed(timestep.alive), self._per_seed(timestep.global_state)
            )
            rng, acted, actions = self._policy(state.params, rng, obs, mask, global_state)
            actions = np.asarray(actions)
            timestep = self._pool.step(actions.reshape(-1, *actions.shape[2:]))
            reward, done = self._per_seed(timestep.reward), self._per_seed(timestep.done)
            running = running + reward
            steps.append((obs, mask, acted, reward, done, self._per_seed(timestep.won),
                          np.where(done, running, 0.0).astype(np.float32), alive, global_state))
            running = np.where(done, 0.0, running).astype(np.float32)
        self._timestep, self._episode_return = timestep, running
        (obs_t, mask_t, acted_t, reward_t, done_t, won_t, finished_t, alive_t,
         global_state_t) = zip(*steps)
        acted = jax.tree.map(lambda *x: jnp.stack(x), *acted_t)
        rollout = Transition(
            obs=jnp.asarray(np.stack(obs_t)),
            action_mask=jnp.asarray(np.stack(mask_t)),
            actions=acted.actions,
            log_probs=acted.log_probs,
            value=acted.value,
            reward=jnp.asarray(np.stack(reward_t)),
            done=jnp.asarray(np.stack(done_t)),
            won=jnp.asarray(np.stack(won_t)),
            finished_return=jnp.asarray(np.stack(finished_t)),
            alive=jnp.asarray(np.stack(alive_t)),
            global_state=jnp.asarray(np.stack(global_state_t)),
            extras=acted.extras,
        )
        state = dataclasses.replace(
            state, timestep=self._state_timestep(timestep), episode_return=jnp.asarray(running),
            rng=rng,
        )
        return state, rollout

    def train_chunk(
        self, state: TrainerState, updates: int | None = None
    ) -> tuple[TrainerState, dict[str, np.ndarray]]:
        """`updates` (default `updates_per_log`) updates: collect on the host, then the jitted
        `learn`."""
        if self._timestep is None:  # after from_bytes: the simulators' episodes restart
            self._start_episodes()
        per_update = []
        for _ in range(self.config.updates_per_log if updates is None else updates):
            state, rollout = self.collect(state)
            state, metrics = self._learn(state, rollout)
            per_update.append(metrics)
        stacked = jax.tree.map(lambda *x: jnp.stack(x, axis=1), *per_update)
        numbers = {key: np.asarray(value) for key, value in self._summarise(stacked).items()}
        numbers["env_steps"] = np.full(self.config.seeds, self.env_steps(state))
        numbers.update(self.env_counters())
        return state, numbers

    # ------------------------------------------------------------------------------- evaluation
    def evaluate(self, state: TrainerState, episodes: int, seed: int = 0) -> dict[str, np.ndarray]:
        """Mean greedy return (and win rate) of `episodes` episodes per seed.

        They run on min(episodes, num_envs) environments per seed, each playing a fixed quota of
        whole episodes one after another, so short episodes are not over-counted. The same
        `seed` gives the same simulator seeds."""
        config, spec = self.config, self.env_spec
        slots = min(episodes, config.num_envs)
        if self._eval_pool is None or self._eval_size != slots:
            if self._eval_pool is not None:
                self._eval_pool.close()
            self._eval_pool = self._new_pool(self._seeds(1, slots))
            self._eval_size = slots
        base = config.seed + 1_000_003 + seed
        seeds = [s for k in range(config.seeds) for s in env_seeds(base + k, 1, slots)]
        timestep = self._eval_pool.reset(seeds)
        quota = np.tile(split_evenly(episodes, slots), (config.seeds, 1))
        running = np.zeros((config.seeds, slots))
        total = np.zeros((config.seeds, slots))
        wins = np.zeros((config.seeds, slots))
        finished = np.zeros((config.seeds, slots), int)
        for _ in range(int(quota.max()) * spec.max_episode_steps):
            if np.all(finished >= quota):
                break
            obs, mask = self._per_seed(timestep.obs), self._per_seed(timestep.action_mask)
            actions = np.asarray(self._greedy(state.params, obs, mask))
            timestep = self._eval_pool.step(actions.reshape(-1, *actions.shape[2:]))
            done = self._per_seed(timestep.done)
            running += self._per_seed(timestep.reward)
            counted = done & (finished < quota)
            total += np.where(counted, running, 0.0)
            wins += counted & self._per_seed(timestep.won)
            finished += done
            running = np.where(done, 0.0, running)
        unfinished = finished < quota  # an env that never ended: its running episode counts
        total += np.where(unfinished, running, 0.0)
        win_rate = wins.sum(axis=1) / episodes
        return {
            "episode_return": (total.sum(axis=1) / episodes).astype(np.float32),
            "win_rate": (win_rate if spec.has_win_rate else np.full_like(win_rate, np.nan))
            .astype(np.float32),
        }

    # ------------------------------------------------------------------------------ checkpoints
    def env_steps(self, state: TrainerState) -> int:
        return int(np.asarray(state.update_step)[0]) * self.config.steps_per_update

    def to_bytes(self, state: TrainerState) -> bytes:
        return flax.serialization.to_bytes(state)

    def from_bytes(self, data: bytes) -> TrainerState:
        """The state in `data`; training then starts fresh episodes (module docstring)."""
        spec, envs = self.env_spec, self.config.num_envs
        obs = jax.ShapeDtypeStruct((envs, spec.num_agents, spec.obs_dim), jnp.float32)
        mask = jax.ShapeDtypeStruct((envs, spec.num_agents, spec.action_dim), jnp.bool_)
        alive = jax.ShapeDtypeStruct((envs, spec.num_agents), jnp.bool_)
        global_state = jax.ShapeDtypeStruct((envs, spec.state_dim), jnp.float32)
        template = jax.eval_shape(self._init, self.seed_keys()[0], obs, mask, alive, global_state)
        state = restore_state(template, self.config.seeds, data)
        self._timestep = None
        return state


def build_trainer(config: TrainConfig) -> Any:
    """`HostTrainer` for host environment ids, `Trainer` for in-graph ones."""
    from cmat.envs.host import is_host_env
    from cmat.runners.trainer import Trainer

    return HostTrainer(config) if is_host_env(config.env) else Trainer(config)
