"""`cmat experiment SPEC.yaml`: plan a grid of runs, run what is missing, report the results.

Every cell of the grid (environment × variant × algorithm × seed group) is one run directory
under `OUT/runs/ENV/VARIANT/ALGO-sFIRST-LAST`. Before anything runs, each directory is inspected:

- absent (or empty): a new run;
- complete (checkpoint at the run's budget, checksum good, eval rows of every seed at that
  step, config equal to what the spec asks): reused as it is;
- partial (a good checkpoint below the budget): resumed from it (`cmat train --resume`);
- anything else (unreadable config, a config that differs from the spec, no or a corrupt
  checkpoint, metrics that lack the checkpoint's eval rows, a fine-tuning stage whose base run
  is being retrained): reported, moved to `OUT/discarded/`, and run again.

Runs execute as `python -m cmat train|finetune` subprocesses, K at once on this machine, or as
Ray tasks on a cluster (`--ray ADDRESS`; every node needs cmat installed and OUT on a shared
filesystem). A fine-tuning stage starts once its base run has finished. Environments the spec
marks unavailable, or that cannot be built here (a suite not installed, an unknown id), are
reported and skipped. At the end the figures, table and statistics are written from every
complete run (`cmat.experiments.report`).
"""

from __future__ import annotations

import dataclasses
import fcntl
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cmat.config import TrainConfig, load_config, resolve_iterations
from cmat.errors import CmatError
from cmat.experiments.spec import EnvEntry, ExperimentSpec, Variant, load_spec
from cmat.rundir import RunDir
from cmat.runners.finetune import finetune_config

FINISHED, NEW, RESUME, REDO, UNAVAILABLE = "finished", "new", "resume", "redo", "unavailable"
IGNORED_FIELDS = ("finetune_from", "logger")
"""Config fields a reused run may differ in: the source path of a fine-tuning stage (absolute
when written) changes when the experiment directory moves, the layout fixes the source; where
scalars were also logged changes no result."""


@dataclass
class Run:
    """One cell of the grid and what has to happen to it."""

    env: EnvEntry
    variant: Variant
    algo: str
    seed: int
    seeds: int
    path: Path
    name: str
    config: TrainConfig | None
    base: Run | None = None
    overrides: tuple[str, ...] = ()
    """What `cmat train --set` needs to rebuild `config` (runs that are not stages)."""
    status: str = NEW
    note: str = ""
    found: str = ""
    """The status planned from what was on disk (status becomes FINISHED once run)."""
    num_agents: int | None = None
    outcome: str | None = None
    """After execution: None (not run), 'ok' or the reason it failed or was skipped."""
    log: Path | None = None

    @property
    def complete(self) -> bool:
        return self.status == FINISHED or self.outcome == "ok"

    @property
    def iterations(self) -> int | None:
        """The resolved m of a CMAT run (None for other algorithms or an unknown n)."""
        if self.algo != "cmat" or self.config is None or self.num_agents is None:
            return None
        return resolve_iterations(self.config.network.consensus_iterations, self.num_agents)


@dataclass
class Plan:
    spec: ExperimentSpec
    out: Path
    runs: list[Run] = field(default_factory=list)
    unavailable: dict[str, str] = field(default_factory=dict)
    """Environment id -> why it is skipped."""


