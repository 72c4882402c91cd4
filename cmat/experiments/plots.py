"""Evaluation curves of one or more run directories (mean over seeds, ±1 std shaded)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from cmat.errors import CmatError
from cmat.rundir import RunDir

Curve = tuple[np.ndarray, np.ndarray, np.ndarray]


def eval_curve(rows: list[dict[str, str]], column: str, kind: str = "eval") -> Curve | None:
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


def plot_runs(run_dirs: list[Path], out: Path) -> None:
    """Eval episode return (and win rate, where any run defines it) against env steps per seed."""
    panels: dict[str, list[tuple[str, Curve]]] = {"episode_return": [], "win_rate": []}
    for path in run_dirs:
        run = RunDir.open(path)
        config, rows = run.config(), run.read_metrics()
        label = f"{config.env} {config.algo} ({run.path.resolve().name})"
        returns = eval_curve(rows, "episode_return")
        if returns is None:
            raise CmatError(f"no evaluation results in {run.path}")
        panels["episode_return"].append((label, returns))
        win_rate = eval_curve(rows, "win_rate")
        if win_rate is not None:
            panels["win_rate"].append((label, win_rate))
    shown = {name: curves for name, curves in panels.items() if curves}
    figure = Figure(figsize=(6 * len(shown), 4), layout="constrained")
    all_axes = figure.subplots(1, len(shown), squeeze=False)[0]
    for axes, (name, curves) in zip(all_axes, shown.items()):
        for label, (steps, mean, std) in curves:
            (line,) = axes.plot(steps, mean, label=label)
            axes.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.2)
        axes.set_xlabel("env steps per seed")
        axes.set_ylabel(f"eval {name.replace('_', ' ')}")
        axes.grid(alpha=0.3)
        axes.legend(fontsize="small")
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=100)


DIAGNOSTIC_PANELS = (
    ("clip fraction", ("joint_clip_frac", "agent_clip_frac")),
    ("approximate KL", ("joint_approx_kl", "agent_approx_kl")),
    ("explained variance", ("explained_variance",)),
    ("entropy (mean over agents)", ("entropy",)),
    ("entropy per agent", ("entropy_agent_",)),
    ("gradient norm per block", ("grad_norm_",)),
)
"""Panels of `plot_diagnostics`: title and the train columns drawn (a trailing _ is a prefix)."""


def plot_diagnostics(run_dirs: list[Path], out: Path) -> None:
    """Per-update training diagnostics of run directories (mean over seeds, ±1 std shaded):
    joint and per-agent clip fraction and approximate KL, explained variance of the value,
    entropy (mean and per agent) and the gradient norm of each parameter block."""
    runs = []
    for path in run_dirs:
        run = RunDir.open(path)
        runs.append((f"{run.config().algo} ({run.path.resolve().name})", run.read_metrics()))
    figure = Figure(figsize=(18, 8), layout="constrained")
    all_axes = figure.subplots(2, 3).reshape(-1)
    drawn = 0
    for axes, (title, wanted) in zip(all_axes, DIAGNOSTIC_PANELS):
        for label, rows in runs:
            columns = list(rows[0]) if rows else []
            for column in [c for c in columns for w in wanted
                           if (c.startswith(w) if w.endswith("_") else c == w)]:
                curve = eval_curve(rows, column, kind="train")
                if curve is None:
                    continue
                steps, mean, std = curve
                (line,) = axes.plot(steps, mean, label=f"{label} {column}")
                axes.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.2)
                drawn += 1
        axes.set_title(title)
        axes.set_xlabel("env steps per seed")
        axes.grid(alpha=0.3)
        if axes.lines:
            axes.legend(fontsize="x-small")
    if drawn == 0:
        raise CmatError("no training diagnostics in " + ", ".join(str(p) for p in run_dirs))
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=100)
