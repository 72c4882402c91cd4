"""The compiled training program for in-graph (JAX) environments: `JaxTrainer`.

One update = the in-graph collector's rollout (`lax.scan` over steps, `vmap` over
environments) → the learner's `learn` (target-critic GAE, PPO epochs × minibatches, soft update
of the target critic; Algorithm 1). A chunk of updates is one `lax.scan`, `vmap`ped over seeds
and jitted as a single program; `make_train` gives the whole run as one pure function,
PureJaxRL style.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from cmat.algorithms import algorithm_entry
from cmat.config import TrainConfig
from cmat.envs import make_env
from cmat.envs.protocol import EnvSpec
from cmat.runners.base import (
    TrainerState,
    eval_keys,
    restore_state,
    seed_keys,
    single_threaded_lapack,
    stack_seeds,
    state_to_bytes,
)
from cmat.runners.collector import InGraphCollector, rollout_report
from cmat.runners.devices import compiler_options, place, sharded_axis, to_host
from cmat.runners.evaluation import evaluate_in_graph
from cmat.runners.learner import LearnerSetup, build_learner, init_learner, learn, summarise_updates


@dataclass(frozen=True)
class TrainSetup:
    """The static parts of the program: closed over, never traced."""

    config: TrainConfig
    collector: InGraphCollector
    learner: LearnerSetup

    @property
    def spec(self) -> EnvSpec:
        return self.learner.spec


def build_setup(config: TrainConfig) -> TrainSetup:
    """The environment, collector, algorithm and optimizer of `config`."""
    env = make_env(config.env, **config.env_kwargs)
    learner = build_learner(config, env.spec)
    collector = InGraphCollector(env, learner.algorithm, config.num_envs, config.rollout_length)
    return TrainSetup(config, collector, learner)


def init_state(setup: TrainSetup, rng: jax.Array) -> TrainerState:
    """A fresh state of one seed: environments reset, parameters initialised."""
    rng, init_key, reset_key = jax.random.split(rng, 3)
    envs = setup.collector.reset(reset_key)
    learner = init_learner(
        setup.learner, init_key, rng, envs.timestep.obs[0], envs.timestep.action_mask[0]
    )
    return TrainerState(learner, envs)


def update_step(
    setup: TrainSetup, state: TrainerState
) -> tuple[TrainerState, dict[str, jax.Array]]:
    """One PPO update of one seed: collect with the current parameters, then learn; the
    update's metrics with the rollout's report."""
    assert state.envs is not None
    rng, rollout_key = jax.random.split(state.learner.rng)
    envs, rollout = setup.collector.collect(state.learner.params, state.envs, rollout_key)
    learner, metrics = learn(setup.learner, dataclasses.replace(state.learner, rng=rng), rollout)
    return TrainerState(learner, envs), {**metrics, **rollout_report(rollout.steps)}


def run_updates(
    setup: TrainSetup, state: TrainerState, max_updates: int, updates: jax.Array
) -> tuple[TrainerState, dict[str, jax.Array]]:
    """`updates` (≤ `max_updates`, traced) updates in one scan of `max_updates` steps: the
    steps past `updates` leave the state as it is, so one compiled program also runs a run's
    shorter last chunk. Episode statistics are pooled over the updates done. The update is
    one jitted function, so the shape query of the skipped branch and the taken branch share
    one trace of it."""

    update = jax.jit(functools.partial(update_step, setup))

    def step(state: TrainerState, index: jax.Array) -> tuple[TrainerState, dict[str, jax.Array]]:
        shapes = jax.eval_shape(update, state)[1]
        skipped = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)
        state, metrics = jax.lax.cond(index < updates, update, lambda s: (s, skipped), state)
        return state, {**metrics, "performed": index < updates}

    state, per_update = jax.lax.scan(step, state, jnp.arange(max_updates))
    return state, summarise_updates(setup.spec, per_update)


def make_train(
    config: TrainConfig,
) -> Callable[[jax.Array], tuple[TrainerState, dict[str, jax.Array]]]:
    """The whole run of one seed as one pure function of its key; `jax.jit` it.

    To train several seeds in one program, use `JaxTrainer`: it vmaps the updates over seeds
    but initialises each seed on its own, because a vmapped orthogonal initialiser (batched QR)
    deadlocks XLA:CPU in jax 0.10.2 once a program holds about 16 of them.
    """
    setup = build_setup(config)

    def train(rng: jax.Array) -> tuple[TrainerState, dict[str, jax.Array]]:
        state = init_state(setup, rng)
        return jax.lax.scan(lambda s, _: update_step(setup, s), state, None, config.num_updates)

    return train


class JaxTrainer:
    """The `Trainer` (cmat.runners.base) of JAX environments: jitted programs for all the run's
    seeds (leading axis of every state leaf), on every device of the run (all processes' in a
    distributed run: cmat.runners.distributed)."""

    def __init__(self, config: TrainConfig) -> None:
        self.config = config
        self.setup = build_setup(config)
        self.env_spec = self.setup.spec
        self.learner_setup = self.setup.learner
        self.devices = jax.devices()
        self.sharded_axis = sharded_axis(len(self.devices), config.seeds, config.num_envs)
        chunk = config.updates_per_log
        collector = self.setup.collector
        options = compiler_options(algorithm_entry(config.algo).ynnpack_matmuls)
        self._init = jax.jit(lambda rng: init_state(self.setup, rng), compiler_options=options)
        self._chunk = jax.jit(
            jax.vmap(
                lambda state, updates: run_updates(self.setup, state, chunk, updates),
                in_axes=(0, None),
            ),
            donate_argnums=0,
            compiler_options=options,
        )
        self._evaluate = jax.jit(
            jax.vmap(
                lambda params, rng, episodes: evaluate_in_graph(
                    collector.env, collector.algorithm, params, rng, episodes,
                    sample=config.eval_actions == "sample"),
                in_axes=(0, 0, None),
            ),
            static_argnums=2,
            compiler_options=options,
        )

    def init(self) -> TrainerState:
        """Fresh state for every seed, initialised seed by seed (see `make_train`), placed on
        the local devices (cmat.runners.devices)."""
        with single_threaded_lapack():
            state = stack_seeds([self._init(key) for key in seed_keys(self.config)])
        return place(state, self.devices, self.sharded_axis)

    def train_chunk(
        self, state: TrainerState, updates: int | None = None
    ) -> tuple[TrainerState, dict[str, np.ndarray]]:
        updates = self.config.updates_per_log if updates is None else updates
        if not 0 < updates <= self.config.updates_per_log:
            raise ValueError(f"updates must be in 1..{self.config.updates_per_log}, got {updates}")
        state, metrics = self._chunk(state, jnp.asarray(updates, jnp.int32))
        numbers: dict[str, np.ndarray] = to_host(metrics)
        numbers["env_steps"] = np.full(self.config.seeds, self.env_steps(state))
        return state, numbers

    def compile_chunk(self, state: TrainerState) -> jax.stages.Compiled:
        """Compile the program `train_chunk` runs on states like `state`, without running it.

        The same program, so with JAX's persistent compilation cache set
        (`JAX_COMPILATION_CACHE_DIR`) a later process's `train_chunk` loads it instead of
        compiling: `benchmarks/gpu.sh` compiles its runs side by side this way, then times them
        one at a time. The result also tells the program's memory (`memory_analysis()`)."""
        return self._chunk.lower(state, jnp.asarray(1, jnp.int32)).compile()

    def evaluate(
        self, state: TrainerState, episodes: int, episode_seed: int = 0
    ) -> dict[str, np.ndarray]:
        keys = eval_keys(self.config, episode_seed)
        metrics = self._evaluate(state.learner.params, keys, episodes)
        evaluation: dict[str, np.ndarray] = to_host(metrics)
        return evaluation

    def env_steps(self, state: TrainerState) -> int:
        """Every seed's update count is the same, so this process's first shard tells it."""
        step = state.learner.update_step
        if isinstance(step, jax.Array):
            step = step.addressable_shards[0].data
        return int(np.asarray(step).ravel()[0]) * self.config.steps_per_update

    def to_bytes(self, state: TrainerState) -> bytes:
        return state_to_bytes(to_host(state))

    def from_bytes(self, data: bytes) -> TrainerState:
        template = jax.eval_shape(self._init, seed_keys(self.config)[0])
        state = restore_state(template.learner, template.envs, self.config.seeds, data)
        return place(state, self.devices, self.sharded_axis)

    def close(self) -> None:
        """Nothing runs outside the program."""
