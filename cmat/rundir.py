"""A run directory: resolved config, metrics CSV, TensorBoard events, checkpoint and curve.

Layout::

    DIR/config.yaml            the full resolved TrainConfig
    DIR/metrics.csv            one row per seed and chunk: kind (train|eval), seed, env_steps, ...;
                           and once complete, the best checkpoint's `absolute` evaluation
    DIR/tb/                    TensorBoard events
    DIR/checkpoints/latest.ckpt   the state after the last chunk (what a resume continues)
    DIR/checkpoints/best.ckpt     each seed's parameters at its best evaluation so far
    DIR/checkpoints/step-N.ckpt   periodic ones (`checkpoint_interval`, `keep_checkpoints`)
    DIR/sessions.jsonl         one line per training session: where it ran, for how long
    DIR/curve.png

A checkpoint file is a magic line, a JSON header line (env_steps, size, sha256) and the trainer's
bytes, replaced atomically, so a reader sees either the previous or the new checkpoint whole.
An exported copy of a run (`RunDir.export`: results without checkpoints, to share or commit)
holds config.yaml, metrics.csv and `checkpoints/latest.json`, the header of the checkpoint it
left out, and sessions.jsonl; it reads as complete at that step but cannot be resumed or
fine-tuned from. A carried copy (`RunDir.export(..., checkpoint=True)`) keeps the checkpoint
instead, to continue the run on another machine.
Metric rows are appended before the checkpoint of their chunk is written; on resume, rows past
the checkpoint's env_steps belong to a chunk that never finished and are dropped.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import fcntl
import hashlib
import io
import json
import math
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tensorboardX import SummaryWriter

from cmat.algorithms import check_config
from cmat.config import ConfigSources, TrainConfig
from cmat.configfile import field_names, from_yaml, read_sources, to_yaml, written_by
from cmat.errors import CmatError, read_text

LOSS_COLUMNS = ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac")
DIAGNOSTIC_COLUMNS = (
    "joint_approx_kl", "joint_clip_frac", "agent_approx_kl", "agent_clip_frac",
    "explained_variance",
)
"""Per-update diagnostics of every algorithm (`cmat.algorithms.ppo.policy_diagnostics`)."""
COLUMNS = (
    "kind", "seed", "env_steps", "episode_return", "win_rate", *LOSS_COLUMNS, *DIAGNOSTIC_COLUMNS,
    "best_env_steps",
)
"""The first columns of metrics.csv; `best_env_steps` is set on `absolute` rows only (the env
steps the best checkpoint's parameters of that seed come from)."""
PER_RUN_PREFIXES = ("entropy_agent_", "grad_norm_", "epochs_run", "env_restarts", "env_nonfinite")
"""Diagnostics whose names depend on the run (one per agent, one per parameter block, host
environments' restarts and non-finite values replaced, cumulative per seed): their columns
follow COLUMNS in the order the first rows give them."""
CHECKPOINT_MAGIC = b"CMAT-CHECKPOINT 1\n"
SAVED_POLICY_HEADER = "policy.json"
"""The file that marks a directory as a policy saved by `cmat.policy.Policy.save` (`cmat
export`): one seed's parameters beside the config.yaml of their run, and no checkpoint."""

Row = Mapping[str, str | int | float]
Checkpoint = str | int
"""Which checkpoint of a run: "latest", "best", or the env steps of a periodic one."""
KINDS = ("train", "eval", "absolute")
"""Kinds of metrics rows: a chunk's training and evaluation, and the best checkpoint's
evaluation on ten times the episodes once the run completes (Mava's absolute metric)."""


@dataclass(frozen=True)
class RunDir:
    """Paths and file operations of one run directory."""

    path: Path

    @property
    def config_path(self) -> Path:
        return self.path / "config.yaml"

    @property
    def metrics_path(self) -> Path:
        return self.path / "metrics.csv"

    @property
    def tb_path(self) -> Path:
        return self.path / "tb"

    @property
    def checkpoint_path(self) -> Path:
        return self.path / "checkpoints" / "latest.ckpt"

    def checkpoint_file(self, which: Checkpoint = "latest") -> Path:
        """The file of checkpoint `which`: `latest`, `best` or the env steps of a periodic one
        (`checkpoints/step-STEPS.ckpt`)."""
        name = which if isinstance(which, str) else f"step-{which:012d}"
        return self.path / "checkpoints" / f"{name}.ckpt"

    def checkpoints(self) -> list[Checkpoint]:
        """The checkpoints this run keeps: latest, best, then the periodic ones by env steps."""
        kept: list[Checkpoint] = [name for name in ("latest", "best")
                                  if self.checkpoint_file(name).is_file()]
        return kept + self.periodic_checkpoints()

    def periodic_checkpoints(self) -> list[Checkpoint]:
        folder = self.path / "checkpoints"
        steps = [int(path.stem.removeprefix("step-")) for path in folder.glob("step-*.ckpt")
                 if path.stem.removeprefix("step-").isdigit()] if folder.is_dir() else []
        return list(sorted(steps))

    @property
    def header_path(self) -> Path:
        """Where an exported copy keeps the header of the checkpoint it left out."""
        return self.path / "checkpoints" / "latest.json"

    @property
    def sessions_path(self) -> Path:
        return self.path / "sessions.jsonl"

    @property
    def curve_path(self) -> Path:
        return self.path / "curve.png"

    @property
    def lock_path(self) -> Path:
        """Present while a process trains into the run (`training_lock`)."""
        return self.path / "run.lock"

    @contextmanager
    def training_lock(self) -> Iterator[None]:
        """Held by the one process that may train into this run (`cmat train`, `--resume`,
        `finetune`): an exclusive `flock` on `lock_path`, which holds the holder's pid and is
        removed on release. Raises CmatError where another process holds it."""
        while True:
            descriptor = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(descriptor, 32).decode(errors="replace").strip()
                os.close(descriptor)
                raise CmatError(
                    f"{self.path} is in use by another cmat process"
                    f"{f' (pid {holder})' if holder.isdigit() else ''}; wait for it to end "
                    f"or stop it") from None
            try:
                same_file = os.fstat(descriptor).st_ino == os.stat(self.lock_path).st_ino
            except FileNotFoundError:
                same_file = False
            if same_file:
                break
            os.close(descriptor)
        try:
            os.ftruncate(descriptor, 0)
            os.write(descriptor, f"{os.getpid()}\n".encode())
            yield
        finally:
            self.lock_path.unlink(missing_ok=True)
            os.close(descriptor)

    @classmethod
    def create(
        cls, path: Path, config: TrainConfig, sources: ConfigSources | None = None
    ) -> RunDir:
        """Start a new run in `path`, which must not hold one already; config.yaml names each
        value's source where `sources` is given."""
        run = cls.check_free(path)
        run.path.mkdir(parents=True, exist_ok=True)
        try:
            run.config_path.open("x").close()
        except FileExistsError:
            raise CmatError(f"{run.path} already holds a run; use --resume {run.path} or "
                            f"another --out") from None
        try:
            run.write_config(config, sources)
        except BaseException:  # a config that was never written does not make a run
            run.config_path.unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                run.path.rmdir()
            raise
        return run

    @classmethod
    def create_named(
        cls, base: Path, config: TrainConfig, sources: ConfigSources | None = None
    ) -> RunDir:
        """Start a new run in a directory made for it: `base`, else the first of `base-2`,
        `base-3`, ... that no one has made (two processes never get the same one)."""
        for attempt in range(1, 10_000):
            path = base if attempt == 1 else base.with_name(f"{base.name}-{attempt}")
            try:
                path.mkdir(parents=True)
            except FileExistsError:
                continue
            return cls.create(path, config, sources)
        raise CmatError(f"no free run directory name beside {base}")

    @classmethod
    def check_free(cls, path: Path) -> RunDir:
        """`path` as a run directory not created yet: CmatError where it holds a run already or
        is a file."""
        run = cls(Path(path))
        if run.config_path.exists():
            raise CmatError(
                f"{run.path} already holds a run; use --resume {run.path} or another --out"
            )
        if run.metrics_path.exists():
            raise CmatError(f"{run.path} holds a metrics.csv but no config.yaml (not a run "
                            f"cmat can resume); use another --out")
        if run.path.exists() and not run.path.is_dir():
            raise CmatError(f"--out {run.path} is not a directory")
        return run

    @classmethod
    def open(cls, path: Path) -> RunDir:
        """An existing run directory (one with a config.yaml)."""
        run = cls(Path(path))
        if run.path.is_file():
            raise CmatError(f"{run.path} is a file; give the run's directory")
        if not run.config_path.is_file():
            raise CmatError(f"{run.path} holds no run (no config.yaml)")
        return run

    def config(self) -> TrainConfig:
        """The run's config. Raises CmatError for one this version cannot read, naming the
        version that wrote it."""
        text = read_text(self.config_path, "run config")
        try:
            return check_config(from_yaml(text))
        except CmatError as error:
            from cmat.version import __version__

            written = written_by(text)
            if written is None or written == __version__:
                raise CmatError(f"{self.config_path}: {error}") from None
            raise CmatError(f"{self.config_path}: {error} (written by cmat {written}; this is "
                            f"cmat {__version__})") from None

    def version(self) -> str | None:
        """The cmat version that wrote config.yaml (None where it is not recorded)."""
        return written_by(self.config_path.read_text())

    def sources(self) -> ConfigSources:
        """Where each value of config.yaml came from (empty for a run that did not record it)."""
        return read_sources(self.config_path.read_text())

    def resumed_sources(self, config: TrainConfig) -> ConfigSources | None:
        """The sources of config.yaml for `config`, the run's config with a budget `cmat train
        --resume --steps` may have changed (None for a run that did not record them). A field
        that the run's config.yaml lacks (one cmat added after the run began) took its default
        and is marked so."""
        sources = self.sources()
        if not sources:
            return None
        for name in field_names(config.algo):
            sources.setdefault(name, "default (not in this run's earlier config.yaml)")
        if self.config().total_steps != config.total_steps:
            sources["total_steps"] = "command line (--resume --steps)"
        return sources

    def write_config(self, config: TrainConfig, sources: ConfigSources | None = None) -> None:
        atomic_write(self.config_path, to_yaml(config, sources).encode())

    def save_checkpoint(
        self, data: bytes, env_steps: int, network: dict[str, Any] | None = None,
        which: Checkpoint = "latest", extra: dict[str, Any] | None = None,
    ) -> None:
        """Write checkpoint `which`: a header (env steps, size, checksum, given the `network`
        config the parameters belong to, and `extra`: the best checkpoint's per-seed record)
        and the trainer's bytes."""
        header: dict[str, Any] = {"env_steps": env_steps, "size": len(data),
                                  "sha256": sha256(data)}
        if network is not None:
            header["network"] = network
        header.update(extra or {})
        path = self.checkpoint_file(which)
        path.parent.mkdir(exist_ok=True)
        atomic_write(path, CHECKPOINT_MAGIC + json.dumps(header).encode() + b"\n" + data)

    def checkpoint_header(self, which: Checkpoint = "latest") -> dict[str, Any] | None:
        """The header of checkpoint `which` (None where it is missing or unreadable)."""
        try:
            with self.checkpoint_file(which).open("rb") as file:
                if file.read(len(CHECKPOINT_MAGIC)) != CHECKPOINT_MAGIC:
                    return None
                header = json.loads(file.readline())
        except (OSError, ValueError):
            return None
        return header if isinstance(header, dict) else None

    def recorded_steps(self, which: Checkpoint = "latest") -> int:
        """The env steps checkpoint `which`'s header records, without reading or checking its
        bytes (`load_checkpoint` does, and raises its errors where the header is unreadable)."""
        header = self.checkpoint_header(which) or {}
        steps = header.get("env_steps")
        return steps if isinstance(steps, int) else self.load_checkpoint(which)[1]

    def checkpoint_network(self, which: Checkpoint = "latest") -> dict[str, Any] | None:
        """The network config checkpoint `which`'s header records (None: a checkpoint from
        before headers recorded it, or none)."""
        network = (self.checkpoint_header(which) or {}).get("network")
        return network if isinstance(network, dict) else None

    @property
    def is_saved_policy(self) -> bool:
        """Whether this directory is a saved policy (`SAVED_POLICY_HEADER`), not a run."""
        return (self.path / SAVED_POLICY_HEADER).exists()

    def refuse_saved_policy(self) -> None:
        """CmatError where this directory is a saved policy, for what needs a run's
        checkpoint (resuming, fine-tuning)."""
        if self.is_saved_policy:
            raise CmatError(f"{self.path} is a policy saved by cmat export (one seed's "
                            f"parameters, no checkpoint): cmat.load_policy, cmat eval and "
                            f"cmat render read it; training continues from its run directory")

    def load_checkpoint(self, which: Checkpoint = "latest") -> tuple[bytes, int]:
        """The trainer bytes and env steps of checkpoint `which` (`checkpoint_file`), checked
        against its header. CmatError where it is missing (naming those the run keeps, or
        saying the directory is a saved policy) or corrupt."""
        path = self.checkpoint_file(which)
        if not path.is_file():
            self.refuse_saved_policy()
            kept = (" (an exported copy: it keeps the run's results, not its checkpoint)"
                    if self.header_path.is_file() else "")
            if which == "latest" or not self.checkpoint_path.is_file():
                raise CmatError(f"no checkpoint in {self.path}{kept}")
            raise CmatError(f"no checkpoint {which!r} in {self.path}; it keeps "
                            f"{', '.join(map(str, self.checkpoints()))}")
        raw = path.read_bytes()
        if not raw.startswith(CHECKPOINT_MAGIC):
            raise CmatError(f"corrupt checkpoint: {path} (not a cmat checkpoint)")
        header_line, _, data = raw[len(CHECKPOINT_MAGIC):].partition(b"\n")
        try:
            header = json.loads(header_line)
            env_steps, size, digest = int(header["env_steps"]), header["size"], header["sha256"]
        except (ValueError, KeyError, TypeError):
            raise CmatError(f"corrupt checkpoint: {path} (unreadable header)") from None
        if len(data) != size:
            raise CmatError(f"corrupt checkpoint: {path} (truncated: {len(data)} of {size} bytes)")
        if sha256(data) != digest:
            raise CmatError(f"corrupt checkpoint: {path} (checksum mismatch)")
        return data, env_steps

    def checkpoint_steps(self) -> tuple[int, bool]:
        """(env steps of the latest checkpoint, whether its bytes are here): those of a checked
        checkpoint, else those an exported copy recorded in `header_path`. CmatError where
        there is neither, or the one there is corrupt."""
        if self.checkpoint_path.exists() or not self.header_path.exists():
            return self.load_checkpoint()[1], True
        try:
            return int(json.loads(self.header_path.read_text())["env_steps"]), False
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError):
            raise CmatError(f"corrupt checkpoint header: {self.header_path}") from None

    def export(self, target: Path, checkpoint: bool = False) -> RunDir:
        """Copy this run's results to `target` without the checkpoint's bytes: config.yaml,
        metrics.csv, sessions.jsonl and the checkpoint's header as `checkpoints/latest.json`;
        with `checkpoint`, the checked latest checkpoint itself instead of its header, and the
        best one, so the copy can be resumed or fine-tuned from (periodic ones stay behind). A
        copy already at `target` is replaced whole (built beside it, then swapped in).
        CmatError where the checkpoint is missing or corrupt."""
        if checkpoint:
            self.load_checkpoint()
        if self.checkpoint_path.exists() or not self.header_path.exists():
            data, steps = self.load_checkpoint()
            header = {"env_steps": steps, "size": len(data), "sha256": sha256(data)}
        else:
            self.checkpoint_steps()
            header = json.loads(self.header_path.read_text())
        target = Path(target)
        target.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}."))
        try:
            copy = RunDir(staging)
            shutil.copyfile(self.config_path, copy.config_path)
            for source, destination in ((self.metrics_path, copy.metrics_path),
                                        (self.sessions_path, copy.sessions_path)):
                if source.is_file():
                    shutil.copyfile(source, destination)
            copy.header_path.parent.mkdir()
            if checkpoint:
                shutil.copyfile(self.checkpoint_path, copy.checkpoint_path)
                best = self.checkpoint_file("best")
                if best.is_file():
                    shutil.copyfile(best, copy.checkpoint_file("best"))
            else:
                copy.header_path.write_text(json.dumps(header) + "\n")
            if target.exists():
                shutil.rmtree(target)
            staging.rename(target)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        return RunDir(target)

    def sessions(self) -> list[dict[str, Any]]:
        """The training sessions recorded so far (`Session.record`); unreadable lines, such as
        a run's from before this record existed, are skipped."""
        if not self.sessions_path.is_file():
            return []
        sessions = []
        for line in self.sessions_path.read_text(errors="replace").splitlines():
            try:
                entry = json.loads(line)
            except ValueError:
                continue
            if isinstance(entry, dict):
                sessions.append(entry)
        return sessions

    def append_metrics(self, rows: list[Row]) -> None:
        """Append rows (NaN as `nan`, missing columns empty) and sync them to disk. A new file's
        columns are COLUMNS and then every other key of the rows in the order they first give
        them (per-run diagnostics, the algorithm's own metrics, the environment's episode
        metrics). Rows with a key the header lacks (a metric that a resumed run's new options
        emit) first rewrite the file with that column added at the end, empty in earlier rows,
        so that no metric is dropped."""
        buffer = io.StringIO()
        header = self.metrics_header()
        columns = [*dict.fromkeys([*(header or COLUMNS), *(key for row in rows for key in row)])]
        if header and columns != header:
            self.widen_metrics(columns)
        writer = csv.DictWriter(buffer, columns, lineterminator="\n")
        if not header:
            writer.writeheader()
        writer.writerows({key: csv_value(value) for key, value in row.items()} for row in rows)
        with naming(self.metrics_path), self.metrics_path.open("a") as file:
            file.write(buffer.getvalue())
            file.flush()
            os.fsync(file.fileno())

    def widen_metrics(self, columns: list[str]) -> None:
        """Rewrite metrics.csv (atomically) under `columns`, a header that extends its own."""
        with self.metrics_path.open(newline="") as file:
            rows = list(csv.DictReader(file))
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, columns, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        atomic_write(self.metrics_path, buffer.getvalue().encode())

    def metrics_header(self) -> list[str]:
        """The columns of an existing metrics.csv (empty if there is none yet)."""
        if not self.metrics_path.is_file() or self.metrics_path.stat().st_size == 0:
            return []
        with self.metrics_path.open(newline="") as file:
            return next(csv.reader(file), [])

    def read_metrics(self) -> list[dict[str, str]]:
        """The rows of metrics.csv as strings (empty if there is none), after checking that the
        header names kind, seed and env_steps and that each row has a `kind` of `KINDS`,
        whole-number `seed` and `env_steps`, and a number (`nan` included) in every other
        non-empty cell. A last line without its newline (a write cut short) is left out, as
        `truncate_metrics` drops it on resume. Raises CmatError naming the file and the line
        of the first row that breaks this, or the first byte that is not UTF-8."""
        if not self.metrics_path.is_file():
            return []
        text = read_text(self.metrics_path, "metrics file")
        lines = io.StringIO(text).readlines()
        if lines and not lines[-1].endswith("\n"):
            lines.pop()
        if not lines:
            return []
        reader = csv.reader(lines)
        header = next(reader, [])
        missing = [column for column in COLUMNS[:3] if column not in header]
        if missing:
            raise CmatError(f"unreadable {self.metrics_path}, line 1: no {missing[0]} column")
        rows = []
        for number, cells in enumerate(reader, start=2):
            problem = metrics_row_problem(header, cells)
            if problem:
                raise CmatError(f"unreadable {self.metrics_path}, line {number}: {problem}")
            rows.append(dict(zip(header, cells)))
        return rows

    def truncate_metrics(self, env_steps: int) -> None:
        """Drop trailing rows past `env_steps` and any half-written last line; keep the rest."""
        if not self.metrics_path.is_file():
            return
        with self.metrics_path.open("r+b") as file:
            lines = file.read().splitlines(keepends=True)
            column = COLUMNS.index("env_steps")
            keep = 0
            for number, line in enumerate(lines, start=1):
                if not line.endswith(b"\n"):
                    break
                if number > 1:
                    try:
                        row_steps = int(next(csv.reader([line.decode()]))[column])
                    except (ValueError, IndexError, UnicodeDecodeError):
                        raise CmatError(f"unreadable {self.metrics_path}, line {number}") from None
                    if row_steps > env_steps:
                        break
                keep += len(line)
            if keep < sum(map(len, lines)):
                file.truncate(keep)
                file.flush()
                os.fsync(file.fileno())

    def summary_writer(self, purge_step: int | None = None) -> SummaryWriter:
        """TensorBoard writer; `purge_step` hides events at or after it left by an earlier try."""
        return SummaryWriter(str(self.tb_path), purge_step=purge_step)


