"""What `cmat experiment` writes from the complete runs of a grid.

- `figure_main.png` (paper Fig. 3): a panel per task, a line per algorithm / variant of figure
  `main`: greedy evaluation metric against env steps, mean ± std over seeds shaded; published
  reference figures for the task as dashed horizontal lines labelled "published".
- `figure_ablation.png` (paper Fig. 4), when the spec has variants of figure `ablation`.
- `results.md`: final greedy metrics (mean ± std over seeds), the ablation table with each
  run's resolved m, aggregate statistics with bootstrap confidence intervals, the published
  figures, and what happened to every run; `results.json`: the same numbers;
  `marl_eval.json`: every evaluation of every run in marl-eval's format.

The metric of a task is the win rate where its environment defines one, else the episode
return. A run's final score is each seed's last greedy evaluation.

Aggregate statistics follow Agarwal et al. (2021) with rliable's definitions
(`rliable.metrics.aggregate_iqm`, `probability_of_improvement`), computed vectorised over
bootstrap replications (equal to rliable's functions, tests/test_experiment.py): a stratified
bootstrap resamples seeds within each task, 95% percentile intervals. rliable's own bootstrap
module is not used: it imports arch < 8, which fails to import under pandas 3. Scores are made
comparable across tasks as win rates in [0, 1] as they are, returns min-max normalised per task
over every final score of the compared lines (there are no per-task random/expert scores).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
from matplotlib.figure import Figure
from scipy import stats

from cmat.experiments.marl_eval import marl_eval_data
from cmat.experiments.plots import Curve, eval_curve
from cmat.experiments.spec import ExperimentSpec
from cmat.rundir import RunDir

if TYPE_CHECKING:
    from cmat.experiments.runner import Plan, Run

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
        return eval_curve(self.rows, metric)

    def finals(self, metric: str) -> list[float]:
        """Each seed's last evaluation of `metric` (seeds without one are left out)."""
        last: dict[str, tuple[int, float]] = {}
        for row in self.rows:
            if row["kind"] != "eval" or row.get(metric, "") == "":
                continue
            steps = int(row["env_steps"])
            if row["seed"] not in last or steps >= last[row["seed"]][0]:
                last[row["seed"]] = (steps, float(row[metric]))
        return [value for _, value in sorted(last.values(), key=lambda item: item[0]) if
                not math.isnan(value)]

    @property
    def iterations(self) -> int | None:
        return self.runs[0].iterations if self.runs else None


def write_report(plan: Plan) -> list[Path]:
    """Write the figures, results.md, results.json and marl_eval.json (marl-eval's format,
    cmat.experiments.marl_eval) of `plan`; returns the paths written."""
    lines = collect_lines(plan)
    metrics = {env.id: task_metric(lines.get(env.id, [])) for env in plan.spec.envs}
    references = load_references()
    written = []
    path = plan.out / "figure_main.png"
    draw(plan, lines, metrics, references, "main", path)
    written.append(path)
    if any("ablation" in v.figures for v in plan.spec.variants):
        path = plan.out / "figure_ablation.png"
        draw(plan, lines, metrics, references, "ablation", path)
        written.append(path)
    summary = summarise(plan, lines, metrics, references)
    (plan.out / "results.json").write_text(json.dumps(summary, indent=1))
    (plan.out / "results.md").write_text(markdown(plan, summary))
    (plan.out / "marl_eval.json").write_text(json.dumps(marl_eval_data(lines), indent=1))
    return [*written, *(plan.out / name for name in ("results.md", "results.json",
                                                       "marl_eval.json"))]


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
                    Line(variant.line_label(algo), variant.name, algo, variant.figures, runs, rows)
                )
    return lines


def task_metric(lines: list[Line]) -> str:
    for line in lines:
        if any(r["kind"] == "eval" and r.get("win_rate", "") not in ("", "nan")
               for r in line.rows):
            return "win_rate"
    return "episode_return"


def load_references() -> list[dict[str, Any]]:
    """The published figures of cmat/experiments/reference_results.yaml."""
    text = resources.files("cmat.experiments").joinpath("reference_results.yaml").read_text()
    return list(yaml.safe_load(text)["results"])


