"""`cmat experiment SPEC.yaml`: plan a grid of runs (`cmat.experiments.plan`), run what is
missing (`cmat.experiments.execute`), report the results from every complete run
(`cmat.experiments.report`).
"""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import shutil
from contextlib import nullcontext
from pathlib import Path

import yaml

from cmat.errors import CmatError
from cmat.experiments.baselines import BASELINES_DIR
from cmat.experiments.execute import (
    LocalExecutor,
    RayExecutor,
    default_parallel,
    discard,
    execute,
    experiment_lock,
    import_ray,
)
from cmat.experiments.plan import (
    FINISHED,
    NEW,
    REDO,
    RESUME,
    Plan,
    Run,
    inspect_all,
    make_plan,
    print_plan,
    retrain_exported_bases,
    say,
    schedule,
)
from cmat.experiments.report import write_report
from cmat.experiments.spec import load_spec
from cmat.rundir import RunDir


def run_experiment(
    spec_path: Path,
    out: Path | None = None,
    parallel: int | None = None,
    ray_address: str | None = None,
    dry_run: bool = False,
    report_only: bool = False,
    only: list[str] | None = None,
    export: Path | None = None,
    carry: bool = False,
    seeds_per_run: int | None = None,
) -> Plan:
    """Plan, execute and report the experiment of `spec_path` in `out`; with `report_only`,
    report the complete runs already in `out` and start none (without the directory's lock,
    so it can report a grid another process is still running). `only` (shell patterns on run
    names `ENV/VARIANT/ALGO-sFIRST-LAST`) runs just the matching runs of the grid; the report
    still covers every complete run. `export` copies the results of every complete run, without
    checkpoints, into that directory and reports there (`export_results`); `carry` adds the
    checkpoints the grid still needs, to continue it from that copy. `seeds_per_run` replaces
    the spec's for the seeds that have no run on disk yet (`cell_seed_groups`): one seed per
    run finishes a long cell piece by piece, each exported as it completes."""
    spec = load_spec(spec_path)
    if parallel is not None and parallel <= 0:
        raise CmatError(f"--parallel must be > 0, got {parallel}")
    if seeds_per_run is not None:
        if seeds_per_run <= 0:
            raise CmatError(f"--seeds-per-run must be > 0, got {seeds_per_run}")
        spec = dataclasses.replace(spec, seeds_per_run=min(seeds_per_run, spec.seeds))
    if dry_run and (report_only or export is not None):
        other = "--report-only" if report_only else "--export"
        raise CmatError(f"--dry-run and {other} exclude each other")
    out = (Path(out) if out is not None else Path("runs") / "experiments" / spec.name).absolute()
    if export is not None:
        export = Path(export).absolute()
        if export == out:
            raise CmatError(f"--export {export} is the experiment directory itself")
    elif carry:
        raise CmatError("--carry applies to --export only")
    if ray_address is not None and not report_only:
        import_ray()
    for flag, directory in (("--out", out), ("--export", export)):
        if directory is not None:
            check_directory_path(directory, flag)
            check_same_experiment(directory, spec.name)
    plan = make_plan(spec, out)
    selected = select(plan, only)
    if not report_only:
        selected = retrain_exported_bases(selected)
    if dry_run:
        print_plan(plan)
        say_selection(selected, plan, only)
        return plan
    if report_only and not out.is_dir():
        raise CmatError(f"--report-only: no experiment directory {out}")
    out.mkdir(parents=True, exist_ok=True)
    with nullcontext() if report_only else experiment_lock(out):
        inspect_all(plan)  # again: another experiment may have held the directory until now
        if not report_only:
            selected = retrain_exported_bases(select(plan, only))
        print_plan(plan)
        say_selection(selected, plan, only)
        if spec.path.resolve() != (out / "spec.yaml").resolve():
            shutil.copyfile(spec.path, out / "spec.yaml")
        for run in selected:
            if run.status == REDO and not report_only:
                discard(run, out)
        jobs = schedule([run for run in selected if run.status in (NEW, RESUME, REDO)])
        if jobs and not report_only:
            cache = out / "jax_cache"
            limit = parallel or (len(jobs) if ray_address is not None else default_parallel())
            executor = (RayExecutor(ray_address, cache) if ray_address is not None
                        else LocalExecutor(cache, limit))
            execute(jobs, executor, limit, out)
        written = write_report(plan)
        for path in written:
            say(f"wrote {path}")
    if export is not None:
        export_results(plan, export, carry)
    failed = [run for run in plan.runs if run.outcome not in (None, "ok")]
    if failed:
        raise CmatError(
            f"{len(failed)} of {len(plan.runs)} runs did not complete "
            f"(first: {failed[0].name}: {failed[0].outcome}); the others are reported in "
            f"{out / 'results.md'}; run the same command again to retry"
        )
    return plan


