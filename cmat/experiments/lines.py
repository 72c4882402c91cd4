"""An experiment's complete runs as lines (one per algorithm / variant and task), the metric of
each task, and the published reference figures that go beside them.

The metric of a task is the win rate where its environment defines one, else the episode
return. A seed's score is its last evaluation, or the mean of its evaluations over the
last part of its budget (`Line.scores`, the spec's `score_window`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from importlib import resources
from typing import Any

import yaml

from cmat.experiments.plan import Plan, Run
from cmat.plots import Curve, metric_curve
from cmat.rundir import RunDir

METRIC_NAMES = {"win_rate": "win rate", "episode_return": "episode return"}


@dataclass
class Line:
    """One algorithm / variant in one task: its complete runs pooled over seed groups."""

    label: str
    variant: str
    algo: str
    figures: tuple[str, ...]
    runs: list[Run]
    rows: list[dict[str, str]]

    def curve(self, metric: str) -> Curve | None:
        return metric_curve(self.rows, metric)

    def scores(self, metric: str, window: float = 0.0) -> list[float]:
        """Each seed's score on `metric`, in seed order: the mean of its evaluations at
        env steps >= (1 - `window`) × its last evaluation's, so `window` = 0 gives the last
        evaluation alone. With E episodes per evaluation, the mean of k evaluations is the
        win rate (or mean return) over their k × E episodes. Seeds without an evaluation of
        `metric`, or with a NaN in the window, are left out."""
        evaluations: dict[int, list[tuple[int, float]]] = {}
        for row in self.rows:
            if row["kind"] == "eval" and row.get(metric, "") != "":
                evaluations.setdefault(int(row["seed"]), []).append(
                    (int(row["env_steps"]), float(row[metric])))
        scores = []
        for seed in sorted(evaluations):
            last = max(steps for steps, _ in evaluations[seed])
            window_values = [value for steps, value in evaluations[seed]
                             if steps >= (1 - window) * last]
            if not any(math.isnan(value) for value in window_values):
                scores.append(sum(window_values) / len(window_values))
        return scores

    @property
    def iterations(self) -> int | None:
        return self.runs[0].iterations if self.runs else None


def collect_lines(plan: Plan) -> dict[str, list[Line]]:
    """Per environment id, the lines of every variant and algorithm with a complete run, in
    spec order."""
    lines: dict[str, list[Line]] = {}
    for env in plan.spec.envs:
        for variant in plan.spec.variants:
            for algo in variant.algos:
                runs = [r for r in plan.runs if r.env is env and r.variant is variant
                        and r.algo == algo and r.complete]
                if not runs:
                    continue
                rows = [row for run in runs for row in RunDir(run.path).read_metrics()]
                lines.setdefault(env.id, []).append(
                    Line(variant.line_label(algo), variant.name, algo, variant.figures, runs, rows))
    return lines


def task_metric(lines: list[Line]) -> str:
    for line in lines:
        if any(r["kind"] == "eval" and r.get("win_rate", "") not in ("", "nan")
               for r in line.rows):
            return "win_rate"
    return "episode_return"


@functools.cache
def reference_file() -> dict[str, Any]:
    """cmat/experiments/reference_results.yaml, parsed once."""
    text = resources.files("cmat.experiments").joinpath("reference_results.yaml").read_text()
    parsed: dict[str, Any] = yaml.safe_load(text)
    return parsed


def load_references() -> list[dict[str, Any]]:
    """The published figures of cmat/experiments/reference_results.yaml (`results`)."""
    return list(reference_file()["results"])


def matching_references(
    references: list[dict[str, Any]], env_id: str, metric: str
) -> list[dict[str, Any]]:
    return [r for r in references if r["env"] == env_id and r["metric"] == metric]


def load_suite_aggregates() -> list[dict[str, Any]]:
    """The published suite-level curves of reference_results.yaml (`suite_aggregates`)."""
    return list(reference_file()["suite_aggregates"])


def matching_suite_aggregates(
    aggregates: list[dict[str, Any]], env_ids: list[str]
) -> list[dict[str, Any]]:
    """The suite aggregates of every suite that one of `env_ids` belongs to (by id prefix)."""
    return [row for row in aggregates
            if any(env_id.startswith(row["env_prefix"]) for env_id in env_ids)]


def drawn_suite_aggregates(
    aggregates: list[dict[str, Any]], env_id: str, metric: str, steps: int
) -> list[dict[str, Any]]:
    """Per algorithm, the suite aggregate on `metric`'s scale for `env_id` whose env steps are
    nearest (in log scale) to the task's budget `steps`."""
    nearest: dict[str, dict[str, Any]] = {}
    for row in matching_suite_aggregates(aggregates, [env_id]):
        if row.get("drawn_on") != metric:
            continue
        best = nearest.get(row["algorithm"])
        if best is None or (abs(math.log(row["env_steps"] / steps))
                            < abs(math.log(best["env_steps"] / steps))):
            nearest[row["algorithm"]] = row
    return list(nearest.values())


def suite_aggregate_label(row: dict[str, Any]) -> str:
    return (f"published {row['algorithm']} {row['value']:.2g}, mean over {row['tasks']} "
            f"{row['suite']} tasks at {row['env_steps']:.0e} steps (Sable paper)")


def reference_label(ref: dict[str, Any]) -> str:
    same = " (StarCraft II, not SMAX)" if ref["benchmark"] == "SMAC" else ""
    return (f"published {ref['algorithm']} {ref['value']:.3g}{same}, {ref['source']}, "
            f"{ref['env_steps']:.0e} steps")
