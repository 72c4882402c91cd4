"""What `cmat experiment` writes from the complete runs of a grid.

- `figure_main.png` and `figure_main.pdf` (paper Fig. 3): a panel per task, a line per
  algorithm / variant of figure `main`: greedy evaluation metric against env steps, mean ± std
  over seeds shaded (clipped to the metric's range); published reference figures for the task
  as dashed horizontal lines labelled "published".
- `figure_ablation.png` and `.pdf` (paper Fig. 4), when the spec has variants of figure
  `ablation`.
- `results.md`: each line's score, mean ± std over seeds (a seed's score is its last greedy
  evaluation, or its mean evaluation over the spec's `score_window`: `Line.scores`), the
  ablation table with each run's resolved m, aggregate statistics with bootstrap confidence
  intervals, the published figures, the paper's claims judged from the scores where the spec
  asks for them (`claims: true`; cmat.experiments.claims; with a window, also from the last
  evaluations alone) and what
  happened to every run; `results.json`: the same numbers;
  `marl_eval.json`: every evaluation of every run in marl-eval's format.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from cmat.algorithms.cmat.options import CMATOptions
from cmat.experiments.baselines import baseline_lines
from cmat.experiments.claims import judge_claims
from cmat.experiments.figures import draw
from cmat.experiments.lines import (
    Line,
    collect_lines,
    load_references,
    load_suite_aggregates,
    matching_references,
    matching_suite_aggregates,
    task_metric,
)
from cmat.experiments.markdown import markdown
from cmat.experiments.marl_eval import marl_eval_data
from cmat.experiments.plan import Plan, Run
from cmat.experiments.spec import EnvEntry, ExperimentSpec
from cmat.experiments.statistics import aggregate
from cmat.rundir import RunDir


def write_report(plan: Plan) -> list[Path]:
    """Write the figures, results.md, results.json and marl_eval.json (marl-eval's format,
    cmat.experiments.marl_eval) of `plan`; returns the paths written."""
    lines = collect_lines(plan)
    for env_id, extra in baseline_lines(plan).items():
        lines.setdefault(env_id, []).extend(extra)
    metrics = {env.id: task_metric(lines.get(env.id, [])) for env in plan.spec.envs}
    references = load_references()
    suite_aggregates = load_suite_aggregates()
    written = []
    written += draw(plan, lines, metrics, references, suite_aggregates, "main",
                    plan.out / "figure_main.png")
    if any("ablation" in v.figures for v in plan.spec.variants):
        written += draw(plan, lines, metrics, references, suite_aggregates, "ablation",
                        plan.out / "figure_ablation.png")
    summary = summarise(plan, lines, metrics, references)
    (plan.out / "results.json").write_text(json.dumps(summary, indent=1))
    (plan.out / "results.md").write_text(markdown(plan, summary))
    (plan.out / "marl_eval.json").write_text(json.dumps(marl_eval_data(lines), indent=1))
    return [*written, *(plan.out / name for name in ("results.md", "results.json",
                                                       "marl_eval.json"))]


def task_steps(env: EnvEntry, lines: list[Line], spec: ExperimentSpec) -> int:
    """The env steps a task's table row states: the budget its runs trained, a run rounding
    the task's `steps` up to whole updates; variants with `steps` of their own (a longer-budget
    line) and fine-tuning stages state theirs in their labels, so they do not count. The
    task's `steps` where none of those runs is complete."""
    own_budget = {v.name for v in spec.variants if v.steps is None and v.finetune is None}
    trained = [run.config.budget_steps for line in lines if line.variant in own_budget
               for run in line.runs if run.config is not None]
    return max(trained) if trained else env.steps


