"""What `cmat train`, `eval`, `finetune` and `experiment` drive: the `Trainer` protocol, the
state it carries, and the checkpoint format every trainer writes.

Two trainers implement the protocol: `cmat.runners.trainer.JaxTrainer` (JAX environments
stepped inside one compiled program) and `cmat.runners.host.HostTrainer` (simulators stepped
on the host). Both pair a collector with the same learner (`cmat.runners.learner`) and the same
evaluation semantics (`cmat.runners.evaluation`).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import flax.serialization
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import threadpoolctl

from cmat.config import TrainConfig
from cmat.envs.protocol import EnvSpec
from cmat.errors import CmatError
from cmat.rundir import Checkpoint, RunDir, network_record
from cmat.runners.collector import EnvsState
from cmat.runners.learner import LearnerSetup, LearnerState


@flax.struct.dataclass
class TrainerState:
    """Every seed's state of a run (a leading seed axis on each leaf): the learner's, and the
    environments' where they live inside the program (None for host runs)."""

    learner: LearnerState
    envs: EnvsState | None


class Trainer(Protocol):
    """A run's programs for all its seeds."""

    @property
    def config(self) -> TrainConfig: ...

    @property
    def env_spec(self) -> EnvSpec: ...

    @property
    def learner_setup(self) -> LearnerSetup:
        """The algorithm and optimizer the run learns with."""
        ...

    def init(self) -> TrainerState:
        """A fresh state of every seed."""
        ...

    def train_chunk(
        self, state: TrainerState, updates: int | None = None
    ) -> tuple[TrainerState, dict[str, np.ndarray]]:
        """`updates` (default and at most `config.updates_per_log`) updates of every seed; the
        metrics have one entry per seed, `env_steps` among them."""
        ...

    def evaluate(
        self, state: TrainerState, episodes: int, episode_seed: int = 0
    ) -> dict[str, np.ndarray]:
        """`episode_return`, `win_rate` and the environment's metrics of `episodes` episodes per
        seed (`cmat.runners.evaluation`), acting as `TrainConfig.eval_actions` says. The
        episodes (start states, environment and action draws) are those of `episode_seed` and
        the run's seeds: the same `episode_seed` replays them, another draws new ones. Training
        evaluates at env step t with `episode_seed = t` (`cmat.runners.loop`), so no two of a
        run's evaluations share episodes, and `cmat eval`'s default 0 shares none with them."""
        ...

    def env_steps(self, state: TrainerState) -> int:
        """Env steps per seed done by `state`."""
        ...

    def to_bytes(self, state: TrainerState) -> bytes: ...

    def from_bytes(self, data: bytes) -> TrainerState:
        """The state in checkpoint `data`; raises CmatError for corrupt or mismatched data."""
        ...

    def close(self) -> None:
        """Release what the trainer runs outside the program (simulator workers)."""
        ...


def state_to_bytes(state: TrainerState) -> bytes:
    """The checkpoint format: one flat map of the learner's fields and, for in-graph runs, the
    environments' (`env_state`, `timestep`, `episode_return`, `memory`: empty for algorithms
    without one)."""
    fields: dict[str, Any] = dict(flax.serialization.to_state_dict(state.learner))
    if state.envs is not None:
        fields.update(flax.serialization.to_state_dict(state.envs))
    return flax.serialization.msgpack_serialize(fields)


def state_difference(expected: Any, found: Any, path: str) -> str | None:
    """Where a checkpoint's state dict (`found`) first departs from the one this config builds
    (`expected`; nested dicts whose leaves have shapes): a key on one side only, or a leaf of
    another shape ('shapes differ: ...'), said of the checkpoint; None where they agree."""
    if isinstance(expected, dict) and isinstance(found, dict):
        for key in expected:
            if key not in found:
                return f"state differs: {path}/{key} is not in the checkpoint"
            difference = state_difference(expected[key], found[key], f"{path}/{key}")
            if difference is not None:
                return difference
        extra = next((key for key in found if key not in expected), None)
        return None if extra is None else (
            f"state differs: the checkpoint has {path}/{extra}, which this config's state lacks")
    if isinstance(expected, dict) or isinstance(found, dict) or expected is None or found is None:
        return None if expected is None and found is None else (
            f"state differs: {path} has another structure in the checkpoint")
    shape = tuple(getattr(found, "shape", np.shape(found)))
    expected_shape = tuple(getattr(expected, "shape", np.shape(expected)))
    if shape != expected_shape:
        return (f"shapes differ: {path} is {shape} in the checkpoint, {expected_shape} for this "
                "config")
    return None