def parse_checkpoint(text: str) -> Checkpoint:
    """`--checkpoint TEXT`: `latest`, `best`, or the env steps of a periodic checkpoint.
    Raises CmatError for anything else."""
    if text in ("latest", "best"):
        return text
    if text.isascii() and text.isdigit():
        return int(text)
    raise CmatError(f"--checkpoint must be latest, best or the env steps of a kept checkpoint, "
                    f"got {text!r}")


def metrics_row_problem(header: list[str], cells: list[str]) -> str | None:
    """What is wrong with one metrics.csv row under `header`, or None."""
    if len(cells) != len(header):
        return f"{len(cells)} cells under {len(header)} columns"
    for column, cell in zip(header, cells):
        if column == "kind":
            if cell not in KINDS:
                return f"kind {cell!r} is none of {', '.join(KINDS)}"
        elif column in ("seed", "env_steps") or cell:
            try:
                int(cell) if column in ("seed", "env_steps") else float(cell)
            except ValueError:
                whole = " whole" if column in ("seed", "env_steps") else ""
                return f"{column} {cell!r} is not a{whole} number"
    return None


def csv_value(value: str | int | float) -> str | int | float:
    """A cell: NaN as `nan` (a value that is not a number, e.g. the win rate of an environment
    without one), so it cannot be mistaken for a missing cell."""
    if isinstance(value, float) and math.isnan(value):
        return "nan"
    return value


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@contextmanager
def naming(path: Path) -> Iterator[None]:
    """Re-raise an OSError without a file name (a full disk while writing) as one that names
    `path`, so that its one-line error says which file could not be written."""
    try:
        yield
    except OSError as error:
        if error.filename is not None:
            raise
        raise OSError(error.errno, error.strerror or str(error), str(path)) from None


