"""Aggregate statistics of an experiment, after Agarwal et al. (2021) with rliable's definitions
(`rliable.metrics.aggregate_iqm`, `probability_of_improvement`), computed vectorised over
bootstrap replications (equal to rliable's functions, tests/test_experiment.py): a stratified
bootstrap resamples seeds within each task, 95% percentile intervals. rliable's own bootstrap
module is not used: it imports arch < 8, which fails to import under pandas 3. Scores are made
comparable across tasks as win rates in [0, 1] as they are, returns min-max normalised per task
over every score of the compared lines (there are no per-task random/expert scores). A seed's
score is `cmat.experiments.lines.Line.scores` with the spec's `score_window`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cmat.experiments.baselines import BASELINE_VARIANT
from cmat.experiments.lines import Line
from cmat.experiments.spec import ExperimentSpec


def iqm(scores: np.ndarray) -> np.ndarray:
    """Interquartile mean over the last two axes (runs × tasks); rliable's aggregate_iqm.
    (scipy.stats is imported here, not with the module: it takes seconds, and a spec error is
    reported before any statistic is needed.)"""
    from scipy import stats

    flat = scores.reshape(*scores.shape[:-2], -1)
    mean: np.ndarray = stats.trim_mean(flat, proportiontocut=0.25, axis=-1)
    return mean


def improvement_probability(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) averaged over tasks (ties count half) for x [..., runs_x, tasks] and
    y [..., runs_y, tasks]; rliable's probability_of_improvement (Mann-Whitney U / (n_x n_y))."""
    greater = (x[..., :, None, :] > y[..., None, :, :]).mean(axis=(-3, -2))
    ties = (x[..., :, None, :] == y[..., None, :, :]).mean(axis=(-3, -2))
    probability: np.ndarray = (greater + 0.5 * ties).mean(axis=-1)
    return probability


def bootstrap(scores: np.ndarray, reps: int, rng: np.random.Generator) -> np.ndarray:
    """`reps` stratified resamples of scores [runs, tasks]: runs drawn with replacement within
    each task, independently per task -> [reps, runs, tasks]."""
    runs, tasks = scores.shape
    picks = rng.integers(0, runs, size=(reps, runs, tasks))
    return np.take_along_axis(np.broadcast_to(scores, (reps, runs, tasks)), picks, axis=1)


def interval(samples: np.ndarray) -> list[float]:
    return [float(np.percentile(samples, 2.5)), float(np.percentile(samples, 97.5))]


def aggregate(
    lines: dict[str, list[Line]], metrics: dict[str, str], spec: ExperimentSpec
) -> dict[str, Any] | None:
    """IQM and mean with CIs per main line of a variant that runs on every environment, and
    P(first line > each other), over the tasks where every such line has scores, leaving out
    the `matrix:` games where another task qualifies (claim (e)'s games, where every line may
    score the optimum in every seed, would add a constant to every line); None when no task has
    two lines to compare."""
    everywhere = {v.name for v in spec.variants if v.envs is None} | {BASELINE_VARIANT}
    labels: list[str] = []
    for task_lines in lines.values():
        for line in task_lines:
            if "main" in line.figures and line.variant in everywhere and line.label not in labels:
                labels.append(line.label)
    per_task: dict[str, dict[str, list[float]]] = {}
    for env_id, task_lines in lines.items():
        scores = {line.label: line.scores(metrics[env_id], spec.score_window)
                  for line in task_lines if line.label in labels}
        if all(scores.get(label) for label in labels):
            per_task[env_id] = scores
    benchmark = {env_id: scores for env_id, scores in per_task.items()
                 if not env_id.startswith("matrix:")}
    per_task = benchmark or per_task
    if not per_task or len(labels) < 2:
        return None
    tasks = list(per_task)
    normalised = {env_id: normalise(per_task[env_id], metrics[env_id]) for env_id in tasks}
    runs = {label: min(len(normalised[t][label]) for t in tasks) for label in labels}
    matrices = {label: np.array([[normalised[t][label][i] for t in tasks]
                                 for i in range(runs[label])]) for label in labels}
    reps = spec.bootstrap_reps
    rng = np.random.default_rng(0)
    samples = {label: bootstrap(matrix, reps, rng) for label, matrix in matrices.items()}
    result: dict[str, Any] = {"tasks": tasks, "reps": reps, "lines": {}, "improvement": {}}
    for label, matrix in matrices.items():
        result["lines"][label] = {
            "runs": runs[label],
            "iqm": float(iqm(matrix)), "iqm_ci": interval(iqm(samples[label])),
            "mean": float(matrix.mean()), "mean_ci": interval(samples[label].mean(axis=(1, 2))),
        }
    reference = labels[0]
    for other in labels[1:]:
        point = improvement_probability(matrices[reference], matrices[other])
        boot = improvement_probability(samples[reference], samples[other])
        result["improvement"][f"{reference} > {other}"] = {
            "probability": float(point), "ci": interval(boot),
        }
    return result


def normalise(scores: dict[str, list[float]], metric: str) -> dict[str, list[float]]:
    """Win rates as they are; returns min-max scaled over every score of the task."""
    if metric == "win_rate":
        return scores
    values = [v for line_scores in scores.values() for v in line_scores]
    low, high = min(values), max(values)
    scale = high - low
    return {label: [0.5 if scale == 0 else (v - low) / scale for v in line_scores]
            for label, line_scores in scores.items()}
