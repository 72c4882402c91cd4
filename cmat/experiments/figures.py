"""The figures of an experiment: `figure_main.png` (paper Fig. 3), a panel per task, a line per
algorithm / variant of figure `main`, evaluation metric against env steps, mean ± std
over seeds shaded, published reference figures as grey dashed horizontal lines, classical
baselines (`cmat.experiments.baselines`) as coloured dashed horizontal lines; and
`figure_ablation.png` (paper Fig. 4) for the variants of figure `ablation`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from cmat.experiments.baselines import BASELINE_VARIANT
from cmat.experiments.lines import (
    METRIC_NAMES,
    Line,
    drawn_suite_aggregates,
    matching_references,
    reference_label,
    suite_aggregate_label,
)
from cmat.experiments.plan import Plan
from cmat.experiments.spec import EnvEntry, ExperimentSpec
from cmat.plots import (
    TEXT_INCHES,
    band,
    legend_below,
    marker,
    new_figure,
    print_style,
    save_figure,
    steps_axis,
)


def draw(
    plan: Plan, lines: dict[str, list[Line]], metrics: dict[str, str],
    references: list[dict[str, Any]], suite_aggregates: list[dict[str, Any]],
    figure_kind: str, path: Path,
) -> list[Path]:
    """A panel per task; `figure_kind` selects the variants drawn (main or ablation). Published
    task figures are dashed grey lines; published suite means on the task's scale
    (lines.drawn_suite_aggregates) are dotted lines in the colour of the same algorithm's line
    where there is one. The main figure has a panel per task; in the ablation figure, where two
    or more of its variants exist, only the tasks that two of them cover get a panel (an
    ablation that runs on two maps draws two panels).

    Sized for print: the text width of a two-column paper (`TEXT_INCHES`), PNG at
    `PRINT_DPI` and a vector PDF beside it; returns the paths written."""
    envs = panel_envs(plan.spec, figure_kind)
    columns = min(3, len(envs))
    rows = math.ceil(len(envs) / columns)
    with print_style():
        figure = new_figure(figsize=(TEXT_INCHES, 2.2 * rows + 1.0), layout="constrained")
        draw_panels(figure, plan, envs, columns, rows, lines, metrics, references,
                    suite_aggregates, figure_kind)
        return save_figure(figure, path, pdf=True)


def draw_panels(
    figure: Any, plan: Plan, envs: list[EnvEntry], columns: int, rows: int,
    lines: dict[str, list[Line]], metrics: dict[str, str], references: list[dict[str, Any]],
    suite_aggregates: list[dict[str, Any]], figure_kind: str,
) -> None:
    """`draw`'s panels, legends and title on `figure`."""
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
            if line.variant == BASELINE_VARIANT:
                handles.setdefault(key, axes.axhline(
                    mean[-1], color=color, lw=1.2, ls="--", label=label))
                continue
            (handle,) = axes.plot(steps, mean, color=color, label=label,
                                  marker=marker(steps), markersize=2)
            band(axes, steps, mean, std, metric, color=color, alpha=0.2)
            handles.setdefault(key, handle)
        published = []
        if figure_kind == "main":
            for number, ref in enumerate(matching_references(references, env.id, metric)):
                published.append(axes.axhline(ref["value"], color="0.35", lw=1,
                                              ls=("--", ":", "-.")[number % 3],
                                              label=wrap(reference_label(ref), 60)))
            for row in drawn_suite_aggregates(suite_aggregates, env.id, metric, env.steps):
                color = colors.get(row["algorithm"], "0.35")
                published.append(axes.axhline(row["value"], color=color, lw=1, ls=":",
                                              label=wrap(suite_aggregate_label(row), 60)))
        steps_axis(axes)
        axes.set_ylabel(f"eval {METRIC_NAMES[metric]}")
        axes.grid(alpha=0.3)
        if figure_kind == "ablation":
            axes.legend(fontsize="x-small")
        elif published:
            axes.legend(handles=published, fontsize="xx-small")
    for index in range(len(envs), rows * columns):
        axes_grid[index // columns][index % columns].set_visible(False)
    if figure_kind == "main" and handles:
        legend_below(figure, list(handles.values()), list(handles))
    title = "training curves" if figure_kind == "main" else "ablation (CMAT)"
    figure.suptitle(f"{plan.spec.name}: {title}, evaluation, mean ± std over seeds",
                    fontsize="small")


def panel_envs(spec: ExperimentSpec, figure_kind: str) -> list[EnvEntry]:
    """The spec's environments that `figure_kind` draws: all of them for the main figure (a
    longer variant on one task leaves the others in it); for the ablation figure, those covered
    by two of its variants with CMAT, or all of them where no task has two."""
    if figure_kind == "main":
        return list(spec.envs)
    variants = [v for v in spec.variants if figure_kind in v.figures and "cmat" in v.algos]
    compared = [env for env in spec.envs if sum(v.covers(env.id) for v in variants) >= 2]
    return compared or list(spec.envs)


def wrap(text: str, width: int) -> str:
    words, lines, current = text.split(), [], ""
    for word in words:
        if current and len(current) + len(word) + 1 > width:
            lines.append(current)
            current = word
        else:
            current = f"{current} {word}".strip()
    return "\n".join([*lines, current])
