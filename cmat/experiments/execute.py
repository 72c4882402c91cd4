"""Executing an experiment's runs: as `python -m cmat train|finetune` subprocesses, K at once on
this machine, or as Ray tasks on a cluster (`--ray ADDRESS`; every node needs cmat installed and
OUT on a shared filesystem). A fine-tuning stage starts once its base run has finished; a run to
redo is first moved to `OUT/discarded/`.
"""

from __future__ import annotations

import fcntl
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from tqdm import tqdm

from cmat.errors import CmatError
from cmat.experiments.plan import FINISHED, RESUME, Run, inspect, say
from cmat.rundir import RunDir


def discard(run: Run, out: Path) -> None:
    """Move a directory that cannot be used out of the grid (kept for inspection)."""
    if not run.path.exists():
        return
    target = out / "discarded" / f"{run.name.replace('/', '__')}-{time.strftime('%Y%m%d-%H%M%S')}"
    number = 1
    while target.exists():
        target = target.with_name(f"{target.name}-{number}")
        number += 1
    target.parent.mkdir(parents=True, exist_ok=True)
    run.path.rename(target)
    run.note += f"; moved to {target.relative_to(out)}"


@contextmanager
def experiment_lock(out: Path) -> Iterator[None]:
    """One `cmat experiment` at a time per directory (released by the OS if it dies)."""
    with (out / ".lock").open("w") as file:
        try:
            fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise CmatError(f"another cmat experiment is running in {out}") from None
        yield


def command(run: Run) -> list[str]:
    """The `cmat` arguments that bring `run` to completion."""
    assert run.config is not None
    steps = str(run.config.total_steps)
    if run.status == RESUME:
        return ["train", "--resume", str(run.path), "--steps", steps]
    if run.variant.finetune is not None:
        assert run.base is not None
        overrides = ["--set", *run.variant.overrides] if run.variant.overrides else []
        return ["finetune", "--from", str(run.base.path), "--mode", run.variant.finetune,
                "--steps", steps, "--out", str(run.path), *overrides]
    return ["train", "--out", str(run.path), "--set", *run.overrides]