def check_directory_path(directory: Path, flag: str) -> None:
    """CmatError where `directory`, or the nearest of its parents that exists, is not a
    directory (a file), before anything is planned or written."""
    existing = next((path for path in (directory, *directory.parents) if path.exists()), None)
    if existing is not None and not existing.is_dir():
        where = "" if existing == directory else f": its parent {existing}"
        raise CmatError(f"{flag} {directory}{where} is a file, not a directory")


def check_same_experiment(directory: Path, name: str) -> None:
    """CmatError where `directory` holds the report of an experiment named otherwise than
    `name` (its `results.json`, else the `name` in its `spec.yaml`): running or reporting
    another spec there would replace that experiment's spec, report and figures."""
    recorded = None
    for file in (directory / "results.json", directory / "spec.yaml"):
        try:
            loaded = (json.loads if file.suffix == ".json" else yaml.safe_load)(file.read_text())
        except (OSError, ValueError, yaml.YAMLError):
            continue
        if isinstance(loaded, dict) and isinstance(loaded.get("name"), str):
            recorded = loaded["name"]
            break
    if recorded is not None and recorded != name:
        raise CmatError(f"{directory} holds the experiment {recorded!r}, not {name!r}: give "
                        f"{name!r} a directory of its own (--out, --export)")


def select(plan: Plan, only: list[str] | None) -> list[Run]:
    """The runs of `plan` whose names match one of the shell patterns `only` (all without);
    CmatError for a pattern that matches none."""
    if only is None:
        return plan.runs
    for pattern in only:
        if not any(fnmatch.fnmatchcase(run.name, pattern) for run in plan.runs):
            example = plan.runs[0].name if plan.runs else "ENV/VARIANT/ALGO-sFIRST-LAST"
            raise CmatError(f"--only {pattern!r} matches no run of the grid (runs are named "
                            f"like {example!r})")
    return [run for run in plan.runs
            if any(fnmatch.fnmatchcase(run.name, pattern) for pattern in only)]


def say_selection(selected: list[Run], plan: Plan, only: list[str] | None) -> None:
    if only is not None:
        say(f"--only {' '.join(only)}: {len(selected)} of {len(plan.runs)} runs: "
            + ", ".join(run.name for run in selected))


def export_results(plan: Plan, target: Path, carry: bool = False) -> None:
    """Copy every complete run of `plan` into `target` as results without checkpoints
    (`RunDir.export`), with the spec and the baselines' evaluations, then write the report
    there from every complete run `target` holds, so `target` can be committed or shared.
    Runs `target` holds that `plan`'s directory lacks stay. `target` then serves as `--out` for
    `--report-only`, and a copy of it as `--out` to continue the grid on another machine:
    exported runs count as complete (a fine-tuning stage still to run retrains its base first).

    With `carry`, the runs the grid still needs go with their checkpoints, so the copy continues
    them instead of starting over: every partial run past its first chunk (resumed there; one
    that has only its initial checkpoint starts over), and every complete run
    that a fine-tuning stage not yet complete starts from. Once nothing needs them, the next
    export replaces those copies with results only."""
    inspect_all(plan)
    pending_bases = {run.base.name for run in plan.runs
                     if run.base is not None and run.status in (NEW, RESUME, REDO)}
    complete = [run for run in plan.runs if run.status == FINISHED]
    partial = [run for run in plan.runs
               if carry and run.status == RESUME and RunDir(run.path).checkpoint_steps()[0] > 0]
    carried = []
    for run in complete + partial:
        run_dir = RunDir(run.path)
        keep = carry and (run.status == RESUME or (run.name in pending_bases
                                                    and run_dir.checkpoint_path.is_file()))
        run_dir.export(target / "runs" / run.name, checkpoint=keep)
        if keep:
            carried.append(run.name)
    target.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(plan.spec.path, target / "spec.yaml")
    if (plan.out / BASELINES_DIR).is_dir():
        shutil.copytree(plan.out / BASELINES_DIR, target / BASELINES_DIR, dirs_exist_ok=True)
    say(f"exported {len(complete)} complete runs (results without checkpoints) to {target}")
    if carry:
        say(f"carried {len(carried)} runs with their checkpoints (partial, or the base of a "
            f"fine-tuning stage still to run)" + (": " + ", ".join(carried) if carried else ""))
    exported = make_plan(plan.spec, target)
    for path in write_report(exported):
        say(f"wrote {path}")