def restore_state(
    learner: LearnerState, envs: EnvsState | None, seeds: int, data: bytes
) -> TrainerState:
    """The all-seeds state serialised in `data` (`state_to_bytes`), checked against one seed's
    templates (shapes and dtypes, e.g. from `jax.eval_shape`)."""
    template = jax.tree.map(lambda x: jax.ShapeDtypeStruct((seeds, *x.shape), x.dtype),
                            TrainerState(learner, envs))
    try:
        raw = flax.serialization.msgpack_restore(data)
        if not isinstance(raw, dict):
            raise TypeError("not a map")
        learner_fields = flax.serialization.to_state_dict(template.learner)
        env_fields = ({} if template.envs is None
                      else flax.serialization.to_state_dict(template.envs))
        expected = {**learner_fields, **env_fields}
        difference = state_difference(
            expected, {name: raw[name] for name in expected if name in raw}, "state")
        if difference is not None:
            raise CmatError(f"checkpoint does not match this run's config ({difference})")
        restored_learner = flax.serialization.from_state_dict(
            template.learner, {name: raw[name] for name in learner_fields})
        restored_envs = None if template.envs is None else flax.serialization.from_state_dict(
            template.envs, {name: raw[name] for name in env_fields})
        restored = TrainerState(restored_learner, restored_envs)
    except CmatError:
        raise
    except Exception as error:  # msgpack and flax raise many types for bad bytes
        raise CmatError(f"corrupt or incompatible checkpoint ({type(error).__name__})") from None
    expected = jax.tree.map(lambda x: (x.shape, x.dtype), template)
    found = jax.tree.map(lambda x: (np.shape(x), np.asarray(x).dtype), restored)
    if expected != found:
        raise CmatError("checkpoint does not match this run's config (shapes differ)")
    state: TrainerState = jax.tree.map(jnp.asarray, restored)
    return state


def restore_run(
    run_dir: RunDir, trainer: Trainer, which: Checkpoint = "latest"
) -> tuple[TrainerState, int]:
    """The state in `run_dir`'s checkpoint `which` (latest, best or a periodic one's env steps:
    cmat.runners.checkpoints), restored by `trainer` (built from the run's config.yaml), and its
    env steps per seed.

    Raises CmatError naming the checkpoint where it is missing or corrupt, where its state does
    not fit `trainer` (a config.yaml edited since, or written by another cmat version: the
    message says which version wrote the run), and where the steps the state counts at the
    config's num_envs x rollout_length differ from the steps its header records (those two
    edited: they fix what one update is)."""
    from cmat.version import __version__

    data, env_steps = run_dir.load_checkpoint(which)
    try:
        state = trainer.from_bytes(data)
    except CmatError as error:
        written = run_dir.version()
        hint = (f"does {run_dir.config_path} still describe the run that wrote it?"
                if written == __version__ else
                f"the run was written by {f'cmat {written}' if written else 'another cmat version'}"
                f", this is cmat {__version__}")
        raise CmatError(f"{run_dir.checkpoint_file(which)}: {error}; {hint}") from None
    recorded = run_dir.checkpoint_network(which)
    if recorded is not None:
        expected = network_record(trainer.config)
        changed = [name for name in recorded if name in expected
                   and recorded[name] != expected[name]]
        if changed:
            name = changed[0]
            section = ("network" if name in dataclasses.asdict(trainer.config.network)
                       else trainer.config.algo)
            raise CmatError(
                f"{run_dir.config_path} does not match its checkpoint: {section}.{name} is "
                f"{expected[name]!r} there, the checkpoint's parameters belong to "
                f"{section}.{name} = {recorded[name]!r}; a run's network cannot change")
    counted = trainer.env_steps(state)
    if counted != env_steps:
        config = trainer.config
        raise CmatError(
            f"{run_dir.config_path} does not match its checkpoint: the checkpoint holds "
            f"{env_steps:,} env steps, which num_envs={config.num_envs} x "
            f"rollout_length={config.rollout_length} would count as {counted:,}; a run's "
            f"num_envs and rollout_length cannot change")
    return state, env_steps


def single_threaded_lapack() -> threadpoolctl.threadpool_limits:
    """A context in which the BLAS/LAPACK libraries of this process (scipy's and numpy's
    OpenBLAS) use one thread, for running parameter initialisation.

    Orthogonal initialisers (MAT's reference initialisation) call LAPACK's QR from XLA:CPU's
    threads. Where another process or test worker also keeps the cores busy, OpenBLAS's own
    threads spin against XLA's: one CMAT initialisation then took 1.09 s instead of 0.012 s
    with one LAPACK thread (`benchmarks/init_time.py`, results/init_time.txt), and on an idle
    machine one thread was faster as well (11 against 31 ms)."""
    return threadpoolctl.threadpool_limits(limits=1, user_api="blas")


def stack_seeds(states: list[TrainerState]) -> TrainerState:
    """One state with a leading seed axis from each seed's state, stacked on the host: no
    program to compile (a jitted or per-leaf `jnp.stack` compiled for seconds at 10 seeds)."""
    stacked: TrainerState = jax.tree.map(
        lambda *leaves: jnp.asarray(np.stack([np.asarray(leaf) for leaf in leaves])), *states)
    return stacked


def seed_keys(config: TrainConfig, offset: int = 0) -> jax.Array:
    """[seeds] PRNG keys of the run's seeds, `offset` added to each seed number."""
    seeds = config.seed + np.arange(config.seeds) + offset
    return jax.vmap(jax.random.PRNGKey)(jnp.asarray(seeds))


EVAL_SEED_OFFSET = 1_000_003
"""Added to a seed number for its evaluation keys: evaluation never replays training's."""


def eval_keys(config: TrainConfig, episode_seed: int) -> jax.Array:
    """[seeds] PRNG keys of the evaluation episodes `episode_seed` of each of the run's seeds."""
    return jax.vmap(jax.random.fold_in, in_axes=(0, None))(
        seed_keys(config, offset=EVAL_SEED_OFFSET), jnp.uint32(episode_seed))