def run_experiment(
    spec_path: Path,
    out: Path | None = None,
    parallel: int | None = None,
    ray_address: str | None = None,
    dry_run: bool = False,
    report_only: bool = False,
) -> Plan:
    """Plan, execute and report the experiment of `spec_path` in `out`; with `report_only`,
    report the complete runs already in `out` and start none (without the directory's lock,
    so it can report a grid another process is still running)."""
    spec = load_spec(spec_path)
    if parallel is not None and parallel <= 0:
        raise CmatError(f"--parallel must be > 0, got {parallel}")
    if dry_run and report_only:
        raise CmatError("--dry-run and --report-only exclude each other")
    out = (Path(out) if out is not None else Path("runs") / "experiments" / spec.name).absolute()
    plan = make_plan(spec, out)
    if dry_run:
        print_plan(plan)
        return plan
    if report_only and not out.is_dir():
        raise CmatError(f"--report-only: no experiment directory {out}")
    out.mkdir(parents=True, exist_ok=True)
    with nullcontext() if report_only else experiment_lock(out):
        inspect_all(plan)  # again: another experiment may have held the directory until now
        print_plan(plan)
        if spec.path.resolve() != (out / "spec.yaml").resolve():
            shutil.copyfile(spec.path, out / "spec.yaml")
        for run in plan.runs:
            if run.status == REDO and not report_only:
                discard(run, out)
        jobs = [run for run in plan.runs if run.status in (NEW, RESUME, REDO)]
        if jobs and not report_only:
            cache = out / "jax_cache"
            executor = (RayExecutor(ray_address, cache) if ray_address is not None
                        else LocalExecutor(cache))
            limit = parallel or (len(jobs) if ray_address is not None else default_parallel())
            execute(jobs, executor, limit, out)
        from cmat.experiments.report import write_report

        written = write_report(plan)
        for path in written:
            say(f"wrote {path}")
    failed = [run for run in plan.runs if run.outcome not in (None, "ok")]
    if failed:
        raise CmatError(
            f"{len(failed)} of {len(plan.runs)} runs did not complete "
            f"(first: {failed[0].name}: {failed[0].outcome}); the others are reported in "
            f"{out / 'results.md'}; run the same command again to retry"
        )
    return plan


# ----------------------------------------------------------------------------------- planning


def make_plan(spec: ExperimentSpec, out: Path) -> Plan:
    """Every run of the grid with its expected config and its status on disk."""
    plan = Plan(spec, out)
    cells: dict[tuple[str, str, str, int], Run] = {}
    ordered = order_variants(spec.variants)
    for env in spec.envs:
        env_runs = []
        for variant in (v for v in ordered if v.covers(env.id)):
            for algo in variant.algos:
                for seed, seeds in spec.seed_groups():
                    base = cells.get((env.id, variant.base or "", algo, seed))
                    run = make_run(spec, out, env, variant, algo, seed, seeds, base)
                    cells[(env.id, variant.name, algo, seed)] = run
                    env_runs.append(run)
        num_agents, reason = None, None
        if env.unavailable is not None:
            reason = f"marked unavailable in the spec: {env.unavailable}"
        else:
            assert env_runs[0].config is not None
            num_agents, reason = probe_env(env_runs[0].config)
        for run in env_runs:
            run.num_agents = num_agents
            if reason is not None:
                run.status, run.note = UNAVAILABLE, reason
        if reason is not None:
            plan.unavailable[env.id] = reason
        plan.runs.extend(env_runs)
    inspect_all(plan)
    return plan


def inspect_all(plan: Plan) -> None:
    """Set every available run's status from its directory (bases before their stages)."""
    for run in plan.runs:
        if run.status != UNAVAILABLE:
            run.status, run.note = inspect(run)
        run.found = run.status


def order_variants(variants: tuple[Variant, ...]) -> list[Variant]:
    """Variants with every fine-tuning stage after the variant it starts from."""
    ordered: list[Variant] = []
    remaining = list(variants)
    while remaining:
        for variant in remaining:
            if variant.base is None or variant.base in {v.name for v in ordered}:
                ordered.append(variant)
                remaining.remove(variant)
                break
    return ordered


def make_run(
    spec: ExperimentSpec, out: Path, env: EnvEntry, variant: Variant, algo: str, seed: int,
    seeds: int, base: Run | None,
) -> Run:
    """A run with the config the spec asks for (checked now, so a bad spec fails up front)."""
    last = seed + seeds - 1
    name = f"{env.slug}/{variant.name}/{algo}-s{seed}" + (f"-{last}" if last != seed else "")
    run = Run(env, variant, algo, seed, seeds, out / "runs" / name, name, None, base)
    where = f"experiment spec {spec.path}: {env.id} / {variant.name} / {algo}"
    try:
        if variant.finetune is not None:
            assert base is not None and base.config is not None
            run.config, _ = finetune_config(base.config, base.path, variant.finetune,
                                            variant.steps or env.steps, variant.overrides)
        else:
            explicit = [f"env={env.id}", f"algo={algo}",
                        f"total_steps={variant.steps or env.steps}", f"seeds={seeds}",
                        f"seed={seed}"]
            run.overrides = (*spec.overrides, *env.overrides, *variant.overrides, *explicit)
            run.config = load_config(None, run.overrides)
    except CmatError as error:
        raise CmatError(f"{where}: {error}") from None
    return run


