"""Planning an experiment: the grid's runs and what each needs, from what is on disk.

Every cell of the grid (environment × variant × algorithm) is one run directory per seed group
under `OUT/runs/ENV/VARIANT/ALGO-sFIRST-LAST` (`cell_seed_groups`: the groups on disk stay, the
other seeds go in groups of the spec's `seeds_per_run`). Before anything runs, each directory is
inspected:

- absent (or empty): a new run;
- complete (checkpoint at the run's budget, checksum good, eval rows of every seed at that
  step, config equal to what the spec asks): reused as it is;
- partial (a good checkpoint below the budget): resumed from it (`cmat train --resume`);
- anything else (unreadable config, a config that differs from the spec, no or a corrupt
  checkpoint, metrics that lack the checkpoint's eval rows, a fine-tuning stage whose base run
  is being retrained): reported, then moved to `OUT/discarded/` and run again
  (`cmat.experiments.execute`).

Environments the spec marks unavailable, or that cannot be built here (a suite not installed,
an unknown id), are reported and skipped.
"""

from __future__ import annotations

import dataclasses
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from cmat.algorithms.cmat.options import CMATOptions
from cmat.config import TrainConfig
from cmat.envs import probe_env
from cmat.errors import CmatError
from cmat.experiments.spec import EnvEntry, ExperimentSpec, Variant, for_algorithm
from cmat.resolve import load_config
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
        if (self.config is None or self.num_agents is None
                or not isinstance(self.config.options, CMATOptions)):
            return None
        return self.config.options.iterations(self.num_agents)


@dataclass
class Plan:
    spec: ExperimentSpec
    out: Path
    runs: list[Run] = field(default_factory=list)
    unavailable: dict[str, str] = field(default_factory=dict)
    """Environment id -> why it is skipped."""


def make_plan(spec: ExperimentSpec, out: Path) -> Plan:
    """Every run of the grid with its expected config and its status on disk."""
    plan = Plan(spec, out)
    cells: dict[tuple[str, str, str, int], Run] = {}
    groups: dict[tuple[str, str, str], list[tuple[int, int]]] = {}
    ordered = order_variants(spec.variants)
    for env in spec.envs:
        env_runs = []
        for variant in (v for v in ordered if v.covers(env.id)):
            for algo in variant.algos:
                groups[env.id, variant.name, algo] = (
                    groups[env.id, variant.base, algo] if variant.base is not None
                    else cell_seed_groups(spec, out / "runs" / env.slug / variant.name, algo))
                for seed, seeds in groups[env.id, variant.name, algo]:
                    base = cells.get((env.id, variant.base or "", algo, seed))
                    run = make_run(spec, out, env, variant, algo, seed, seeds, base)
                    cells[(env.id, variant.name, algo, seed)] = run
                    env_runs.append(run)
        num_agents, reason = None, None
        if env.unavailable is not None:
            reason = f"marked unavailable in the spec: {env.unavailable}"
        else:
            config = env_runs[0].config
            assert config is not None
            try:
                num_agents, reason = probe_env(config.env, config.env_kwargs)
            except CmatError as error:
                raise CmatError(f"{spec.path}: task {env.id}: {error}") from None
        for run in env_runs:
            run.num_agents = num_agents
            if reason is not None:
                run.status, run.note = UNAVAILABLE, reason
        if reason is not None:
            plan.unavailable[env.id] = reason
        plan.runs.extend(env_runs)
    inspect_all(plan)
    return plan


RUN_NAME = re.compile(r"(?P<algo>.+)-s(?P<first>\d+)(?:-(?P<last>\d+))?")
"""A run directory's name within its cell's folder: `ALGO-sFIRST` or `ALGO-sFIRST-LAST`."""


