"""Training on host environments (MuJoCo, GRF, PettingZoo): `HostTrainer`.

Only collection differs from `JaxTrainer`. Each step is one jitted call of the algorithm's
`act_with_memory`, vmapped over every environment of every seed, then one `step` of the host pool
(`cmat.envs.host.pool`, in-process or in worker processes). The rollout, stacked to
[T, seeds, envs, ...], goes to the shared learner's `learn` (cmat.runners.learner), jitted and
vmapped over seeds. Greedy evaluation (cmat.runners.evaluation) runs on a second pool, so
training episodes are not cut by it. A recurrent algorithm's state (`memory`, [seeds, envs, ...])
is carried from step to step on the host side of the loop and reset where an episode starts, as
the in-graph collector does; each rollout records the state it began with.

Seeds: seed k runs its own `num_envs` environments (env slot i of all seeds is i + k·num_envs in
the pool). Checkpoints hold the learner's state (cmat.runners.base); host simulator state cannot
be saved, so a resumed run starts fresh episodes (the ones running at the checkpoint are
dropped) from a fresh recurrent state.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from cmat.algorithms import algorithm_entry
from cmat.algorithms.base import ActResult, Params, initial_memories, with_memory
from cmat.config import TrainConfig
from cmat.envs.host import default_workers, make_host_env
from cmat.envs.host.pool import COUNTERS, InProcessPool, WorkerPool, make_pool
from cmat.envs.host.protocol import HostBatch
from cmat.runners.base import (
    EVAL_SEED_OFFSET,
    TrainerState,
    restore_state,
    seed_keys,
    single_threaded_lapack,
    stack_seeds,
    state_to_bytes,
)
from cmat.runners.collector import env_actions, rollout_report
from cmat.runners.devices import compiler_options
from cmat.runners.evaluation import split_evenly, tally_result, tally_start, tally_step
from cmat.runners.learner import (
    LearnerSetup,
    LearnerState,
    build_learner,
    init_learner,
    learn,
    summarise_updates,
)
from cmat.runners.types import Rollout, Transition


def host_learner(
    setup: LearnerSetup, rng: jax.Array, obs: jax.Array, mask: jax.Array
) -> LearnerState:
    """A fresh learner of one seed whose environments show `obs` and `mask` [envs, ...]."""
    rng, init_key = jax.random.split(rng)
    return init_learner(setup, init_key, rng, obs[0], mask[0])


def policy_step(
    setup: LearnerSetup, params: Params, rng: jax.Array, memory: Any, obs: jax.Array,
    mask: jax.Array, global_state: jax.Array, start: jax.Array,
) -> tuple[jax.Array, ActResult, jax.Array, Any]:
    """Sample actions for every environment of every seed ([seeds, envs, ...]; `params` per
    seed) from the state `memory` after the previous step (reset where `start` [seeds, envs]
    begins an episode); returns the seeds' next keys, what `act_with_memory` returned, the
    actions to send (`env_actions`) and the new state."""
    envs = obs.shape[1]
    keys = jax.vmap(jax.random.split)(rng)
    act_keys = jax.vmap(lambda key: jax.random.split(key, envs))(keys[:, 1])
    stepper = with_memory(setup.algorithm)
    act = jax.vmap(jax.vmap(stepper.act_with_memory, in_axes=(None, 0, 0, 0, 0, 0, 0)))
    acted, memory = act(params, memory, obs, mask, act_keys, global_state, start)
    return keys[:, 0], acted, env_actions(setup.spec, acted.actions), memory


def eval_step(
    setup: LearnerSetup, sample: bool, params: Params, memory: Any, obs: jax.Array,
    mask: jax.Array, start: jax.Array, global_state: jax.Array, key: jax.Array,
) -> tuple[jax.Array, Any]:
    """Evaluation actions to send for every environment of every seed, greedy or (`sample`)
    drawn from the policy with `key`, and the new state."""
    stepper = with_memory(setup.algorithm)
    if sample:
        keys = jax.random.split(key, obs.shape[:2])
        act = jax.vmap(jax.vmap(stepper.act_with_memory,
                                in_axes=(None, 0, 0, 0, 0, 0, 0)), in_axes=(0, 0, 0, 0, 0, 0, 0))
        acted, memory = act(params, memory, obs, mask, keys, global_state, start)
        return env_actions(setup.spec, acted.actions), memory
    greedy = jax.vmap(jax.vmap(stepper.greedy_with_memory, in_axes=(None, 0, 0, 0, 0)))
    actions, memory = greedy(params, memory, obs, mask, start)
    return env_actions(setup.spec, actions), memory


def env_seeds(base: int, stream: int, count: int, episode_seed: int | None = None) -> list[int]:
    """`count` distinct simulator seeds for seed `base`; `stream` 0 trains, 1 evaluates (the
    evaluation episodes `episode_seed`, `Trainer.evaluate`)."""
    entropy = [base, stream] if episode_seed is None else [base, stream, episode_seed]
    return [int(s) for s in np.random.SeedSequence(entropy).generate_state(count)]


class HostTrainer:
    """The `Trainer` (cmat.runners.base) of host environments: a host collector (the pool)
    beside the shared learner, driven by `run_training` and the CLI like `JaxTrainer`."""

    def __init__(self, config: TrainConfig) -> None:
        self.config = config
        self.workers = (
            config.host_workers if config.host_workers is not None else default_workers(config.env)
        )
        probe = make_host_env(config.env, seed=config.seed, nonfinite=config.host_nonfinite,
                              **config.env_kwargs)
        self.env_spec = probe.spec
        self._reference = probe.description()
        self._spare = [probe]  # becomes the first environment of an in-process pool
        self.learner_setup = build_learner(config, self.env_spec)
        options = compiler_options(algorithm_entry(config.algo).ynnpack_matmuls)
        self._init = jax.jit(partial(host_learner, self.learner_setup), compiler_options=options)
        self._policy = jax.jit(partial(policy_step, self.learner_setup), compiler_options=options)
        self._eval_step = jax.jit(
            partial(eval_step, self.learner_setup, config.eval_actions == "sample"),
            compiler_options=options)
        self._report = jax.jit(jax.vmap(rollout_report, in_axes=1))
        self._learn = jax.jit(
            jax.vmap(partial(learn, self.learner_setup), in_axes=(0, Rollout._make((1, 0, 0, 0)))),
            donate_argnums=0,
            compiler_options=options,
        )
        self._summarise = jax.jit(jax.vmap(partial(summarise_updates, self.env_spec)))
        self._pool: InProcessPool | WorkerPool | None = None
        self._eval_pool: InProcessPool | WorkerPool | None = None
        self._eval_size = 0
        self._timestep: HostBatch | None = None
        self._episode_return = np.zeros((config.seeds, config.num_envs), np.float32)
        self._memory: Any = initial_memories(self.learner_setup.algorithm, config.seeds,
                                             config.num_envs)

    # ----------------------------------------------------------------------------- environments
    def _seeds(self, stream: int, per_seed: int) -> list[int]:
        config = self.config
        return [s for k in range(config.seeds)
                for s in env_seeds(config.seed + k, stream, per_seed)]

    def _new_pool(self, seeds: list[int]) -> InProcessPool | WorkerPool:
        spare, self._spare = self._spare, []
        config = self.config
        return make_pool(config.env, config.env_kwargs, seeds, self.workers, spare,
                         config.host_crash_limit, config.host_nonfinite, self._reference)

    def _start_episodes(self) -> HostBatch:
        """Build the training pool if needed and start an episode in every environment."""
        if self._pool is None:
            self._pool = self._new_pool(self._seeds(0, self.config.num_envs))
        self._timestep = self._pool.reset()
        self._episode_return[:] = 0.0
        self._memory = initial_memories(self.learner_setup.algorithm, self.config.seeds,
                                        self.config.num_envs)
        return self._timestep

    def _per_seed(self, batch: np.ndarray) -> np.ndarray:
        """[seeds·envs, ...] → [seeds, envs, ...]."""
        seeds = self.config.seeds
        return batch.reshape(seeds, batch.shape[0] // seeds, *batch.shape[1:])

    def close(self) -> None:
        """Stop the environments (worker processes included)."""
        for pool in (self._pool, self._eval_pool):
            if pool is not None:
                pool.close()
        self._pool = self._eval_pool = self._timestep = None
        for env in self._spare:
            env.close()
        self._spare = []

    def env_counters(self) -> dict[str, np.ndarray]:
        """Per seed, over its training environments so far: simulator restarts
        (`env_restarts`) and non-finite values replaced by 0 (`env_nonfinite`)."""
        if self._pool is None:
            return {name: np.zeros(self.config.seeds, np.int64) for name in COUNTERS}
        return {name: self._per_seed(values).sum(axis=1)
                for name, values in self._pool.counters().items()}

    # --------------------------------------------------------------------------------- training
    def init(self) -> TrainerState:
        """Fresh state for every seed, initialised seed by seed (see `trainer.make_train`)."""
        timestep = self._start_episodes()
        obs, mask = self._per_seed(timestep.obs), self._per_seed(timestep.action_mask)
        with single_threaded_lapack():
            learners = [self._init(key, obs[k], mask[k])
                        for k, key in enumerate(seed_keys(self.config))]
        return stack_seeds([TrainerState(learner, None) for learner in learners])

    def collect(self, learner: LearnerState) -> tuple[LearnerState, Rollout]:
        """The host collector: `rollout_length` steps of every environment with the learner's
        parameters ([T, seeds, envs, ...]); the learner comes back with its advanced key."""
        assert self._pool is not None and self._timestep is not None
        timestep, rng = self._timestep, learner.rng
        running, memory = self._episode_return, self._memory
        first_memory = memory
        steps = []
        for _ in range(self.config.rollout_length):
            obs = self._per_seed(timestep.obs)
            mask = self._per_seed(timestep.action_mask)
            alive, global_state, start = (
                self._per_seed(timestep.alive), self._per_seed(timestep.global_state),
                self._per_seed(timestep.done),
            )
            rng, acted, actions, memory = self._policy(learner.params, rng, memory, obs, mask,
                                                       global_state, start)
            actions = np.asarray(actions)
            timestep = self._pool.step(actions.reshape(-1, *actions.shape[2:]))
            reward, done = self._per_seed(timestep.reward), self._per_seed(timestep.done)
            running = running + reward
            steps.append((obs, mask, acted, reward, done, self._per_seed(timestep.won),
                          np.where(done, running, 0.0).astype(np.float32), alive, global_state,
                          start))
            running = np.where(done, 0.0, running).astype(np.float32)
        self._timestep, self._episode_return, self._memory = timestep, running, memory
        (obs_t, mask_t, acted_t, reward_t, done_t, won_t, finished_t, alive_t,
         global_state_t, start_t) = zip(*steps, strict=True)
        acted = jax.tree.map(lambda *x: jnp.stack(x), *acted_t)
        transitions = Transition(
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
            start=jnp.asarray(np.stack(start_t)),
        )
        rollout = Rollout(transitions, jnp.asarray(self._per_seed(timestep.obs)),
                          jnp.asarray(self._per_seed(timestep.global_state)), first_memory)
        return dataclasses.replace(learner, rng=rng), rollout

    def train_chunk(
        self, state: TrainerState, updates: int | None = None
    ) -> tuple[TrainerState, dict[str, np.ndarray]]:
        """`updates` (default `updates_per_log`) updates: collect on the host, then the jitted
        `learn`."""
        if self._timestep is None:  # after from_bytes: the simulators' episodes restart
            self._start_episodes()
        learner = state.learner
        per_update = []
        for _ in range(self.config.updates_per_log if updates is None else updates):
            learner, rollout = self.collect(learner)
            learner, metrics = self._learn(learner, rollout)
            per_update.append({**metrics, **self._report(rollout.steps)})
        state = TrainerState(learner, None)
        stacked = jax.tree.map(lambda *x: jnp.stack(x, axis=1), *per_update)
        numbers = {key: np.asarray(value) for key, value in self._summarise(stacked).items()}
        numbers["env_steps"] = np.full(self.config.seeds, self.env_steps(state))
        numbers.update(self.env_counters())
        return state, numbers

    # ------------------------------------------------------------------------------- evaluation
    def evaluate(
        self, state: TrainerState, episodes: int, episode_seed: int = 0
    ) -> dict[str, np.ndarray]:
        """Evaluation episodes (greedy or sampled: `TrainConfig.eval_actions`) on a second pool,
        so training episodes are not cut: min(episodes, num_envs) slots per seed
        (cmat.runners.evaluation). The same `episode_seed` gives the same simulator seeds and
        samples (`Trainer.evaluate`)."""
        config, spec = self.config, self.env_spec
        slots = min(episodes, config.num_envs)
        if self._eval_pool is None or self._eval_size != slots:
            if self._eval_pool is not None:
                self._eval_pool.close()
            self._eval_pool = self._new_pool(self._seeds(1, slots))
            self._eval_size = slots
        base = config.seed + EVAL_SEED_OFFSET
        seeds = [s for k in range(config.seeds)
                 for s in env_seeds(base + k, 1, slots, episode_seed)]
        timestep = self._eval_pool.reset(seeds)
        quota = np.tile(split_evenly(episodes, slots), (config.seeds, 1))
        tally = tally_start((config.seeds, slots), spec)
        memory = initial_memories(self.learner_setup.algorithm, config.seeds, slots)
        key = jax.random.fold_in(jax.random.PRNGKey(base), episode_seed)
        for _ in range(int(quota.max()) * spec.max_episode_steps):
            if np.all(tally.finished >= quota):
                break
            obs, mask = self._per_seed(timestep.obs), self._per_seed(timestep.action_mask)
            key, act_key = jax.random.split(key)
            actions, memory = self._eval_step(
                state.learner.params, memory, obs, mask, self._per_seed(timestep.done),
                self._per_seed(timestep.global_state), act_key)
            actions = np.asarray(actions)
            more = (tally.finished + 1 < quota).reshape(-1)  # else the slot's last episode
            timestep = self._eval_pool.step(actions.reshape(-1, *actions.shape[2:]), more)
            tally = tally_step(tally, self._per_seed(timestep.reward),
                               self._per_seed(timestep.done), self._per_seed(timestep.won), quota)
        result: dict[str, np.ndarray] = tally_result(tally, quota, episodes, spec)
        return result

    # ------------------------------------------------------------------------------ checkpoints
    def env_steps(self, state: TrainerState) -> int:
        return int(np.asarray(state.learner.update_step)[0]) * self.config.steps_per_update

    def to_bytes(self, state: TrainerState) -> bytes:
        return state_to_bytes(state)

    def from_bytes(self, data: bytes) -> TrainerState:
        """The state in `data`; training then starts fresh episodes (module docstring)."""
        spec, envs = self.env_spec, self.config.num_envs
        obs = jax.ShapeDtypeStruct((envs, spec.num_agents, spec.obs_dim), jnp.float32)
        mask = jax.ShapeDtypeStruct((envs, spec.num_agents, spec.action_dim), jnp.bool_)
        template = jax.eval_shape(self._init, seed_keys(self.config)[0], obs, mask)
        state = restore_state(template, None, self.config.seeds, data)
        self._timestep = None
        return state