def probe_env(config: TrainConfig) -> tuple[int | None, str | None]:
    """(number of agents, None), or (None, why the environment cannot be built here)."""
    from cmat.envs import make_env

    try:
        prefix = config.env.partition(":")[0]
        from cmat.envs import HOST_PREFIXES

        if prefix in HOST_PREFIXES:
            from cmat.envs.host import make_host_env

            env: Any = make_host_env(config.env, **config.env_kwargs)
        else:
            env = make_env(config.env, **config.env_kwargs)
        num_agents = int(env.spec.num_agents)
        close = getattr(env, "close", None)
        if callable(close):
            close()
        return num_agents, None
    except CmatError as error:
        return None, str(error)
    except Exception as error:  # a suite's own import or build failure: report, don't crash
        return None, f"{type(error).__name__}: {error}".splitlines()[0]


def inspect(run: Run) -> tuple[str, str]:
    """What to do with `run`'s directory, and why (see the module docstring)."""
    path, expected = run.path, run.config
    if run.base is not None and run.base.status != FINISHED:
        if path.exists() and any(path.iterdir()):
            return REDO, "its base run is not complete yet, so this stage must start again"
        return NEW, f"after {run.base.name}"
    if not path.exists() or not any(path.iterdir()):
        return NEW, ""
    assert expected is not None
    try:
        run_dir = RunDir.open(path)
        config = run_dir.config()
    except (CmatError, OSError, UnicodeDecodeError) as error:
        return REDO, f"unreadable run directory: {error}"
    differs = config_difference(config, expected)
    if differs is not None:
        return REDO, f"config differs from the spec ({differs})"
    try:
        _, steps = run_dir.load_checkpoint()
    except CmatError as error:
        return REDO, str(error)
    target = expected.budget_steps
    if steps > target:
        return REDO, f"checkpoint at {steps} env steps, past the spec's {target}"
    if steps > 0:
        problem = metrics_problem(run_dir, steps, config)
        if problem is not None:
            return REDO, problem
    if steps == target:
        return FINISHED, f"complete at {steps} env steps"
    return RESUME, f"at {steps} of {target} env steps"


def config_difference(found: TrainConfig, expected: TrainConfig) -> str | None:
    """The first field (dotted) in which `found` differs from `expected`, ignoring the budget
    (a longer budget resumes) and IGNORED_FIELDS; None if none does."""
    ignore = {name: getattr(expected, name) for name in ("total_steps", *IGNORED_FIELDS)}
    left = dataclasses.asdict(dataclasses.replace(found, **ignore))
    right = dataclasses.asdict(expected)
    for key in right:
        if isinstance(right[key], dict) and isinstance(left[key], dict) and key != "env_kwargs":
            for sub in right[key]:
                if left[key].get(sub) != right[key][sub]:
                    return f"{key}.{sub}: {left[key].get(sub)!r}, spec {right[key][sub]!r}"
        elif left[key] != right[key]:
            return f"{key}: {left[key]!r}, spec {right[key]!r}"
    return None


def metrics_problem(run_dir: RunDir, steps: int, config: TrainConfig) -> str | None:
    """Why metrics.csv cannot back a checkpoint at `steps`, or None."""
    try:
        rows = run_dir.read_metrics()
        final = {int(r["seed"]) for r in rows
                 if r["kind"] == "eval" and int(r["env_steps"]) == steps}
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as error:
        return f"unreadable metrics.csv ({type(error).__name__})"
    seeds = set(range(config.seed, config.seed + config.seeds))
    if not seeds <= final:
        return f"metrics.csv lacks the eval rows of its checkpoint at {steps} env steps"
    return None


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


def print_plan(plan: Plan) -> None:
    counts = {status: sum(r.status == status for r in plan.runs)
              for status in (FINISHED, RESUME, NEW, REDO, UNAVAILABLE)}
    say(f"experiment {plan.spec.name}: {len(plan.runs)} runs in {plan.out} "
        f"({counts[FINISHED]} complete, {counts[RESUME]} to resume, {counts[NEW]} new, "
        f"{counts[REDO]} to redo, {counts[UNAVAILABLE]} unavailable)")
    for env_id, reason in plan.unavailable.items():
        say(f"  skip    {env_id}: unavailable: {reason}")
    labels = {FINISHED: "reuse", RESUME: "resume", NEW: "new", REDO: "redo"}
    for run in plan.runs:
        if run.status in labels:
            say(f"  {labels[run.status]:7} {run.name}" + (f": {run.note}" if run.note else ""))