def summarise(
    plan: Plan, lines: dict[str, list[Line]], metrics: dict[str, str],
    references: list[dict[str, Any]],
) -> dict[str, Any]:
    tasks = []
    for env in plan.spec.envs:
        metric = metrics[env.id]
        steps = task_steps(env, lines.get(env.id, []), plan.spec)
        entry: dict[str, Any] = {"env": env.id, "label": env.label, "metric": metric,
                                 "steps": steps, "lines": {}}
        if env.id in plan.unavailable:
            entry["unavailable"] = plan.unavailable[env.id]
        for line in lines.get(env.id, []):
            scores = line.scores(metric, plan.spec.score_window)
            entry["lines"][line.label] = {
                "variant": line.variant, "algo": line.algo, "figures": list(line.figures),
                "scores": scores,
                "finals": line.scores(metric),
                "mean": float(np.mean(scores)) if scores else None,
                "std": float(np.std(scores)) if scores else None,
                "steps": (line.runs[0].config.budget_steps
                          if line.runs and line.runs[0].config else None),
                "iterations": line.iterations,
                "consensus_source": consensus_source(line),
                "metrics": last_metrics(line),
            }
        entry["published"] = matching_references(references, env.id, metric)
        tasks.append(entry)
    summary: dict[str, Any] = {
        "name": plan.spec.name,
        "seeds": plan.spec.seeds,
        "tasks": tasks,
        "aggregate": aggregate(lines, metrics, plan.spec),
        "suite_published": matching_suite_aggregates(
            load_suite_aggregates(), [env.id for env in plan.spec.envs]),
        "runs": [{"run": run.name, "status": run.found, "note": run.note,
                  "outcome": run.outcome, "seconds": training_seconds(run),
                  "eval_protocol": eval_protocol(run)}
                 for run in plan.runs],
    }
    summary["compute"] = compute_totals(summary["runs"])
    if plan.spec.claims:
        summary["claims"] = judge_claims(summary, plan.spec)
        if plan.spec.score_window > 0:
            summary["claims_from_finals"] = judge_claims(summary, plan.spec, scores="finals")
    return summary


def consensus_source(line: Line) -> str | None:
    """The consensus source of a CMAT line (`cmat.consensus_source`), None for other lines."""
    config = line.runs[0].config if line.runs else None
    return config.options.consensus_source if config and isinstance(
        config.options, CMATOptions) else None


def last_metrics(line: Line) -> dict[str, float]:
    """Every evaluation figure of `line` (the return, the win rate, the environment's metrics
    such as dispatch's service rate) at each seed's last evaluation, averaged over the seeds
    that define it."""
    last: dict[str, dict[str, str]] = {}
    for row in line.rows:
        if row["kind"] == "eval" and (row["seed"] not in last or
                                      int(row["env_steps"]) >= int(last[row["seed"]]["env_steps"])):
            last[row["seed"]] = row
    values: dict[str, list[float]] = {}
    for row in last.values():
        for key, text in row.items():
            if key not in ("kind", "seed", "env_steps") and text not in ("", None):
                number = float(text)
                if not math.isnan(number):
                    values.setdefault(key, []).append(number)
    return {key: float(np.mean(numbers)) for key, numbers in values.items()}


def training_seconds(run: Run) -> dict[str, float]:
    """Wall-clock seconds `run` has trained so far (its directory's sessions.jsonl, which runs
    from before that record existed lack) per place it ran (`place`)."""
    seconds: dict[str, float] = {}
    if not run.path.is_dir():
        return seconds
    for session in RunDir(run.path).sessions():
        where = place(session)
        seconds[where] = seconds.get(where, 0.0) + float(session.get("seconds", 0.0))
    return seconds


def eval_protocol(run: Run) -> int | None:
    """The oldest evaluation protocol (`cmat.rundir.EVAL_PROTOCOL`) among `run`'s sessions
    (1 for a session that does not record one); None for a run without sessions."""
    if not run.path.is_dir():
        return None
    sessions = RunDir(run.path).sessions()
    return min((int(s.get("eval_protocol", 1)) for s in sessions), default=None)


def place(session: dict[str, Any]) -> str:
    """Where a session ran: 'cpu (N cores)', or 'BACKEND (DEVICE KIND)' on an accelerator."""
    backend = session.get("backend", "?")
    if backend == "cpu":
        cpus = session.get("cpus", "?")
        return f"cpu ({cpus} core{'' if cpus == 1 else 's'})"
    return f"{backend} ({session.get('device', '?')})"


def compute_totals(runs: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per place (`place`): the runs that trained there and their total hours."""
    totals: dict[str, dict[str, float]] = {}
    for run in runs:
        for where, seconds in run["seconds"].items():
            entry = totals.setdefault(where, {"runs": 0, "hours": 0.0})
            entry["runs"] += 1
            entry["hours"] += seconds / 3600
    return totals
