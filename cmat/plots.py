"""Evaluation curves of one or more run directories (mean over seeds, ±1 std shaded)."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cmat.errors import CmatError
from cmat.rundir import RunDir

if TYPE_CHECKING:
    from matplotlib.figure import Figure

Curve = tuple[np.ndarray, np.ndarray, np.ndarray]

PRINT_DPI = 200
"""Resolution of every PNG cmat writes (a column of a printed paper wants at least 150)."""
COLUMN_INCHES = 3.4
"""Width of one column of a two-column paper; a figure of several panels takes the text width,
`TEXT_INCHES`."""
TEXT_INCHES = 7.0
PRINT_STYLE: dict[Any, Any] = {
    "font.size": 7, "axes.titlesize": 8, "axes.labelsize": 7, "legend.fontsize": 6,
    "xtick.labelsize": 6, "ytick.labelsize": 6, "lines.linewidth": 1.2,
}
"""Font sizes in points at the figure's printed size (matplotlib rcParams)."""
METRIC_RANGES = {"win_rate": (0.0, 1.0)}
"""Metrics with a bounded range: their ±std bands are clipped to it."""


def print_style() -> Any:
    """A context in which new figures get `PRINT_STYLE`'s font sizes."""
    from matplotlib import rc_context

    return rc_context(PRINT_STYLE)


def band(axes: Any, steps: np.ndarray, mean: np.ndarray, std: np.ndarray, metric: str,
         **options: Any) -> None:
    """The ±1 std band around `mean`, clipped to the metric's range (`METRIC_RANGES`)."""
    low, high = METRIC_RANGES.get(metric, (-np.inf, np.inf))
    axes.fill_between(steps, np.clip(mean - std, low, high), np.clip(mean + std, low, high),
                      **options)


def steps_axis(axes: Any) -> None:
    """Label the x axis as env steps per seed, in engineering notation (200k, 1M)."""
    from matplotlib.ticker import EngFormatter

    axes.xaxis.set_major_formatter(EngFormatter(sep=""))
    axes.set_xlabel("env steps per seed")


def save_figure(figure: Figure, path: Path, pdf: bool = False) -> list[Path]:
    """Write `figure` to `path` (PNG at `PRINT_DPI`, or the format its suffix names), and with
    `pdf` a vector PDF beside it; returns the paths written."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=PRINT_DPI)
    written = [Path(path)]
    if pdf and Path(path).suffix != ".pdf":
        figure.savefig(Path(path).with_suffix(".pdf"))
        written.append(Path(path).with_suffix(".pdf"))
    return written


FEW_POINTS = 12
"""Curves of at most this many points get a marker on each (a single point draws no line)."""


def new_figure(**options: Any) -> Figure:
    """A matplotlib `Figure` (no pyplot state); matplotlib is imported on the first figure,
    which keeps it (about 1.5 s) out of every command's start-up."""
    from matplotlib.figure import Figure

    return Figure(**options)


