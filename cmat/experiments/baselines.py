"""Classical policies as lines of an experiment: the spec's `baselines` (dispatch tasks only:
`cmat.envs.dispatch.baselines`), evaluated on every dispatch task of the grid when its report is
written, beside the learned lines in the tables, statistics and figures.

A baseline learns nothing, so its line is one evaluation per seed: `eval_episodes` episodes of
the task's configuration (its runs' `eval_episodes` and `env_kwargs`) from that seed's keys,
recorded at the task's budget. Evaluations are kept in `OUT/baselines/TASK/NAME.json` and
reused while the episodes, options and seeds they were made with are the grid's; an export
(`cmat experiment ... --export DIR`) takes them along, so its report does not evaluate them again.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from cmat.experiments.lines import Line
from cmat.experiments.plan import Plan
from cmat.experiments.spec import EnvEntry

BASELINES_DIR = "baselines"
"""The folder of an experiment directory that keeps the baselines' evaluations, one
`TASK/NAME.json` each."""

BASELINE_VARIANT = "baseline"
"""The `Line.variant` of a baseline line."""

BASELINE_LABELS = {"random": "random (legal)", "greedy": "greedy (nearest)",
                   "hungarian": "Hungarian"}
"""The legend entry of each baseline of `cmat.envs.dispatch.baselines.POLICIES`."""


def baseline_lines(plan: Plan) -> dict[str, list[Line]]:
    """Per dispatch task of the grid (not unavailable), one line per spec baseline."""
    lines: dict[str, list[Line]] = {}
    for env in plan.spec.envs:
        if not plan.spec.baselines or not env.id.startswith("dispatch:") \
                or env.id in plan.unavailable:
            continue
        config = next(r.config for r in plan.runs if r.env is env and r.config is not None)
        setting = {"episodes": config.eval_episodes, "env_kwargs": config.env_kwargs,
                   "seeds": list(range(plan.spec.seed, plan.spec.seed + plan.spec.seeds)),
                   "env_steps": config.budget_steps}
        for name in plan.spec.baselines:
            rows = evaluated_rows(plan.out / BASELINES_DIR / env.slug / f"{name}.json", env,
                                  name, setting)
            lines.setdefault(env.id, []).append(Line(
                BASELINE_LABELS[name], BASELINE_VARIANT, f"baseline:{name}", ("main",), [], rows))
    return lines


def evaluated_rows(
    path: Path, env: EnvEntry, name: str, setting: dict[str, Any]
) -> list[dict[str, str]]:
    """metrics.csv-like eval rows (strings; NaN as '') of baseline `name` on `env`, one per
    seed of `setting`, from `path` where it holds this setting's, else evaluated and saved."""
    try:
        saved = json.loads(path.read_text())
        if saved["setting"] == setting:
            return list(saved["rows"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    from cmat.envs.dispatch.baselines import baseline_env, evaluate_means

    task = baseline_env(env.id, setting["env_kwargs"])
    rows = []
    for seed in setting["seeds"]:
        means = evaluate_means(task, name, setting["episodes"], seed)
        rows.append({"kind": "eval", "seed": str(seed), "env_steps": str(setting["env_steps"]),
                     "win_rate": "", **{key: "" if math.isnan(value) else repr(value)
                                        for key, value in means.items()}})
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"setting": setting, "rows": rows}, indent=1))
    return rows