def cell_seed_groups(spec: ExperimentSpec, folder: Path, algo: str) -> list[tuple[int, int]]:
    """(first seed, number of seeds) of each run of the cell whose runs are `folder/ALGO-s…`,
    in seed order: the run directories already there keep their seeds, whichever
    `seeds_per_run` made them (a grid continued with one seed per run keeps its finished runs
    of three; of two that overlap, the one with more seeds), and the spec's other seeds go in
    runs of up to `seeds_per_run` consecutive seeds."""
    wanted = set(range(spec.seed, spec.seed + spec.seeds))
    found = []
    if folder.is_dir():
        for path in folder.iterdir():
            match = RUN_NAME.fullmatch(path.name)
            if path.is_dir() and match is not None and match["algo"] == algo:
                first = int(match["first"])
                last = int(match["last"]) if match["last"] is not None else first
                found.append((first, last - first + 1))
    groups = []
    for first, seeds in sorted(found, key=lambda group: (-group[1], group[0])):
        members = set(range(first, first + seeds))
        if seeds > 0 and members <= wanted:
            groups.append((first, seeds))
            wanted -= members
    new: list[tuple[int, int]] = []
    for seed in sorted(wanted):
        if new and sum(new[-1]) == seed and new[-1][1] < spec.seeds_per_run:
            new[-1] = (new[-1][0], new[-1][1] + 1)
        else:
            new.append((seed, 1))
    return sorted(groups + new)


def inspect_all(plan: Plan) -> None:
    """Set every available run's status from its directory (bases before their stages)."""
    for run in plan.runs:
        if run.status != UNAVAILABLE:
            run.status, run.note = inspect(run)
        run.found = run.status


def retrain_exported_bases(runs: list[Run]) -> list[Run]:
    """`runs` with, before the first fine-tuning stage to run from it, every complete base run
    that is an exported copy: a stage starts from its base's checkpoint, which an export leaves
    out, so the base is trained again (same config and seeds) and the copy discarded."""
    ordered: list[Run] = []
    for run in runs:
        base = run.base
        if (run.status in (NEW, REDO) and base is not None and base.status == FINISHED
                and not RunDir(base.path).checkpoint_path.is_file()):
            base.status = REDO
            base.note = f"exported without its checkpoint, which {run.name} needs"
            run.note = f"after {base.name}"
        if base is not None and base.status == REDO and base not in ordered:
            ordered.append(base)
        if run not in ordered:
            ordered.append(run)
    return ordered


def schedule(runs: list[Run]) -> list[Run]:
    """The runs to execute in the order to start them: partial runs first, the one with the
    fewest env steps per seed left to its budget first (a grid continued from a carried export
    or a GPU slice finishes what it carried, nearest first, before starting anything new), then
    the others in grid order, every stage still after its base."""

    def remaining(run: Run) -> tuple[bool, int]:
        if run.status != RESUME or run.config is None:
            return True, 0
        return False, run.config.budget_steps - RunDir(run.path).checkpoint_steps()[0]

    return sorted(runs, key=remaining)


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
                                            variant.steps or env.steps,
                                            for_algorithm(variant.overrides, algo))
        else:
            explicit = [f"env={env.id}", f"algo={algo}",
                        f"total_steps={variant.steps or env.steps}", f"seeds={seeds}",
                        f"seed={seed}"]
            run.overrides = (*for_algorithm((*spec.overrides, *env.overrides,
                                             *variant.overrides), algo), *explicit)
            run.config = load_config(None, run.overrides)
    except CmatError as error:
        raise CmatError(f"{where}: {error}") from None
    return run


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
        steps, present = run_dir.checkpoint_steps()
    except CmatError as error:
        return REDO, str(error)
    target = expected.budget_steps
    if steps > target:
        return REDO, f"checkpoint at {steps} env steps, past the spec's {target}"
    if steps > 0:
        problem = metrics_problem(run_dir, steps, config)
        if problem is not None:
            return REDO, problem
    kept = "" if present else " (exported: results without the checkpoint)"
    if steps == target:
        return FINISHED, f"complete at {steps} env steps{kept}"
    if not present:
        return REDO, f"exported at {steps} of {target} env steps, without the checkpoint to resume"
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
    except CmatError as error:
        return str(error)
    except OSError as error:
        return f"unreadable metrics.csv ({error.strerror})"
    seeds = set(range(config.seed, config.seed + config.seeds))
    if not seeds <= final:
        return f"metrics.csv lacks the eval rows of its checkpoint at {steps} env steps"
    return None


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
    """One line of the experiment's output, above its progress bar where one is shown."""
    tqdm.write(message)
    sys.stdout.flush()
