"""Evaluation curves of one or more run directories (mean over seeds, ±1 std shaded)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from cmat.errors import CmatError
from cmat.rundir import RunDir

Curve = tuple[np.ndarray, np.ndarray, np.ndarray]


def eval_curve(rows: list[dict[str, str]], column: str) -> Curve | None:
    """(env_steps, mean, std) over seeds of an eval column; None where it is never defined."""
    by_step: dict[int, list[float]] = {}
    for row in rows:
        if row["kind"] == "eval" and row[column] != "":
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