UMASK = os.umask(0o022)
os.umask(UMASK)
"""The process's file-creation mask, read once: files written through a temporary file get the
permissions a plain `open` would give them (mkstemp's are 0600)."""


def atomic_write(path: Path, data: bytes) -> None:
    """Write `data` to `path` through a synced temporary file in the same directory. An
    OSError names `path`; the previous file stays as it was."""
    with naming(path):
        atomic_write_named(path, data)


def atomic_write_named(path: Path, data: bytes) -> None:
    descriptor, temp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        os.fchmod(descriptor, 0o666 & ~UMASK)
        with os.fdopen(descriptor, "wb") as file:
            file.write(data)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temp_name, path)
    except BaseException:
        Path(temp_name).unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def network_record(config: TrainConfig) -> dict[str, Any]:
    """`config.network` and the algorithm's options that shape its network
    (`AlgorithmOptions.network_options`) as a checkpoint header records them, by field name in
    one mapping (JSON values): the network its parameters belong to (`RunDir.save_checkpoint`,
    `cmat.runners.base.restore_run`). The options that change how the network computes, not
    what (`attention_block`), and the loss options are not recorded: a run may change them."""
    options = config.options
    record = {**dataclasses.asdict(config.network),
              **{name: getattr(options, name) for name in options.network_options}}
    recorded: dict[str, Any] = json.loads(json.dumps(record))
    return recorded