def default_parallel() -> int:
    """Runs at once on this machine: one per two cores (each on its own two, `core_groups`),
    at most one per 4 GiB of available memory."""
    cpus = len(os.sched_getaffinity(0))
    available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 2**30
    return max(1, min(cpus // 2, int(available // 4)))


def core_groups(slots: int) -> list[list[int]]:
    """This process's cores split into `slots` disjoint groups of consecutive cores, one per
    run at once; none (runs share every core) for one slot or fewer cores than slots.

    Runs that share cores each size XLA's thread pool to all of them and contend: on this
    project's 2-core machine two SMAX 2s3z CMAT runs (3 seeds each) at once trained at 1.07-1.17x
    the summed steps/s when each was pinned to one core (docs/experiments.md, "Where the runs
    execute").
    """
    cores = sorted(os.sched_getaffinity(0))
    if slots <= 1 or len(cores) < slots:
        return []
    size, extra = divmod(len(cores), slots)
    groups, start = [], 0
    for slot in range(slots):
        end = start + size + (1 if slot < extra else 0)
        groups.append(cores[start:end])
        start = end
    return groups


def execute(jobs: list[Run], executor: Any, limit: int, out: Path) -> None:
    """Run `jobs` (fine-tuning stages after their base) with at most `limit` at once, showing
    the grid's progress (`GridProgress`) while they run."""
    pending = list(jobs)
    running: dict[Any, tuple[Run, float]] = {}
    total, finished = len(jobs), 0
    progress = GridProgress(jobs)
    try:
        while pending or running:
            for run in list(pending):
                if len(running) >= limit:
                    break
                base = run.base
                if base is not None and base in jobs and base.outcome is None:
                    continue
                pending.remove(run)
                if base is not None and not base.complete:
                    run.outcome = f"skipped: its base run {base.name} did not complete"
                    say(f"[skip] {run.name}: {run.outcome}")
                    continue
                run.log = out / "logs" / f"{run.name}.log"
                run.log.parent.mkdir(parents=True, exist_ok=True)
                argv = command(run)
                with run.log.open("a") as log:
                    log.write(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} cmat {' '.join(argv)}\n")
                handle = executor.submit(argv, run.log)
                running[handle] = (run, time.monotonic())
                say(f"[start] {run.name} ({run.status}; log {run.log.relative_to(out)})")
            if not running:
                continue
            progress.show([run for run, _ in running.values()], len(pending))
            ended = executor.wait(list(running), timeout=PROGRESS_SECONDS)
            if ended is None:
                continue
            handle, code = ended
            run, started = running.pop(handle)
            finished += 1
            run.outcome = judge(run, code)
            seconds = time.monotonic() - started
            result = "done" if run.outcome == "ok" else f"FAILED: {run.outcome}"
            progress.show([run for run, _ in running.values()], len(pending))
            say(f"[{finished}/{total}] {run.name}: {result} ({seconds:.0f} s); "
                f"{progress.summary()}")
    except BaseException:
        executor.stop(list(running))
        raise
    finally:
        progress.close()


PROGRESS_SECONDS = 2.0
"""How often the grid's progress is read from the running runs' checkpoints."""


class GridProgress:
    """The grid's progress over the env steps of every seed of `jobs`, read from the runs'
    checkpoint headers: a bar on a terminal (runs done, running, queued; steps/s; ETA) and a
    summary for each run's `done` line. Steps/s counts from the first steps any run of this
    execution wrote, so compilation before them is not in it; later runs' compilation is, as
    it is part of what the grid still has to do."""

    def __init__(self, jobs: list[Run]) -> None:
        self.jobs = jobs
        self.start = {run.name: self.steps(run) for run in jobs}
        self.total = sum(self.budget(run) for run in jobs)
        self.done_before = sum(self.start.values())
        self.first: tuple[int, float] | None = None
        self.bar = tqdm(total=self.total, initial=self.done_before, unit="step",
                        unit_scale=True, desc="grid", disable=None, dynamic_ncols=True,
                        smoothing=0, bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} {postfix}")

    @staticmethod
    def budget(run: Run) -> int:
        return 0 if run.config is None else run.config.budget_steps * run.config.seeds

    @staticmethod
    def steps(run: Run) -> int:
        """Env steps of every seed in `run`'s latest checkpoint, read from its header alone
        (this is polled while runs train; 0 before the first)."""
        steps = (RunDir(run.path).checkpoint_header() or {}).get("env_steps")
        if run.config is None or not isinstance(steps, int):
            return 0
        return steps * run.config.seeds

    def done_steps(self) -> int:
        return sum(self.budget(run) if run.outcome == "ok" else self.steps(run)
                   for run in self.jobs)

    def rate(self, done: int) -> float | None:
        """Env steps per second since the first steps of this execution."""
        now = time.monotonic()
        if self.first is None:
            if done > self.done_before:
                self.first = (done, now)
            return None
        steps, since = self.first
        return (done - steps) / (now - since) if done > steps and now > since else None

    def summary(self, running: int | None = None, queued: int | None = None) -> str:
        done = self.done_steps()
        rate = self.rate(done)
        finished = sum(run.outcome is not None for run in self.jobs)
        parts = [f"{finished}/{len(self.jobs)} runs ended"]
        if running is not None:
            parts.append(f"{running} running, {queued} queued")
        parts.append(f"{done / max(self.total, 1):.0%} of {self.total:,} env steps")
        if rate:
            eta = (self.total - done) / rate
            parts.append(f"{rate:,.0f} steps/s, ETA {format_seconds(eta)}")
        self.bar.n = done
        return ", ".join(parts)

    def show(self, running: list[Run], queued: int) -> None:
        self.bar.set_postfix_str(self.summary(len(running), queued), refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        self.bar.close()


def format_seconds(seconds: float) -> str:
    """`42 s`, `17 min`, `3.2 h`."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def judge(run: Run, code: int | str) -> str:
    """'ok' when the run exited 0 and its directory is now complete; else what went wrong."""
    if isinstance(code, str):
        return code
    if code != 0:
        return f"exit code {code}: {last_error(run.log)}"
    status, note = inspect(run)
    if status != FINISHED:
        return f"exited 0 but the run directory is not complete: {note}"
    run.status = FINISHED
    return "ok"


def last_error(log: Path | None) -> str:
    if log is None or not log.is_file():
        return "no log"
    lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("cmat: error:")]
    raised = [line for line in lines if re.match(r"^[\w.]+(Error|Exception|Interrupt)\b", line)]
    return (errors or raised or lines or ["no output"])[-1][:300]


def run_cmat(argv: list[str], log_path: str, cache: str) -> int:
    """Run `python -m cmat ARGV` with this interpreter, appending its output to `log_path`
    (what a Ray task executes on its node)."""
    with open(log_path, "a") as log:
        return subprocess.run(
            [sys.executable, "-m", "cmat", *argv], stdout=log, stderr=subprocess.STDOUT,
            env=child_env(cache), check=False,
        ).returncode


def child_env(
    cache: str, parent: int | None = None, cores: list[int] | None = None
) -> dict[str, str]:
    """The environment of a run: unbuffered output; JAX's persistent compilation cache in the
    experiment directory (runs of a grid compile the same programs: a rerun or a resumed run
    loads them instead of compiling, unless JAX_COMPILATION_CACHE_DIR is set already); the
    pid whose death should end the run and the cores it may use (see `cmat.__main__`)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "TF_CPP_MIN_LOG_LEVEL": "2"}
    env.setdefault("JAX_COMPILATION_CACHE_DIR", cache)
    if parent is not None:
        env["CMAT_PARENT_PID"] = str(parent)
    if cores:
        env["CMAT_CORES"] = ",".join(map(str, cores))
    return env


class LocalExecutor:
    """Runs as subprocesses of this process; each ends when this process dies (a killed
    experiment leaves no run writing into its directory). With `slots` runs at once, each
    runs on its own group of cores (`core_groups`)."""

    def __init__(self, cache: Path, slots: int = 1) -> None:
        self.cache = str(cache)
        self.free_cores = core_groups(slots)
        self.cores: dict[subprocess.Popen[bytes], list[int]] = {}

    def submit(self, argv: list[str], log: Path) -> subprocess.Popen[bytes]:
        cores = self.free_cores.pop(0) if self.free_cores else None
        with log.open("a") as file:
            process = subprocess.Popen(
                [sys.executable, "-m", "cmat", *argv], stdout=file, stderr=subprocess.STDOUT,
                env=child_env(self.cache, parent=os.getpid(), cores=cores),
            )
        if cores is not None:
            self.cores[process] = cores
        return process

    def wait(
        self, handles: list[subprocess.Popen[bytes]], timeout: float | None = None
    ) -> tuple[subprocess.Popen[bytes], int] | None:
        """The first of `handles` to end and its exit code; None if none ends in `timeout`
        seconds."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            for process in handles:
                code = process.poll()
                if code is not None:
                    if process in self.cores:
                        self.free_cores.append(self.cores.pop(process))
                    return process, code
            if deadline is not None and time.monotonic() >= deadline:
                return None
            time.sleep(0.2)

    def stop(self, handles: list[subprocess.Popen[bytes]]) -> None:
        """Interrupt running runs (they keep their last checkpoint), then kill stragglers."""
        for process in handles:
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 30
        for process in handles:
            try:
                process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()


def import_ray() -> Any:
    """The `ray` module; CmatError naming the extra to install where it is missing."""
    try:
        import ray
    except ImportError:
        raise CmatError("--ray needs Ray: pip install 'ray>=2.40,<3' (cmat's ray extra)") from None
    return ray


class RayExecutor:
    """Runs as Ray tasks of one CPU each on the cluster at `address` (`ray.init(address)`)."""

    def __init__(self, address: str, cache: Path) -> None:
        self.cache = str(cache)
        self.ray = ray = import_ray()
        try:
            ray.init(address=address, ignore_reinit_error=True, log_to_driver=False)
        except Exception as error:  # Ray raises ConnectionError, RuntimeError, ValueError
            raise CmatError(f"cannot connect to the Ray cluster at {address}: "
                            f"{str(error).splitlines()[0] if str(error) else error!r}") from None
        self.task = ray.remote(num_cpus=1)(run_cmat)

    def submit(self, argv: list[str], log: Path) -> Any:
        return self.task.remote(argv, str(log), self.cache)

    def wait(
        self, handles: list[Any], timeout: float | None = None
    ) -> tuple[Any, int | str] | None:
        ready, _ = self.ray.wait(handles, num_returns=1, timeout=timeout)
        if not ready:
            return None
        try:
            return ready[0], int(self.ray.get(ready[0]))
        except Exception as error:  # the task or its node died
            return ready[0], f"Ray task failed: {type(error).__name__}"

    def stop(self, handles: list[Any]) -> None:
        for ref in handles:
            self.ray.cancel(ref, force=True)
