"""`results.md`: an experiment's summary (`cmat.experiments.report.summarise`) as Markdown."""

from __future__ import annotations

from typing import Any

from cmat.experiments.lines import METRIC_NAMES
from cmat.experiments.plan import Plan


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
                 f"task(s) ({', '.join(agg['tasks'])}) where each of them has final scores; "
                 f"win rates as they are, returns min-max normalised per "
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
