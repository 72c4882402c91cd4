"""The paper's claims judged from an experiment's scores: a verdict per claim, computed.

The claims (paper, Introduction and Experiments):

- (a) CMAT beats MAT, PMAT, Triple-BERT, HAPPO and MAPPO on every task;
- (b) the fine-tuned variants are best;
- (c) the consensus from the mixture of e0..em beats the one from the last vector e_m;
- (d) m = n decoder iterations is a robust default;
- (e) CMAT avoids MAT's Pareto-suboptimal equilibrium on the Fig. 1 game.

Which lines a claim compares is read from the grid, not named here. The reference CMAT line is
the `default` variant's CMAT. (a): every CMAT line of the main figure that is not a fine-tuning
stage (the default and, e.g., the paper preset) against every other algorithm's main line.
(b): each fine-tuning stage's line against every other main line on the tasks it ran. (c): the
reference against each CMAT line whose consensus comes from e_m and whose m equals the
reference's. (d): the reference (m = n) against each CMAT line with another m and the
reference's consensus source. (e): CMAT against MAT on the matrix games (`matrix:` ids);
(a)-(d) use the other tasks.

Scores: each seed's score (`cmat.experiments.lines.Line.scores`: its last evaluation, or
its mean evaluation over the spec's `score_window`). Evidence for "X beats Y": rliable's
probability of improvement P(X > Y) with a stratified
bootstrap 95% percentile interval, on each task (seeds resampled) and aggregated over the tasks
both lines ran (scores normalised as in `cmat.experiments.statistics.normalise`), beside the IQM
of each line with its 95% interval, on each task and over those tasks. A comparison is decided
when its interval excludes 0.5: X reliably better when the lower bound is above 0.5, Y reliably
better when the upper bound is below it. Verdicts, from the per-task comparisons:

- "supported": X is reliably better in every comparison the claim needs (for (d): no other m
  is reliably better on any task, and m = n is reliably better than some other m on some task);
- "not supported": some comparison finds Y reliably better (for (d): some other m);
- "not separable at this budget": neither (at least one interval contains 0.5);
- "tied: equal scores in every seed": every seed of both lines scored the same on every task
  (as when every line reaches a game's optimum), so no budget would separate them;
- "no data": no task on which the claim's lines both have scores.

A verdict reached on fewer tasks, or fewer per-task comparisons, than the claim covers in the
spec says on how many of each (`coverage`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from cmat.algorithms import algorithm_label
from cmat.experiments.baselines import BASELINE_VARIANT
from cmat.experiments.spec import ExperimentSpec
from cmat.experiments.statistics import bootstrap, improvement_probability, interval, iqm, normalise

SEPARATION = 0.5
"""P(X > Y) of two indistinguishable lines; a decided comparison's interval excludes it."""

SUPPORTED, NOT_SUPPORTED, NOT_SEPARABLE, TIED, NO_DATA = (
    "supported", "not supported", "not separable at this budget",
    "tied: equal scores in every seed", "no data")

CLAIMS = {
    "a": "CMAT beats MAT, PMAT, Triple-BERT, HAPPO and MAPPO on every task",
    "b": "the fine-tuned variants are best",
    "c": "the mixture consensus beats the last consensus vector",
    "d": "m = n is a robust default",
    "e": "CMAT avoids MAT's Pareto-suboptimal equilibrium on the Fig. 1 game",
}

PAPER_BASELINES = ("mat", "pmat", "triple_bert", "happo", "mappo")
"""The baselines of claim (a); a grid without one of them says so in the claim's row."""

EVIDENCE_NEEDED = {
    "a": "complete runs of a CMAT line and a baseline on the same benchmark (not `matrix:`) task",
    "b": "complete runs of a fine-tuning stage and another main line on the same benchmark task",
    "c": ("complete runs of CMAT (default) and a CMAT line with `consensus_source: last` on the "
          "same benchmark task"),
    "d": "complete runs of CMAT (default) and CMAT at another m on the same benchmark task",
    "e": "complete runs of CMAT (default) and MAT on the same `matrix:` task",
}
"""What each claim's comparisons are made of: the reason a claim with no comparison has no
data (the grid or its spec lacks these)."""


@dataclass(frozen=True)
class TaskComparison:
    task: str
    probability: float
    ci: list[float]
    outcome: str
    """'x' (X reliably better), 'y' (Y reliably better), 'tie' (interval contains 0.5) or
    'same' (every seed of both lines scored one value)."""
    iqm_x: float
    iqm_x_ci: list[float]
    iqm_y: float
    iqm_y_ci: list[float]
    """Each line's IQM on the task with its 95% interval, from the same resamples as `ci`."""