def say(message: str) -> None:
    print(message, flush=True)


@contextmanager
def experiment_lock(out: Path) -> Iterator[None]:
    """One `cmat experiment` at a time per directory (released by the OS if it dies)."""
    with (out / ".lock").open("w") as file:
        try:
            fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise CmatError(f"another cmat experiment is running in {out}") from None
        yield


# ---------------------------------------------------------------------------------- execution


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
    """Runs at once on this machine: one per two cores (XLA uses several threads per run),
    at most one per 4 GiB of available memory."""
    cpus = len(os.sched_getaffinity(0))
    available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 2**30
    return max(1, min(cpus // 2, int(available // 4)))


def execute(jobs: list[Run], executor: Any, limit: int, out: Path) -> None:
    """Run `jobs` (fine-tuning stages after their base) with at most `limit` at once."""
    pending = list(jobs)
    running: dict[Any, tuple[Run, float]] = {}
    total, finished = len(jobs), 0
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
            handle, code = executor.wait(list(running))
            run, started = running.pop(handle)
            finished += 1
            run.outcome = judge(run, code)
            seconds = time.monotonic() - started
            result = "done" if run.outcome == "ok" else f"FAILED: {run.outcome}"
            say(f"[{finished}/{total}] {run.name}: {result} ({seconds:.0f} s)")
    except BaseException:
        executor.stop(list(running))
        raise


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
        return subprocess.run([sys.executable, "-m", "cmat", *argv], stdout=log,
                              stderr=subprocess.STDOUT, env=child_env(cache), check=False).returncode


def child_env(cache: str, parent: int | None = None) -> dict[str, str]:
    """The environment of a run: unbuffered output; JAX's persistent compilation cache in the
    experiment directory (runs of a grid compile the same programs: a rerun or a resumed run
    loads them instead of compiling, unless JAX_COMPILATION_CACHE_DIR is set already); and the
    pid whose death should end the run (see `cmat.__main__`)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "TF_CPP_MIN_LOG_LEVEL": "2"}
    env.setdefault("JAX_COMPILATION_CACHE_DIR", cache)
    if parent is not None:
        env["CMAT_PARENT_PID"] = str(parent)
    return env


class LocalExecutor:
    """Runs as subprocesses of this process; each ends when this process dies (a killed
    experiment leaves no run writing into its directory)."""

    def __init__(self, cache: Path) -> None:
        self.cache = str(cache)

    def submit(self, argv: list[str], log: Path) -> subprocess.Popen:
        with log.open("a") as file:
            return subprocess.Popen(
                [sys.executable, "-m", "cmat", *argv], stdout=file, stderr=subprocess.STDOUT,
                env=child_env(self.cache, parent=os.getpid()),
            )

    def wait(self, handles: list[subprocess.Popen]) -> tuple[subprocess.Popen, int]:
        while True:
            for process in handles:
                code = process.poll()
                if code is not None:
                    return process, code
            time.sleep(0.2)

    def stop(self, handles: list[subprocess.Popen]) -> None:
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


class RayExecutor:
    """Runs as Ray tasks of one CPU each on the cluster at `address` (`ray.init(address)`)."""

    def __init__(self, address: str, cache: Path) -> None:
        self.cache = str(cache)
        try:
            import ray
        except ImportError:
            raise CmatError("--ray needs Ray: pip install 'cmat[ray]'") from None
        self.ray = ray
        try:
            ray.init(address=address, ignore_reinit_error=True, log_to_driver=False)
        except Exception as error:  # Ray raises ConnectionError, RuntimeError, ValueError
            raise CmatError(f"cannot connect to the Ray cluster at {address}: "
                            f"{str(error).splitlines()[0] if str(error) else error!r}") from None
        self.task = ray.remote(num_cpus=1)(run_cmat)

    def submit(self, argv: list[str], log: Path) -> Any:
        return self.task.remote(argv, str(log), self.cache)

    def wait(self, handles: list[Any]) -> tuple[Any, int | str]:
        ready, _ = self.ray.wait(handles, num_returns=1)
        try:
            return ready[0], int(self.ray.get(ready[0]))
        except Exception as error:  # the task or its node died
            return ready[0], f"Ray task failed: {type(error).__name__}"

    def stop(self, handles: list[Any]) -> None:
        for ref in handles:
            self.ray.cancel(ref, force=True)