def legend_below(figure: Figure, handles: list[Any], labels: list[str],
                 fontsize: str = "small") -> None:
    """One legend under the figure's panels, in as many columns as fit its width (measured
    with the figure's renderer); labels too long for one column are wrapped, so that no entry
    is cut off however long the labels are."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    renderer = FigureCanvasAgg(figure).get_renderer()  # type: ignore[no-untyped-call]
    room = 0.98 * figure.bbox.width
    for columns in range(len(labels), 0, -1):
        legend = figure.legend(handles, labels, loc="outside lower center", ncols=columns,
                               fontsize=fontsize)
        width = legend.get_window_extent(renderer).width
        if width <= room:
            return
        legend.remove()
    longest = max(len(label) for label in labels)
    wrapped = ["\n".join(textwrap.wrap(label, max(8, int(longest * room / width) - 4)))
               for label in labels]
    figure.legend(handles, wrapped, loc="outside lower center", ncols=1, fontsize=fontsize)


def marker(steps: np.ndarray) -> str | None:
    return "o" if len(steps) <= FEW_POINTS else None


def check_figure_path(out: Path) -> None:
    """CmatError unless matplotlib writes the format `out`'s suffix names and `out` is not a
    directory; checked before any run is read."""
    formats = new_figure().canvas.get_supported_filetypes()
    suffix = Path(out).suffix.lower().removeprefix(".")
    if suffix not in formats:
        raise CmatError(f"cannot write a figure to {out}: "
                        f"{'unknown format ' + repr(suffix) if suffix else 'no file suffix'}; "
                        f"use one of {', '.join('.' + name for name in sorted(formats))}")
    if Path(out).is_dir():
        raise CmatError(f"cannot write a figure to {out}: it is a directory")


def metric_curve(rows: list[dict[str, str]], column: str, kind: str = "eval") -> Curve | None:
    """(env_steps, mean, std) over seeds of a column of the `kind` rows (eval or train); None
    where it is never defined."""
    by_step: dict[int, list[float]] = {}
    for row in rows:
        if row["kind"] == kind and row.get(column, "") != "":
            value = float(row[column])
            if not math.isnan(value):
                by_step.setdefault(int(row["env_steps"]), []).append(value)
    if not by_step:
        return None
    steps = np.array(sorted(by_step))
    values = [np.array(by_step[step]) for step in steps]
    return steps, np.array([v.mean() for v in values]), np.array([v.std() for v in values])


def run_names(run_dirs: list[Path]) -> list[str]:
    """The shortest trailing part of each path (as given, not resolved) that tells the runs
    apart: `per_agent_clip/cmat-s0-2` and `tau_one/cmat-s0-2` rather than `cmat-s0-2` twice."""
    parts = [Path(path).absolute().parts for path in run_dirs]
    for depth in range(1, max((len(p) for p in parts), default=1) + 1):
        names = ["/".join(p[-depth:]) for p in parts]
        if len(set(names)) == len(names):
            return names
    return [str(path) for path in run_dirs]


def plot_runs(run_dirs: list[Path], out: Path) -> None:
    """Eval episode return (and win rate, where any run defines it) against env steps per seed.

    Raises CmatError for an unwritable `out` (`check_figure_path`) or a run without
    evaluations."""
    check_figure_path(out)
    panels: dict[str, list[tuple[str, Curve]]] = {"episode_return": [], "win_rate": []}
    runs = [RunDir.open(path) for path in run_dirs]
    configs = [run.config() for run in runs]
    envs = {config.env for config in configs}
    algos = {config.algo for config in configs}
    for run, config, name in zip(runs, configs, run_names(run_dirs)):
        rows = run.read_metrics()
        label = " ".join([*([config.env] if len(envs) > 1 else []),
                          *([config.algo] if len(algos) > 1 else []),
                          *([f"finetune {config.finetune}"] if config.finetune else [])])
        label = f"{label} ({name})" if label else name
        returns = metric_curve(rows, "episode_return")
        if returns is None:
            raise CmatError(f"no evaluation results in {run.path}")
        panels["episode_return"].append((label, returns))
        win_rate = metric_curve(rows, "win_rate")
        if win_rate is not None:
            panels["win_rate"].append((label, win_rate))
    shown = {name: curves for name, curves in panels.items() if curves}
    with print_style():
        figure = new_figure(figsize=(COLUMN_INCHES if len(shown) == 1 else TEXT_INCHES,
                                     2.6 + 0.15 * len(handles_of(shown))),
                            layout="constrained")
        draw_curves(figure, shown, envs, algos)
        save_figure(figure, out)


def handles_of(shown: dict[str, list[tuple[str, Curve]]]) -> list[str]:
    return list(dict.fromkeys(label for curves in shown.values() for label, _ in curves))


def draw_curves(figure: Figure, shown: dict[str, list[tuple[str, Curve]]], envs: set[str],
                algos: set[str]) -> None:
    """`plot_runs`'s panels: one per metric in `shown`, a line per run."""
    all_axes = figure.subplots(1, len(shown), squeeze=False)[0]
    colors = {label: f"C{index % 10}" for index, (label, _) in enumerate(shown["episode_return"])}
    handles: dict[str, Any] = {}
    for axes, (name, curves) in zip(all_axes, shown.items()):
        for label, (steps, mean, std) in curves:
            color = colors[label]
            (line,) = axes.plot(steps, mean, color=color, marker=marker(steps), markersize=2)
            band(axes, steps, mean, std, name, color=color, alpha=0.2)
            handles.setdefault(label, line)
        steps_axis(axes)
        axes.set_ylabel(f"eval {name.replace('_', ' ')}")
        axes.grid(alpha=0.3)
    title = " · ".join(sorted(envs if len(envs) == 1 else set()) + sorted(
        algos if len(algos) == 1 else set()))
    if title:
        figure.suptitle(title, fontsize="medium")
    legend_below(figure, list(handles.values()), list(handles))