@dataclass(frozen=True)
class Comparison:
    """X against Y on the tasks where both have scores."""

    x: str
    y: str
    tasks: list[str]
    probability: float
    ci: list[float]
    iqm_x: float
    iqm_x_ci: list[float]
    iqm_y: float
    iqm_y_ci: list[float]
    per_task: list[TaskComparison]

    def count(self, outcome: str) -> int:
        return sum(t.outcome == outcome for t in self.per_task)


@dataclass
class Claim:
    key: str
    statement: str
    comparisons: list[Comparison] = field(default_factory=list)
    tasks_in_spec: int = 0
    comparisons_in_spec: int = 0
    """Per-task comparisons the spec plans for the claim: for each line X is compared with
    (with scores yet or not), the spec's tasks that both lines' variants run on."""
    verdict: str = NO_DATA
    not_run: tuple[str, ...] = ()
    """The claim's lines that no variant of the spec runs (claim (a)'s absent baselines)."""


def outcome(ci: list[float], xs: np.ndarray, ys: np.ndarray) -> str:
    if np.all(xs == xs.flat[0]) and np.all(ys == xs.flat[0]):
        return "same"
    if ci[0] > SEPARATION:
        return "x"
    if ci[1] < SEPARATION:
        return "y"
    return "tie"


def compare(x: str, y: str, scores: dict[str, dict[str, list[float]]], reps: int) -> (
        Comparison | None):
    """P(x > y) per task and aggregated over the tasks of `scores` (task -> label ->
    normalised scores) where both have scores; None where there is no such task."""
    tasks = [t for t, lines in scores.items() if lines.get(x) and lines.get(y)]
    if not tasks:
        return None
    rng = np.random.default_rng(0)
    per_task = []
    for task in tasks:
        xs, ys = (np.array(scores[task][label])[:, None] for label in (x, y))
        point = float(improvement_probability(xs, ys))
        resampled_x, resampled_y = bootstrap(xs, reps, rng), bootstrap(ys, reps, rng)
        ci = interval(improvement_probability(resampled_x, resampled_y))
        per_task.append(TaskComparison(
            task, point, ci, outcome(ci, xs, ys),
            float(iqm(xs)), interval(iqm(resampled_x)), float(iqm(ys)), interval(iqm(resampled_y)),
        ))
    runs = {label: min(len(scores[t][label]) for t in tasks) for label in (x, y)}
    matrix = {label: np.array([[scores[t][label][i] for t in tasks] for i in range(runs[label])])
              for label in (x, y)}
    samples = {label: bootstrap(m, reps, rng) for label, m in matrix.items()}
    return Comparison(
        x, y, tasks,
        float(improvement_probability(matrix[x], matrix[y])),
        interval(improvement_probability(samples[x], samples[y])),
        float(iqm(matrix[x])), interval(iqm(samples[x])),
        float(iqm(matrix[y])), interval(iqm(samples[y])),
        per_task,
    )


def verdict(comparisons: list[Comparison], robust_default: bool = False) -> str:
    """The verdict of a claim from its comparisons' per-task outcomes (module docstring)."""
    outcomes = [t.outcome for c in comparisons for t in c.per_task]
    if not outcomes:
        return NO_DATA
    if "y" in outcomes:
        return NOT_SUPPORTED
    if all(o == "same" for o in outcomes):
        return TIED
    if robust_default:
        return SUPPORTED if "x" in outcomes else NOT_SEPARABLE
    return SUPPORTED if all(o == "x" for o in outcomes) else NOT_SEPARABLE