def matching_references(
    references: list[dict[str, Any]], env_id: str, metric: str
) -> list[dict[str, Any]]:
    return [r for r in references if r["env"] == env_id and r["metric"] == metric]


def reference_label(ref: dict[str, Any]) -> str:
    same = " (StarCraft II, not SMAX)" if ref["benchmark"] == "SMAC" else ""
    return (f"published {ref['algorithm']} {ref['value']:.3g}{same}, {ref['source']}, "
            f"{ref['env_steps']:.0e} steps")


# ------------------------------------------------------------------------------------ figures


def draw(
    plan: Plan, lines: dict[str, list[Line]], metrics: dict[str, str],
    references: list[dict[str, Any]], figure_kind: str, path: Path,
) -> None:
    """A panel per task; `figure_kind` selects the variants drawn (main or ablation)."""
    envs = plan.spec.envs
    columns = min(3, len(envs))
    rows = math.ceil(len(envs) / columns)
    figure = Figure(figsize=(5.2 * columns, 3.9 * rows + 0.9), layout="constrained")
    axes_grid = figure.subplots(rows, columns, squeeze=False)
    palette = [f"C{i}" for i in range(10)]
    colors: dict[str, str] = {}
    handles: dict[str, Any] = {}
    for index, env in enumerate(envs):
        axes = axes_grid[index // columns][index % columns]
        axes.set_title(env.label, fontsize="medium")
        metric = metrics[env.id]
        drawn = [line for line in lines.get(env.id, []) if figure_kind in line.figures
                 and (figure_kind == "main" or line.algo == "cmat")]
        if env.id in plan.unavailable or not drawn:
            reason = plan.unavailable.get(env.id, "no complete run")
            axes.text(0.5, 0.5, wrap(f"unavailable: {reason}" if env.id in plan.unavailable
                                     else reason, 48),
                      ha="center", va="center", fontsize="small", transform=axes.transAxes)
            axes.set_xticks([])
            axes.set_yticks([])
            continue
        for line in drawn:
            curve = line.curve(metric)
            if curve is None:
                continue
            label = line.label
            if figure_kind == "ablation" and line.iterations is not None:
                label = f"{label} [m={line.iterations}]"
            key = label if figure_kind == "ablation" else line.label
            color = colors.setdefault(key, palette[len(colors) % len(palette)])
            steps, mean, std = curve
            (handle,) = axes.plot(steps, mean, color=color, label=label,
                                  marker="o" if len(steps) <= 12 else None, markersize=3)
            axes.fill_between(steps, mean - std, mean + std, color=color, alpha=0.2)
            handles.setdefault(key, handle)
        published = []
        if figure_kind == "main":
            for number, ref in enumerate(matching_references(references, env.id, metric)):
                published.append(axes.axhline(ref["value"], color="0.35", lw=1,
                                              ls=("--", ":", "-.")[number % 3],
                                              label=wrap(reference_label(ref), 60)))
        axes.set_xlabel("env steps per seed")
        axes.set_ylabel(f"eval {METRIC_NAMES[metric]}")
        axes.grid(alpha=0.3)
        if figure_kind == "ablation":
            axes.legend(fontsize="x-small")
        elif published:
            axes.legend(handles=published, fontsize="xx-small")
    for index in range(len(envs), rows * columns):
        axes_grid[index // columns][index % columns].set_visible(False)
    if figure_kind == "main" and handles:
        figure.legend(list(handles.values()), list(handles), loc="outside lower center",
                      ncols=min(6, len(handles)), fontsize="small")
    title = "training curves" if figure_kind == "main" else "ablation (CMAT)"
    figure.suptitle(f"{plan.spec.name}: {title}, greedy evaluation, mean ± std over seeds",
                    fontsize="small")
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=90)


def wrap(text: str, width: int) -> str:
    words, lines, current = text.split(), [], ""
    for word in words:
        if current and len(current) + len(word) + 1 > width:
            lines.append(current)
            current = word
        else:
            current = f"{current} {word}".strip()
    return "\n".join([*lines, current])


# --------------------------------------------------------------------------------- statistics


def iqm(scores: np.ndarray) -> np.ndarray:
    """Interquartile mean over the last two axes (runs × tasks); rliable's aggregate_iqm."""
    flat = scores.reshape(*scores.shape[:-2], -1)
    return stats.trim_mean(flat, proportiontocut=0.25, axis=-1)


def improvement_probability(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) averaged over tasks (ties count half) for x [..., runs_x, tasks] and
    y [..., runs_y, tasks]; rliable's probability_of_improvement (Mann-Whitney U / (n_x n_y))."""
    greater = (x[..., :, None, :] > y[..., None, :, :]).mean(axis=(-3, -2))
    ties = (x[..., :, None, :] == y[..., None, :, :]).mean(axis=(-3, -2))
    return (greater + 0.5 * ties).mean(axis=-1)


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
    P(first line > each other), over the tasks where every such line has final scores; None
    when no task has two lines to compare."""
    everywhere = {v.name for v in spec.variants if v.envs is None}
    labels: list[str] = []
    for task_lines in lines.values():
        for line in task_lines:
            if "main" in line.figures and line.variant in everywhere and line.label not in labels:
                labels.append(line.label)
    per_task: dict[str, dict[str, list[float]]] = {}
    for env_id, task_lines in lines.items():
        finals = {line.label: line.finals(metrics[env_id])
                  for line in task_lines if line.label in labels}
        if all(finals.get(label) for label in labels):
            per_task[env_id] = finals
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


def normalise(finals: dict[str, list[float]], metric: str) -> dict[str, list[float]]:
    """Win rates as they are; returns min-max scaled over every final score of the task."""
    if metric == "win_rate":
        return finals
    values = [v for scores in finals.values() for v in scores]
    low, high = min(values), max(values)
    scale = high - low
    return {label: [0.5 if scale == 0 else (v - low) / scale for v in scores]
            for label, scores in finals.items()}


# ---------------------------------------------------------------------------------- documents


def summarise(
    plan: Plan, lines: dict[str, list[Line]], metrics: dict[str, str],
    references: list[dict[str, Any]],
) -> dict[str, Any]:
    tasks = []
    for env in plan.spec.envs:
        metric = metrics[env.id]
        trained = [run.config for line in lines.get(env.id, []) for run in line.runs
                   if run.config is not None and run.config.finetune is None]
        steps = (max(c.budget_steps for c in trained) if trained
                 else env.steps)  # a run rounds its budget up to whole updates
        entry: dict[str, Any] = {"env": env.id, "label": env.label, "metric": metric,
                                 "steps": steps, "lines": {}}
        if env.id in plan.unavailable:
            entry["unavailable"] = plan.unavailable[env.id]
        for line in lines.get(env.id, []):
            finals = line.finals(metric)
            entry["lines"][line.label] = {
                "variant": line.variant, "algo": line.algo, "figures": list(line.figures),
                "finals": finals,
                "mean": float(np.mean(finals)) if finals else None,
                "std": float(np.std(finals)) if finals else None,
                "steps": line.runs[0].config.total_steps if line.runs[0].config else None,
                "iterations": line.iterations,
                "consensus_source": (line.runs[0].config.network.consensus_source
                                     if line.algo == "cmat" and line.runs[0].config else None),
            }
        entry["published"] = matching_references(references, env.id, metric)
        tasks.append(entry)
    return {
        "name": plan.spec.name,
        "seeds": plan.spec.seeds,
        "tasks": tasks,
        "aggregate": aggregate(lines, metrics, plan.spec),
        "runs": [{"run": run.name, "status": run.found, "note": run.note,
                  "outcome": run.outcome} for run in plan.runs],
    }


def markdown(plan: Plan, summary: dict[str, Any]) -> str:
    out = [f"# Experiment `{plan.spec.name}`", "",
           (f"Spec: `spec.yaml` (from `{plan.spec.path}`). Final greedy metric: each seed's last "
            f"greedy evaluation, mean ± std over seeds (n = {plan.spec.seeds} unless marked). "
            f"Metric: win rate where the environment defines one, else episode return."), ""]
    main = labels_of(summary, "main")
    if main:
        out += ["## Final greedy metrics", "",
                "| task | metric | steps | " + " | ".join(main) + " |",
                "|---" * (3 + len(main)) + "|"]
    for task in summary["tasks"] if main else []:
        if "unavailable" in task:
            cells = [f"unavailable: {task['unavailable']}"] + [""] * (len(main) - 1)
        else:
            cells = [cell(task["lines"].get(label), plan.spec.seeds) for label in main]
        metric = "—" if "unavailable" in task else METRIC_NAMES[task["metric"]]
        out.append(f"| {task['label']} | {metric} | {task['steps']:,} | " + " | ".join(cells)
                   + " |")
    stage_steps = {line["variant"]: line["steps"] for task in summary["tasks"]
                   for line in task["lines"].values() if "main" in line["figures"]
                   and plan.spec.variant(line["variant"]).finetune}
    for variant, steps in stage_steps.items():
        out.append(f"\nFine-tuning stage `{variant}` ran {steps:,} env steps after its base run "
                   f"(its curve counts its own steps).")
    ablation = labels_of(summary, "ablation")
    if ablation:
        out += ["", "## Ablation", "", "| task | variant | m | consensus | final |",
                "|---|---|---|---|---|"]
        for task in summary["tasks"]:
            for label, line in task["lines"].items():
                if "ablation" in line["figures"] and line["algo"] == "cmat":
                    out.append(f"| {task['label']} | {label} | {line['iterations']} | "
                               f"{line['consensus_source']} | {cell(line, plan.spec.seeds)} |")
    out += ["", "## Aggregate statistics", ""]
    agg = summary["aggregate"]
    if agg is None:
        out.append("Not computed: it needs two or more main lines with final scores on a "
                   "common task.")
    else:
        out += [(f"Lines of the variants that run on every task, over {len(agg['tasks'])} "
                 f"task(s) ({', '.join(agg['tasks'])}) where each of them has final scores; win rates as they are, returns min-max normalised per "
                 f"task; stratified bootstrap over seeds within tasks, {agg['reps']} "
                 f"replications, 95% percentile intervals (rliable's IQM and probability of "
                 f"improvement)."), "",
                "| line | runs | IQM [95% CI] | mean [95% CI] |", "|---|---|---|---|"]
        for label, line in agg["lines"].items():
            out.append(f"| {label} | {line['runs']} | {line['iqm']:.3f} "
                       f"[{line['iqm_ci'][0]:.3f}, {line['iqm_ci'][1]:.3f}] | "
                       f"{line['mean']:.3f} [{line['mean_ci'][0]:.3f}, {line['mean_ci'][1]:.3f}] |")
        out += ["", "| comparison | P(X > Y) [95% CI] |", "|---|---|"]
        for pair, value in agg["improvement"].items():
            out.append(f"| {pair} | {value['probability']:.3f} "
                       f"[{value['ci'][0]:.3f}, {value['ci'][1]:.3f}] |")
    published = [(task, ref) for task in summary["tasks"] for ref in task["published"]]
    out += ["", "## Published reference figures (context, not this project's runs)", ""]
    if published:
        out += ["| task | algorithm | published | benchmark | env steps | source |",
                "|---|---|---|---|---|---|"]
        for task, ref in published:
            std = f" ± {ref['std']:.3g}" if ref.get("std") is not None else ""
            note = f" ({ref['note']})" if ref.get("note") else ""
            out.append(f"| {task['label']} | {ref['algorithm']} | {ref['value']:.3g}{std} | "
                       f"{ref['benchmark']} {ref['scenario']} | {ref['env_steps']:.0e} | "
                       f"{ref['source']}{note} |")
    else:
        out.append("None for these tasks.")
    out += ["", "## Runs", "", "| run | found | this time |", "|---|---|---|"]
    for run in summary["runs"]:
        found = run["status"] + (f": {run['note']}" if run["note"] else "")
        out.append(f"| {run['run']} | {found} | {run['outcome'] or '—'} |")
    return "\n".join(out) + "\n"


def labels_of(summary: dict[str, Any], figure: str) -> list[str]:
    labels: list[str] = []
    for task in summary["tasks"]:
        for label, line in task["lines"].items():
            if figure in line["figures"] and label not in labels:
                labels.append(label)
    return labels


def cell(line: dict[str, Any] | None, seeds: int) -> str:
    if line is None or line["mean"] is None:
        return "—"
    n = len(line["finals"])
    return f"{line['mean']:.3g} ± {line['std']:.2g}" + ("" if n == seeds else f" (n={n})")
