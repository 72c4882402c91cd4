"""`results.md`: an experiment's summary (`cmat.experiments.report.summarise`) as Markdown."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from cmat.experiments.baselines import BASELINE_VARIANT
from cmat.experiments.claims import EVIDENCE_NEEDED, NO_DATA, SEPARATION, coverage
from cmat.experiments.lines import METRIC_NAMES
from cmat.experiments.plan import Plan
from cmat.experiments.spec import SPECS


def markdown(plan: Plan, summary: dict[str, Any]) -> str:
    out = [f"# Experiment `{plan.spec.name}`", "",
           (f"Spec: `spec.yaml` (from {spec_origin(plan.spec.path)}). Seeds "
            f"{seed_range(plan)} of every line. {settings_text(plan)} Score: "
            f"{score_text(plan)}, mean ± std (population "
            f"std, ddof = 0) over seeds (n = {plan.spec.seeds} unless marked). Metric: win "
            f"rate where the environment defines one, else episode return."
            f"{old_protocol_text(summary)}"), ""]
    main = labels_of(summary, "main")
    if main:
        out += ["## Scores", "",
                "| task | metric | steps | " + " | ".join(main) + " |",
                "|---" * (3 + len(main)) + "|"]
    for task in summary["tasks"] if main else []:
        if "unavailable" in task:
            cells = [f"unavailable: {task['unavailable']}"] + [""] * (len(main) - 1)
        else:
            cells = [cell(task["lines"].get(label), plan.spec.seeds) for label in main]
        metric = ("—" if "unavailable" in task or not task["lines"]
                  else METRIC_NAMES[task["metric"]])
        out.append(f"| {task['label']} | {metric} | {task['steps']:,} | " + " | ".join(cells)
                   + " |")
    if plan.spec.baselines:
        out.append(f"\nBaselines ({', '.join(plan.spec.baselines)}; dispatch tasks): one "
                   f"evaluation per seed of the task's evaluation episodes and options, not "
                   f"trained (`cmat.experiments.baselines`).")
    out += task_metrics_section(summary)
    stage_steps = {line["variant"]: line["steps"] for task in summary["tasks"]
                   for line in task["lines"].values() if "main" in line["figures"]
                   and line["variant"] != BASELINE_VARIANT
                   and plan.spec.variant(line["variant"]).finetune}
    for variant, steps in stage_steps.items():
        out.append(f"\nFine-tuning stage `{variant}` ran {steps:,} env steps after its base run "
                   f"(its curve counts its own steps).")
    ablation = labels_of(summary, "ablation")
    if ablation:
        out += ["", "## Ablation", "", "| task | variant | m | consensus | score |",
                "|---|---|---|---|---|"]
        for task in summary["tasks"]:
            for label, line in task["lines"].items():
                if "ablation" in line["figures"] and line["algo"] == "cmat":
                    out.append(f"| {task['label']} | {label} | {line['iterations']} | "
                               f"{line['consensus_source']} | {cell(line, plan.spec.seeds)} |")
    out += ["", "## Aggregate statistics", ""]
    agg = summary["aggregate"]
    if agg is None:
        out.append("Not computed: it needs two or more main lines with scores on a "
                   "common task.")
    else:
        out += [(f"Lines of the variants that run on every task, over {len(agg['tasks'])} "
                 f"task(s) ({', '.join(agg['tasks'])}) where each of them has scores (the "
                 f"`matrix:` games only when no other task qualifies); "
                 f"win rates as they are, returns min-max normalised per "
                 f"task; stratified bootstrap over seeds within tasks, {agg['reps']} "
                 f"replications, 95% percentile intervals (rliable's IQM and probability of "
                 f"improvement)."), "",
                "| line | runs | IQM [95% CI] | mean [95% CI] |", "|---|---|---|---|"]
        for label, line in agg["lines"].items():
            out.append(f"| {label} | {line['runs']} | "
                       f"{with_interval(line['iqm'], line['iqm_ci'])} | "
                       f"{with_interval(line['mean'], line['mean_ci'])} |")
        out += ["", "| comparison | P(X > Y) [95% CI] |", "|---|---|"]
        for pair, value in agg["improvement"].items():
            out.append(f"| {pair} | {with_interval(value['probability'], value['ci'])} |")
    out += claims_section(summary, score_text(plan), plan.spec.seeds)
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
    suite_rows = summary.get("suite_published", [])
    if suite_rows:
        out += ["", "Published suite means: each algorithm's curve in the Sable paper's benchmark, "
                "aggregated over the suite's tasks (10 seeds per task, tuned hyper-parameters), "
                "read off the figure at three budgets. Context for the suite, not a figure of "
                "any one task above; drawn on a task's panel (dotted) only where its scale is "
                "the task's (LBF's team return is normalised to [0, 1]).", "",
                "| suite | algorithm | mean over tasks | env steps | source |",
                "|---|---|---|---|---|"]
        for row in suite_rows:
            note = f" ({row['note']})" if row.get("note") else ""
            out.append(f"| {row['suite']} ({row['tasks']} tasks) | {row['algorithm']} | "
                       f"{row['value']:.3g} | {row['env_steps']:.0e} | {row['source']}{note} |")
    out += ["", "## Runs", ""]
    compute = compute_text(summary)
    if compute:
        out += [compute, ""]
    out += ["| run | found | this time | trained |", "|---|---|---|---|"]
    for run in summary["runs"]:
        found = run["status"] + (f": {run['note']}" if run["note"] else "")
        trained = ", ".join(f"{duration(seconds)} on {where}"
                            for where, seconds in run.get("seconds", {}).items())
        out.append(f"| {run['run']} | {found} | {run['outcome'] or '—'} | {trained or '—'} |")
    return "\n".join(out) + "\n"


def task_metrics_section(summary: dict[str, Any]) -> list[str]:
    """Per task whose environment reports figures beyond the return and the win rate (e.g.
    dispatch's service rate and waits), a table of every line's figures at each seed's last
    evaluation, averaged over seeds (`report.last_metrics`); nothing for other tasks."""
    out: list[str] = []
    for task in summary["tasks"]:
        lines = {label: line for label, line in task.get("lines", {}).items()
                 if line.get("metrics")}
        names = [name for name in dict.fromkeys(
            key for line in lines.values() for key in line["metrics"])
            if name not in ("episode_return", "win_rate")]
        if not names:
            continue
        if not out:
            out += ["", "## Environment metrics", "",
                    "Each line's figures at each seed's last evaluation, mean over seeds."]
        out += ["", f"**{task['label']}**", "",
                "| line | episode return | " + " | ".join(names) + " |",
                "|---" * (2 + len(names)) + "|"]
        for label, line in lines.items():
            values = [line["metrics"].get(name) for name in ("episode_return", *names)]
            out.append(f"| {label} | " + " | ".join(
                "—" if value is None else f"{value:,.0f}" if abs(value) >= 1000
                else f"{value:.3g}" for value in values) + " |")
    return out


def duration(seconds: float) -> str:
    """'2.5 h', '14 min' or '40 s': hours from one hour up, minutes from one minute up."""
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 60:.0f} min" if seconds >= 60 else f"{seconds:.0f} s"


def compute_text(summary: dict[str, Any]) -> str:
    """The runs' training wall time per place, and how many distinct runs it covers where a
    run trained in more than one place; '' when no run has that record."""
    compute = summary.get("compute") or {}
    if not compute:
        return ""
    distinct = sum(1 for run in summary["runs"] if run["seconds"])
    return ("Training wall time of the runs on disk (each run's sessions.jsonl; runs without "
            "that record are not counted): " + "; ".join(
                f"{duration(entry['hours'] * 3600)} on {where} over {entry['runs']:.0f} runs"
                for where, entry in compute.items())
            + (f" ({distinct} distinct runs: a run that trained in more than one place counts "
               f"in each)" if len(compute) > 1 else "") + ".")


def seed_range(plan: Plan) -> str:
    first, count = plan.spec.seed, plan.spec.seeds
    return str(first) if count == 1 else f"{first}–{first + count - 1}"


def settings_text(plan: Plan) -> str:
    """The settings the spec gives every run (its top-level `set`); per-task and per-variant
    settings are in spec.yaml."""
    shared = ", ".join(f"`{override}`" for override in plan.spec.overrides)
    return (f"Every run: {shared}; otherwise each algorithm's reference settings "
            f"(per-task and per-variant settings in spec.yaml)." if shared else
            "Every run at its algorithm's reference settings, except the per-task and "
            "per-variant settings in spec.yaml.")


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
    n = len(line["scores"])
    return f"{line['mean']:.3g} ± {line['std']:.2g}" + ("" if n == seeds else f" (n={n})")


def score_text(plan: Plan) -> str:
    """How a seed's score is made (cmat.experiments.lines.Line.scores), in words."""
    window = plan.spec.score_window
    kinds = {run.config.eval_actions for run in plan.runs if run.config is not None}
    evaluation = {frozenset({"greedy"}): "greedy evaluation",
                  frozenset({"sample"}): "sampled evaluation"}.get(
        frozenset(kinds), "evaluation (greedy or sampled: each run's `eval_actions`)")
    if window == 0:
        return f"each seed's last {evaluation}"
    return (f"each seed's mean {evaluation} over the last {window * 100:g}% of its env steps "
            f"(`score_window`; its last evaluation included)")


def old_protocol_text(summary: dict[str, Any]) -> str:
    """A sentence naming the runs evaluated before each evaluation drew its own episodes
    (`cmat.rundir.EVAL_PROTOCOL`), or nothing."""
    old = [run["run"] for run in summary["runs"] if run.get("eval_protocol") == 1]
    if not old:
        return ""
    return (f" {len(old)} of {len(summary['runs'])} runs were evaluated under the old protocol "
            f"(every evaluation of a run replayed the same episodes, so a score window averages "
            f"repeated evaluations of one set of episodes): {', '.join(old)}.")


def claims_section(summary: dict[str, Any], score: str, seeds: int) -> list[str]:
    """The claims table (one row per claim; with a score window, also the verdict from the
    last evaluations alone) and the per-task comparisons behind it."""
    claims = summary.get("claims") or []
    if not claims:
        return []
    from_finals = {claim["statement"]: claim for claim in summary.get("claims_from_finals", [])}
    labels = {task["env"]: task["label"] for task in summary["tasks"]}
    out = ["", "## The paper's claims", "",
           (f"Each claim is judged from this grid's scores ({score}) by "
            f"cmat.experiments.claims: "
            f"P(X > Y) is rliable's probability of improvement with a stratified bootstrap 95% "
            f"interval, per task and aggregated over the tasks both lines ran (returns min-max "
            f"normalised per task), beside each line's IQM with its interval from the same "
            f"resamples (with fewer than 4 seeds a task's IQM is their mean). "
            f"A comparison is decided when its interval excludes "
            f"{SEPARATION}. Supported: X reliably better in every per-task comparison the claim "
            f"needs (for (d): no other m reliably better anywhere, and m = n reliably better "
            f"than some other m somewhere). Not supported: the other line reliably better in "
            f"some comparison. Tied: every seed of both lines scored the same on every task. "
            f"Not separable at this budget: otherwise. A verdict resting on fewer tasks or "
            f"per-task comparisons than the spec plans says how many. With {seeds} seeds a "
            f"side the bootstrap interval is [1.00, 1.00] as soon as every seed of X beats "
            f"every seed of Y, while an exact one-sided Mann-Whitney test of that outcome gives "
            f"p = {1 / math.comb(2 * seeds, seeds):.2g}: read a decided comparison with that "
            f"in mind. "
            f"Fine-tuning stages ran "
            f"their own steps after their base run. Tasks with `matrix:` ids are claim (e)'s."
            + (" The last column judges each claim the same way from each seed's last "
               "evaluation alone, to show how much the verdict owes to the score's definition."
               if from_finals else "")),
           "", "| claim | verdict | evidence: X vs Y, aggregate P(X > Y) [95% CI], IQM of X and "
               "Y (normalised scores), tasks where X / Y was reliably better / neither |"
           + (" verdict from last evaluations |" if from_finals else ""),
           "|---|---|---|" + ("---|" if from_finals else "")]
    for claim in claims:
        evidence = "; ".join(
            f"{c['x']} vs {c['y']}: {c['probability']:.2f} [{c['ci'][0]:.2f}, {c['ci'][1]:.2f}]"
            f", IQM {c['iqm_x']:.2f} vs {c['iqm_y']:.2f}, "
            f"{tally(c)} of {len(c['tasks'])} task(s)"
            for c in claim["comparisons"]) or f"none: needs {EVIDENCE_NEEDED[claim['key']]}"
        not_run = claim.get("not_run", ())
        statement = claim["statement"] + (f" (this grid runs no {', '.join(not_run)})"
                                          if not_run else "")
        row = (f"| ({claim['key']}) {statement} | "
               f"{claim['verdict']}{coverage(claim)} | {evidence} |")
        if from_finals:
            last = from_finals.get(claim["statement"])
            row += f" {last['verdict'] + coverage(last) if last else NO_DATA} |"
        out.append(row)
    rows = [(claim, c, t) for claim in claims for c in claim["comparisons"]
            for t in c["per_task"]]
    if rows:
        out += ["", "| claim | X | Y | task | P(X > Y) [95% CI] | reliably better | "
                    "IQM of X [95% CI] | IQM of Y [95% CI] |",
                "|---|---|---|---|---|---|---|---|"]
        decided = {"x": "X", "y": "Y", "tie": "neither", "same": "neither (equal scores)"}
        for claim, c, t in rows:
            task = labels.get(t["task"], t["task"])
            out.append(f"| ({claim['key']}) | {c['x']} | {c['y']} | {task}"
                       f" | {t['probability']:.2f} [{t['ci'][0]:.2f}, {t['ci'][1]:.2f}] | "
                       f"{decided[t['outcome']]} | {with_interval(t['iqm_x'], t['iqm_x_ci'])} | "
                       f"{with_interval(t['iqm_y'], t['iqm_y_ci'])} |")
    if all(claim["verdict"] == NO_DATA for claim in claims):
        out += ["", "No claim has data yet: none of the comparisons they need has complete runs "
                    "of both lines."]
    return out


def with_interval(value: float, ci: list[float]) -> str:
    return f"{value:.3f} [{ci[0]:.3f}, {ci[1]:.3f}]"


def tally(comparison: dict[str, Any]) -> str:
    counts = [sum(t["outcome"] in o for t in comparison["per_task"])
              for o in (("x",), ("y",), ("tie", "same"))]
    return " / ".join(str(n) for n in counts)


def spec_origin(path: Path) -> str:
    """Where a report's spec came from: the name of a spec shipped with cmat, else its path."""
    if path.resolve().parent == SPECS.resolve():
        return f"cmat's spec `{path.stem}`"
    return f"`{path}`"