def judge_claims(
    summary: dict[str, Any], spec: ExperimentSpec, scores: str = "scores"
) -> list[dict[str, Any]]:
    """The claims (a)-(e) judged from `summary` (`cmat.experiments.report.summarise`): per claim
    its statement, comparisons, the number of the spec's tasks it covers and its verdict.
    `scores` names the per-seed values of each line that are compared: "scores" (the spec's
    score window) or "finals" (each seed's last evaluation)."""
    by_task: dict[str, dict[str, list[float]]] = {}
    lines: dict[str, dict[str, Any]] = {}
    # m of each line on each of its tasks: m = n resolves to a different count per task.
    iterations: dict[str, dict[str, Any]] = {}
    for task in summary["tasks"]:
        if "unavailable" in task:
            continue
        learned = {label: line for label, line in task["lines"].items()
                   if line["variant"] != BASELINE_VARIANT}
        task_scores = {label: line[scores] for label, line in learned.items() if line[scores]}
        by_task[task["env"]] = normalise(task_scores, task["metric"]) if task_scores else {}
        for label, line in learned.items():
            lines.setdefault(label, line)
            iterations.setdefault(label, {})[task["env"]] = line.get("iterations")
    game = {t: s for t, s in by_task.items() if t.startswith("matrix:")}
    benchmark = {t: s for t, s in by_task.items() if not t.startswith("matrix:")}
    spec_tasks = [e.id for e in spec.envs if e.unavailable is None]
    reps = spec.bootstrap_reps

    def variant_of(label: str) -> Any:
        return spec.variant(lines[label]["variant"])

    def stage(label: str) -> bool:
        return variant_of(label).finetune is not None

    def main(label: str) -> bool:
        return "main" in lines[label]["figures"]

    reference = next((label for label, line in lines.items()
                      if line["variant"] == "default" and line["algo"] == "cmat"), None)
    cmat_lines = [label for label, line in lines.items()
                  if line["algo"] == "cmat" and main(label) and not stage(label)]
    baselines = [label for label, line in lines.items() if line["algo"] != "cmat" and main(label)]
    stages = [label for label in lines if stage(label)]
    ref_line = lines.get(reference) if reference else None

    def pairs(x: str, ys: list[str], scores: dict[str, dict[str, list[float]]]) -> (
            list[Comparison]):
        return [c for y in ys if (c := compare(x, y, scores, reps)) is not None]

    def covered(variant_names: set[str], in_game: bool) -> int:
        return sum(1 for t in spec_tasks if t.startswith("matrix:") == in_game
                   and all(spec.variant(v).covers(t) for v in variant_names))

    def planned(x: str, ys: list[str], in_game: bool = False) -> int:
        return sum(covered({lines[x]["variant"], lines[y]["variant"]}, in_game) for y in ys)

    in_spec = {algo for v in spec.variants if "main" in v.figures for algo in v.algos}
    absent = tuple(algorithm_label(algo) for algo in PAPER_BASELINES if algo not in in_spec)
    claims: list[Claim] = []
    for label in cmat_lines:
        budget = variant_of(label).steps
        rivals = [y for y in baselines if variant_of(y).steps == budget]  # same budget only
        claims.append(Claim("a", f"{CLAIMS['a']} ({label})", pairs(label, rivals, benchmark),
                            covered({lines[label]["variant"]}, False),
                            planned(label, rivals), not_run=absent))
    for label in stages:
        others = [o for o in lines if o != label and main(o) and not stage(o)]
        claims.append(Claim("b", f"{CLAIMS['b']} ({label})", pairs(label, others, benchmark),
                            covered({lines[label]["variant"]}, False), planned(label, others)))
    seen_stages = {lines[label]["variant"] for label in stages}
    for variant in spec.variants:
        if variant.finetune is not None and variant.name not in seen_stages:
            for algo in variant.algos:
                claims.append(Claim("b", f"{CLAIMS['b']} ({variant.line_label(algo)})", [],
                                    covered({variant.name}, False)))
    if ref_line is not None and reference is not None:
        def same_m(label: str) -> bool:
            shared = iterations[label].keys() & iterations[reference].keys()
            return all(iterations[label][t] == iterations[reference][t] for t in shared)

        last = [label for label, line in lines.items() if line["algo"] == "cmat"
                and line["consensus_source"] == "last" and not stage(label) and same_m(label)]
        other_m = [label for label, line in lines.items() if line["algo"] == "cmat"
                   and line["consensus_source"] == ref_line["consensus_source"]
                   and not stage(label) and not same_m(label)]
        claims.append(Claim("c", CLAIMS["c"], pairs(reference, last, benchmark),
                            covered({lines[o]["variant"] for o in last}, False),
                            planned(reference, last)))
        claims.append(Claim("d", CLAIMS["d"], pairs(reference, other_m, benchmark),
                            covered({lines[o]["variant"] for o in other_m}, False),
                            planned(reference, other_m)))
        mat = [label for label, line in lines.items()
               if line["algo"] == "mat" and line["variant"] == "default"]
        claims.append(Claim("e", CLAIMS["e"], pairs(reference, mat, game), covered(set(), True),
                            planned(reference, mat, in_game=True)))
    claims += [Claim(key, statement) for key, statement in CLAIMS.items()
               if not any(claim.key == key for claim in claims)]
    claims.sort(key=lambda claim: claim.key)
    for claim in claims:
        claim.verdict = verdict(claim.comparisons, robust_default=claim.key == "d")
    return [asdict(claim) for claim in claims]


def coverage(claim: dict[str, Any]) -> str:
    """' (on k of K tasks; d of D per-task comparisons)', each part only where the claim's
    comparisons cover fewer tasks than the spec has or fewer of the per-task comparisons the
    spec plans (a line's run not yet complete there); '' for a complete claim or no data."""
    if claim["verdict"] == NO_DATA:
        return ""
    parts = []
    tasks = {t for c in claim["comparisons"] for t in c["tasks"]}
    if len(tasks) < claim["tasks_in_spec"]:
        parts.append(f"on {len(tasks)} of {claim['tasks_in_spec']} tasks")
    done = sum(len(c["tasks"]) for c in claim["comparisons"])
    if done < claim.get("comparisons_in_spec", 0):
        parts.append(f"{done} of {claim['comparisons_in_spec']} per-task comparisons")
    return f" ({'; '.join(parts)})" if parts else ""
