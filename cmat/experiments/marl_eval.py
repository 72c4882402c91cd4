"""An experiment's runs in the JSON format of InstaDeep's marl-eval (`id-marl-eval` on PyPI),
the tool Mava and BenchMARL publish results with, so cmat's numbers sit beside theirs.

Layout (marl-eval's README, "Data format")::

    {suite: {task: {algorithm: {run: {"step_K": {"step_count": env steps,
                                               "episode_return": [..], "win_rate": [..]},
                                     "absolute_metrics": {...}}}}}}

suite and task split the environment id (`smax:3m` → `smax`, `3m`); algorithm is the line's
label in results.md; run is the seed. Each `step_K` is one evaluation of the run (cmat logs
the mean over its greedy episodes, so each list holds that one mean); `absolute_metrics` is
marl-eval's absolute metric, the run's `absolute` row (its best checkpoint evaluated on ten
times the episodes, cmat.runners.checkpoints), or for a run from before those rows the last
evaluation. Metrics a task does
not have (a win rate where there is none, NaN) are left out. marl-eval compares the runs of a
task step by step, so a line evaluated at other steps than the task's first line (a fine-tuning
stage with its own budget) is left out of the file; results.json has it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cmat.experiments.lines import Line

METRICS = ("episode_return", "win_rate")


def marl_eval_data(lines: dict[str, list[Line]]) -> dict[str, Any]:
    """The marl-eval JSON object of the lines of every environment id."""
    data: dict[str, Any] = {}
    for env_id, env_lines in lines.items():
        suite, _, task = env_id.partition(":")
        tasks = data.setdefault(suite, {}).setdefault(task, {})
        schedule = None
        for line in env_lines:
            runs = runs_of(line.rows)
            steps = {key: value["step_count"] for run in runs.values()
                     for key, value in run.items() if key.startswith("step_")}
            schedule = steps if schedule is None else schedule
            if steps == schedule:
                tasks[line.label] = runs
    return data


def runs_of(rows: list[dict[str, str]]) -> dict[str, Any]:
    """Per seed, its evaluations in step order and its absolute metrics (module doc)."""
    evaluations: dict[str, dict[int, dict[str, list[float]]]] = {}
    absolute: dict[str, tuple[int, dict[str, list[float]]]] = {}
    for row in rows:
        if row["kind"] not in ("eval", "absolute"):
            continue
        values = {metric: [float(row[metric])] for metric in METRICS
                  if row.get(metric, "") != "" and not math.isnan(float(row[metric]))}
        at = int(row["env_steps"])
        if row["kind"] == "absolute":
            if at >= absolute.get(row["seed"], (-1, {}))[0]:
                absolute[row["seed"]] = (at, values)
        else:
            evaluations.setdefault(row["seed"], {})[at] = values
    runs: dict[str, Any] = {}
    for seed, by_step in sorted(evaluations.items(), key=lambda item: int(item[0])):
        steps = sorted(by_step)
        run: dict[str, Any] = {
            f"step_{index}": {"step_count": step, **by_step[step]}
            for index, step in enumerate(steps)
        }
        run["absolute_metrics"] = dict(absolute.get(seed, (0, by_step[steps[-1]]))[1])
        runs[seed] = run
    return runs