DIAGNOSTIC_PANELS = (
    ("clip fraction", ("joint_clip_frac", "agent_clip_frac")),
    ("approximate KL", ("joint_approx_kl", "agent_approx_kl")),
    ("explained variance", ("explained_variance",)),
    ("entropy (mean over agents)", ("entropy",)),
    ("entropy per agent", ("entropy_agent_",)),
    ("gradient norm per block", ("grad_norm_",)),
)
"""Panels of `plot_diagnostics`: title and the train columns drawn (a trailing _ is a prefix)."""


LINE_STYLES = ("-", "--", ":", "-.")


def plot_diagnostics(run_dirs: list[Path], out: Path) -> None:
    """Per-update training diagnostics of run directories (mean over seeds, ±1 std shaded):
    joint and per-agent clip fraction and approximate KL, explained variance of the value,
    entropy (mean and per agent) and the gradient norm of each parameter block.

    One colour per run (legend under the figure); within a panel, up to four columns are told
    apart by line style (panel legend). Panels with more columns than that (one per agent or
    per block) name each column only when a single run is drawn; with several, their lines
    share the run's colour. Raises CmatError for an unwritable `out` (`check_figure_path`) or
    runs without diagnostics."""
    check_figure_path(out)
    runs = []
    for path, name in zip(run_dirs, run_names(run_dirs)):
        run = RunDir.open(path)
        runs.append((f"{run.config().algo} ({name})", run.read_metrics()))
    colours = [f"C{index % 10}" for index in range(len(runs))]
    with print_style():
        figure = new_figure(figsize=(TEXT_INCHES, 4.6), layout="constrained")
        draw_diagnostics(figure, runs, colours, run_dirs)
        save_figure(figure, out)


def draw_diagnostics(figure: Figure, runs: list[tuple[str, list[dict[str, str]]]],
                     colours: list[str], run_dirs: list[Path]) -> None:
    """`plot_diagnostics`'s six panels."""
    all_axes = figure.subplots(2, 3).reshape(-1)
    drawn = 0
    for axes, (title, wanted) in zip(all_axes, DIAGNOSTIC_PANELS):
        found = [[c for c in (list(rows[0]) if rows else []) for w in wanted
                  if (c.startswith(w) if w.endswith("_") else c == w)] for _, rows in runs]
        names = list(dict.fromkeys(column for columns in found for column in columns))
        styled = len(names) <= len(LINE_STYLES)
        for (_label, rows), columns, colour in zip(runs, found, colours):
            for column in columns:
                curve = metric_curve(rows, column, kind="train")
                if curve is None:
                    continue
                steps, mean, std = curve
                style = LINE_STYLES[names.index(column)] if styled else "-"
                tag = column if styled or len(runs) == 1 else None
                axes.plot(steps, mean, linestyle=style, color=colour if len(runs) > 1 else None,
                          linewidth=1.2 if styled else 0.6, label=tag, marker=marker(steps),
                          markersize=2)
                axes.fill_between(steps, mean - std, mean + std, color=axes.lines[-1].get_color(),
                                  alpha=0.15 if styled else 0.05)
                drawn += 1
        axes.set_title(title)
        steps_axis(axes)
        axes.grid(alpha=0.3)
        if axes.lines and (styled or len(runs) == 1):
            handles, labels = axes.get_legend_handles_labels()
            unique = dict(zip(labels, handles))
            if len(runs) > 1:  # the panel legend names line styles; colours name runs
                unique = {column: axes.plot([], [], linestyle=LINE_STYLES[i], color="0.3")[0]
                          for i, column in enumerate(names)}
            axes.legend(unique.values(), unique.keys(), fontsize="x-small")
    if drawn == 0:
        raise CmatError("no training diagnostics in " + ", ".join(str(p) for p in run_dirs))
    if len(runs) > 1:
        handles = [figure.axes[0].plot([], [], color=colour)[0] for colour in colours]
        legend_below(figure, handles, [label for label, _ in runs])