EVAL_PROTOCOL = 2
"""How the session's evaluations chose their episodes, recorded in each sessions.jsonl line:
2, the evaluation at env step t plays the episodes of episode seed t (fresh episodes at every
evaluation, `cmat.runners.base.Trainer.evaluate`); 1 (lines without the field, cmat before
2026-12-05), every evaluation of a run replayed the same episodes."""


class Session:
    """One training session of a run (a `cmat train` or `finetune`, or a `--resume`): where it
    ran (host, JAX backend and device, CPU cores) and its wall-clock seconds and env steps so far,
    rewritten as the last line of sessions.jsonl after every chunk, so a killed session keeps
    its record up to its last checkpoint."""

    def __init__(self, run_dir: RunDir, env_steps: int) -> None:
        import jax

        device = jax.devices()[0]
        self.run_dir = run_dir
        self.earlier = run_dir.sessions()
        self.start = time.monotonic()
        self.entry: dict[str, Any] = {
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "host": socket.gethostname(),
            "backend": jax.default_backend(), "device": device.device_kind,
            "cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
            else os.cpu_count(),
            "processes": jax.process_count(), "devices": len(jax.devices()),
            "from_steps": env_steps, "to_steps": env_steps, "seconds": 0.0,
            "eval_protocol": EVAL_PROTOCOL,
        }

    def record(self, env_steps: int) -> None:
        self.entry.update(to_steps=env_steps, seconds=round(time.monotonic() - self.start, 1))
        lines = [json.dumps(entry) + "\n" for entry in (*self.earlier, self.entry)]
        atomic_write(self.run_dir.sessions_path, "".join(lines).encode())
