"""The learn → log → evaluate → checkpoint loop around a Trainer, writing a run directory."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from cmat.config import TrainConfig
from cmat.errors import CmatError
from cmat.plots import plot_runs
from cmat.rundir import (
    DIAGNOSTIC_COLUMNS,
    PER_RUN_PREFIXES,
    Row,
    RunDir,
    Session,
    network_record,
)
from cmat.runners.checkpoints import BestCheckpoint, keep_periodic

if TYPE_CHECKING:
    from cmat.runners.base import Trainer, TrainerState

RESULT_KEYS = ("env_steps", "episode_return", "win_rate")


def run_training(
    trainer: Trainer, run_dir: RunDir, resume: bool, start: TrainerState | None = None
) -> None:
    """Train in chunks of `updates_per_log` updates until exactly `num_updates` are done (the
    last chunk may be shorter; `TrainConfig.num_updates` is the one rounding rule).

    After each chunk: a train and an eval row per seed in metrics.csv and TensorBoard (where
    charts/steps_per_second counts the steps of all seeds), then the checkpoint. Resuming
    continues from the checkpoint and drops metric rows written after it; resuming a complete
    run says so and writes nothing. An interruption leaves the rows and the checkpoint of the
    last completed chunk. A chunk with a non-finite loss, gradient norm or parameter raises
    `CmatError` naming the update, before anything of it is written, so the last good
    checkpoint stays as it was. A new run starts from `start` where given (a fine-tuning run's
    state, cmat.runners.finetune), else `trainer.init()`. One process at a time trains into a
    run (`RunDir.training_lock`; CmatError for a second). Each session of the run (this call)
    is recorded in sessions.jsonl (`Session`).
    """
    with run_dir.training_lock():
        train_locked(trainer, run_dir, resume, start)


def train_locked(
    trainer: Trainer, run_dir: RunDir, resume: bool, start: TrainerState | None
) -> None:
    """`run_training` once the run's lock is held."""
    config = trainer.config
    if resume:
        from cmat.runners.base import restore_run

        state, done = restore_run(run_dir, trainer)
        if resume_is_complete(config, run_dir, done):
            return
        run_dir.write_config(config, run_dir.resumed_sources(config))
        run_dir.truncate_metrics(done)
    else:
        state = trainer.init() if start is None else start
        done = trainer.env_steps(state)
        run_dir.save_checkpoint(trainer.to_bytes(state), done, network_record(config))
    session = Session(run_dir, done)
    best = BestCheckpoint(trainer, run_dir)
    watch = EpisodeEndWatch(config.env, trainer.env_spec.max_episode_steps)
    remaining = (config.budget_steps - done) // config.steps_per_update
    chunks = [config.updates_per_log] * (remaining // config.updates_per_log)
    chunks += [remaining % config.updates_per_log] if remaining % config.updates_per_log else []
    try:
        with (
            remembered_interrupts() as interrupted,
            scalar_writers(config, run_dir, purge_step=done + 1 if resume else None) as writer,
            Progress(total=config.budget_steps, initial=done, unit="step", unit_scale=True,
                     desc=config.env, dynamic_ncols=True, smoothing=0,
                     postfix="compiling") as bar,
        ):
            for updates in chunks:
                state = run_chunk(trainer, state, run_dir, writer, bar, updates, watch, best)
                bar.compiled()
                session.record(trainer.env_steps(state))
                if interrupted():
                    raise KeyboardInterrupt
    except KeyboardInterrupt:
        run_dir.truncate_metrics(run_dir.recorded_steps())
        raise
    absolute = best.absolute(state)
    absolute["env_steps"] = np.full(config.seeds, config.budget_steps)
    run_dir.append_metrics(seed_rows("absolute", absolute, config.seed))
    plot_runs([run_dir.path], run_dir.curve_path)


class Progress(tqdm):  # type: ignore[misc]
    """The training bar: its rate and ETA count the steps after the session's first chunk
    (`compiled`) only, so the compilation is not in them; until the second chunk ends the ETA
    reads `?`."""

    mark: tuple[float, float] | None = None

    def compiled(self) -> None:
        """Mark the end of the first chunk (later calls change nothing)."""
        if self.mark is None:
            self.mark = (self.n, self._time())

    @property
    def format_dict(self) -> dict[str, Any]:
        values: dict[str, Any] = super().format_dict
        steps, since = self.mark or (self.n, self._time())
        seconds = self._time() - since
        values["initial"] = steps
        values["rate"] = (self.n - steps) / seconds if self.n > steps and seconds else None
        return values


def resume_is_complete(config: TrainConfig, run_dir: RunDir, done: int) -> bool:
    """Whether a run resumed with `config` at `done` env steps per seed has nothing left to
    train (then says so on stderr); CmatError where its budget is below what is done."""
    if config.budget_steps < done:
        raise CmatError(f"steps ({config.total_steps}) is below the {done} env steps already done")
    if config.budget_steps == done:
        print(f"cmat: {run_dir.path} is complete at {done:,} env steps per seed; "
              f"--steps N above that extends it", file=sys.stderr)
        return True
    return False


@contextmanager
def remembered_interrupts() -> Iterator[Callable[[], bool]]:
    """While it is open, Ctrl-C (SIGINT) raises KeyboardInterrupt as usual and is also
    remembered: the returned function says whether one came. Python drops a KeyboardInterrupt
    raised inside a garbage-collection callback (JAX registers one, which runs often while a
    program compiles), so the loop raises it again after the chunk it arrived in. Only where
    SIGINT has Python's default handler and this is the main thread; elsewhere nothing
    changes and the function says False."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield lambda: False
        return
    received: list[int] = []

    def remember(signum: int, frame: Any) -> None:
        received.append(signum)
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, remember)
    try:
        yield lambda: bool(received)
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)


class WandbWriter:
    """`add_scalar` / `flush` / `close` of tensorboardX's SummaryWriter, into a Weights & Biases
    run (`TrainConfig.logger` 'wandb'). A resumed run continues the same W&B run (its id is
    derived from the run directory)."""

    def __init__(self, config: TrainConfig, run_dir: RunDir) -> None:
        try:
            import wandb
        except ImportError:
            raise CmatError(
                "logger=wandb needs the wandb package: pip install 'wandb>=0.19,<1' "
                "(cmat's wandb extra)"
            ) from None
        online = os.environ.get("WANDB_MODE") == "online" or (
            "WANDB_MODE" not in os.environ and bool(os.environ.get("WANDB_API_KEY")))
        path = run_dir.path.resolve()
        self.run = wandb.init(
            project=os.environ.get("WANDB_PROJECT", "cmat"), name=path.name,
            id=hashlib.sha256(str(path).encode()).hexdigest()[:16], resume="allow",
            dir=str(path), config=dataclasses.asdict(config),
            mode="online" if online else "offline",
        )
        self.pending: dict[int, dict[str, float]] = {}

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        self.pending.setdefault(step, {})[tag] = value

    def flush(self) -> None:
        for step in sorted(self.pending):
            self.run.log(self.pending[step], step=step)
        self.pending.clear()

    def close(self) -> None:
        self.flush()
        self.run.finish()


class ScalarWriters:
    """The run's TensorBoard writer and, with `logger` 'wandb', a `WandbWriter`, as one."""

    def __init__(self, writers: list[Any]) -> None:
        self.writers = writers

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        for writer in self.writers:
            writer.add_scalar(tag, value, step)

    def flush(self) -> None:
        for writer in self.writers:
            writer.flush()


@contextmanager
def scalar_writers(
    config: TrainConfig, run_dir: RunDir, purge_step: int | None
) -> Iterator[ScalarWriters]:
    with run_dir.summary_writer(purge_step=purge_step) as tensorboard:
        extra = [WandbWriter(config, run_dir)] if config.logger == "wandb" else []
        try:
            yield ScalarWriters([tensorboard, *extra])
        finally:
            for writer in extra:
                writer.close()


class EpisodeEndWatch:
    """Warns once (stderr) when no environment of any seed has ended an episode for more steps
    than the spec's `max_episode_steps`: cmat imposes that bound only on evaluation, so an
    environment that never sets `done` trains on with train rows whose return reads nan."""

    def __init__(self, env_id: str, max_episode_steps: int) -> None:
        self.env_id, self.max_episode_steps = env_id, max_episode_steps
        self.steps_without_end = 0
        self.warned = False

    def chunk(self, episode_returns: np.ndarray, steps_per_env: int) -> None:
        """After a chunk of `steps_per_env` steps per environment whose per-seed train return
        is `episode_returns` (nan where no episode ended)."""
        if not np.all(np.isnan(episode_returns)):
            self.steps_without_end = 0
            return
        self.steps_without_end += steps_per_env
        if self.steps_without_end > self.max_episode_steps and not self.warned:
            self.warned = True
            tqdm.write(
                f"cmat: warning: {self.env_id}: no episode has ended in the last "
                f"{self.steps_without_end:,} steps of any environment, more than its "
                f"max_episode_steps ({self.max_episode_steps}); training ends no episode itself, "
                f"so train rows read nan until the environment sets done", file=sys.stderr)


def run_chunk(
    trainer: Trainer, state: TrainerState, run_dir: RunDir, writer: ScalarWriters, bar: Progress,
    updates: int, watch: EpisodeEndWatch, best: BestCheckpoint,
) -> TrainerState:
    """`updates` updates, their evaluation, logs and checkpoints (latest, `best`, periodic);
    `watch` sees each chunk's train returns."""
    config = trainer.config
    before = trainer.env_steps(state)
    start = time.perf_counter()
    state, train = trainer.train_chunk(state, updates)
    stop_if_faulty(train, before // config.steps_per_update, config.seed, run_dir)
    steps = trainer.env_steps(state)
    steps_per_second = (steps - before) * config.seeds / (time.perf_counter() - start)
    watch.chunk(np.asarray(train["episode_return"]), (steps - before) // config.num_envs)
    evaluation = trainer.evaluate(state, config.eval_episodes, episode_seed=steps)
    evaluation = {**evaluation, "env_steps": train["env_steps"]}
    rows = seed_rows("train", train, config.seed) + seed_rows("eval", evaluation, config.seed)
    run_dir.append_metrics(rows)
    log_scalars(writer, rows, steps, steps_per_second)
    data = trainer.to_bytes(state)
    run_dir.save_checkpoint(data, steps, network_record(config))
    best.update(state, evaluation, steps)
    keep_periodic(trainer, run_dir, data, before, steps)
    bar.set_postfix(postfix(evaluation, trainer.env_spec.has_win_rate), refresh=False)
    bar.update(steps - before)
    return state


def stop_if_faulty(
    train: dict[str, np.ndarray], updates_before: int, base_seed: int, run_dir: RunDir
) -> None:
    """Raise `CmatError` naming the first update (1-based, counted over the run) and seed whose
    rollout or update failed a check (`cmat.runners.learner.ROLLOUT_FAULTS`), and the check; pops
    the two flags from `train`."""
    from cmat.runners.learner import ROLLOUT_FAULTS

    first = train.pop("fault_update").astype(int)
    codes = train.pop("fault_code").astype(int)
    bad = np.flatnonzero(first >= 0)
    if bad.size == 0:
        return
    seed = bad[np.argmin(first[bad])]
    kept = (f"the last good checkpoint ({updates_before} updates) is left as it was in "
            f"{run_dir.path}" if updates_before else "no update was saved")
    raise CmatError(
        f"{ROLLOUT_FAULTS[codes[seed] - 1]} at update "
        f"{updates_before + first[seed] + 1} (seed {base_seed + seed}); training stopped and "
        f"{kept}"
    )


def seed_rows(kind: str, metrics: Mapping[str, np.ndarray], base_seed: int) -> list[Row]:
    """One CSV row per seed from per-seed metric arrays."""
    seeds = len(metrics["env_steps"])
    return [
        {
            "kind": kind, "seed": base_seed + index, "env_steps": int(metrics["env_steps"][index]),
            **{key: float(values[index]) for key, values in metrics.items() if key != "env_steps"},
        }
        for index in range(seeds)
    ]


def log_scalars(writer: ScalarWriters, rows: list[Row], step: int, steps_per_second: float) -> None:
    """Rows as TensorBoard scalars: train/..., eval/..., losses/... tagged per seed."""
    for row in rows:
        for key, value in row.items():
            if key in ("kind", "seed", "env_steps") or math.isnan(float(value)):
                continue
            namespace = (
                row["kind"] if key in RESULT_KEYS or row["kind"] == "eval"
                else "diagnostics" if key in DIAGNOSTIC_COLUMNS or key.startswith(PER_RUN_PREFIXES)
                else "losses"
            )
            writer.add_scalar(f"{namespace}/{key}/seed_{row['seed']}", float(value), step)
    writer.add_scalar("charts/steps_per_second", steps_per_second, step)
    writer.flush()


def postfix(evaluation: Mapping[str, np.ndarray], has_win_rate: bool) -> dict[str, str]:
    shown = {"return": f"{np.nanmean(evaluation['episode_return']):.3g}"}
    if has_win_rate:
        shown["win"] = f"{np.nanmean(evaluation['win_rate']):.2f}"
    return shown
