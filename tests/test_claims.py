"""The claims section: verdicts computed from the lines' scores, never written in."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from cmat.experiments.claims import (
    CLAIMS,
    NO_DATA,
    NOT_SEPARABLE,
    NOT_SUPPORTED,
    SUPPORTED,
    TIED,
    compare,
    coverage,
    judge_claims,
)
from cmat.experiments.markdown import claims_section, compute_text
from cmat.experiments.report import compute_totals
from cmat.experiments.spec import ExperimentSpec, load_spec

pytestmark = pytest.mark.unit

TASKS = ("matrix:fig1", "smax:3m", "smax:2s3z")
STRONG, WEAK, MIDDLE = [0.9, 0.95, 1.0], [0.1, 0.2, 0.3], [0.5, 0.6, 0.55]


@pytest.fixture
def spec(tmp_path: Path) -> ExperimentSpec:
    path = tmp_path / "claims.yaml"
    path.write_text(yaml.safe_dump({
        "steps": 100, "envs": list(TASKS), "algos": ["cmat", "mat", "mappo"],
        "variants": {
            "default": {"figure": ["main", "ablation"]},
            "paper": {"algos": ["cmat"], "set": {"preset": "paper"}, "label": "CMAT paper"},
            "finetune_action": {"algos": ["cmat"], "from": "default", "finetune": "action",
                                "envs": ["smax:3m", "smax:2s3z"], "label": "CMAT-ft"},
            "last": {"algos": ["cmat"], "figure": "ablation", "label": "last",
                     "envs": ["smax:3m", "smax:2s3z"],
                     "set": {"cmat": {"consensus_source": "last"}}},
            "m_half": {"algos": ["cmat"], "figure": "ablation", "label": "m = n/2",
                       "envs": ["smax:3m", "smax:2s3z"],
                       "set": {"cmat": {"consensus_iterations": "n/2"}}},
        },
    }))
    return load_spec(path)


TEAM = {"matrix:fig1": 2, "smax:3m": 3, "smax:2s3z": 5}
"""n of each task: m = n resolves to a different count on each, as in a real summary."""
LINES = {  # label: (variant, algo, figures, consensus source, m as configured)
    "CMAT": ("default", "cmat", ["main", "ablation"], "mixture", "n"),
    "MAT": ("default", "mat", ["main", "ablation"], None, None),
    "MAPPO": ("default", "mappo", ["main", "ablation"], None, None),
    "CMAT paper": ("paper", "cmat", ["main"], "mixture", "n"),
    "CMAT-ft": ("finetune_action", "cmat", ["main"], "mixture", "n"),
    "last": ("last", "cmat", ["ablation"], "last", "n"),
    "m = n/2": ("m_half", "cmat", ["ablation"], "mixture", "n/2"),
}


def summary(finals: dict[str, dict[str, list[float]]]) -> dict[str, Any]:
    """A summary as `summarise` writes it: scores per task and line label (each seed's last
    evaluation too), m resolved against the task's team."""
    tasks = []
    for task in TASKS:
        lines = {}
        for label, scores in finals.get(task, {}).items():
            variant, algo, figures, source, m = LINES[label]
            iterations = None if m is None else TEAM[task] // (2 if m == "n/2" else 1)
            lines[label] = {"variant": variant, "algo": algo, "figures": figures,
                            "scores": scores, "finals": scores, "iterations": iterations,
                            "consensus_source": source}
        metric = "episode_return" if task.startswith("matrix:") else "win_rate"
        tasks.append({"env": task, "label": task, "metric": metric, "lines": lines})
    return {"tasks": tasks}


def by_key(claims: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    return {claim["statement"].rsplit("(", 1)[-1].rstrip(")") if claim["key"] in "ab"
            else claim["key"]: claim for claim in claims}


def full_grid(**changes: list[float]) -> dict[str, dict[str, list[float]]]:
    """CMAT strong, its paper preset and fine-tuning strong, every other line weak."""
    smax = {"CMAT": STRONG, "MAT": WEAK, "MAPPO": WEAK, "CMAT paper": STRONG,
            "CMAT-ft": STRONG, "last": WEAK, "m = n/2": WEAK, **changes}
    game = {"CMAT": [100.0] * 3, "MAT": [100.0] * 3, "MAPPO": [100.0] * 3}
    return {"matrix:fig1": game, "smax:3m": dict(smax), "smax:2s3z": dict(smax)}


def test_verdicts_follow_the_scores(spec: ExperimentSpec) -> None:
    claims = by_key(judge_claims(summary(full_grid()), spec))
    assert claims["CMAT"]["verdict"] == SUPPORTED
    assert tuple(claims["CMAT"]["not_run"]) == ("PMAT", "Triple-BERT", "HAPPO")
    assert claims["CMAT paper"]["verdict"] == SUPPORTED
    assert claims["c"]["verdict"] == SUPPORTED
    assert claims["d"]["verdict"] == SUPPORTED
    assert claims["e"]["verdict"] == TIED  # every method at the optimum in every seed
    # The fine-tuning stage ties CMAT and its paper preset: best is not separable.
    assert claims["CMAT-ft"]["verdict"] == NOT_SEPARABLE


def test_a_baseline_reliably_better_on_one_task_refutes_every_task(
    spec: ExperimentSpec,
) -> None:
    grid = full_grid()
    grid["smax:2s3z"]["MAPPO"] = MIDDLE
    grid["smax:2s3z"]["CMAT"] = WEAK
    claims = by_key(judge_claims(summary(grid), spec))
    assert claims["CMAT"]["verdict"] == NOT_SUPPORTED
    mappo = next(c for c in claims["CMAT"]["comparisons"] if c["y"] == "MAPPO")
    assert [t["outcome"] for t in mappo["per_task"]] == ["x", "y"]
    assert claims["CMAT paper"]["verdict"] == SUPPORTED


def test_overlapping_scores_are_not_separable(spec: ExperimentSpec) -> None:
    grid = full_grid(MAT=[0.85, 0.95, 1.0], last=[0.9, 0.95, 1.0])
    claims = by_key(judge_claims(summary(grid), spec))
    assert claims["CMAT"]["verdict"] == NOT_SEPARABLE
    assert claims["c"]["verdict"] == NOT_SEPARABLE


def test_robust_default_fails_when_another_m_wins_and_is_open_when_all_tie(
    spec: ExperimentSpec,
) -> None:
    assert by_key(judge_claims(summary(full_grid(**{"m = n/2": [1.0] * 3, "CMAT": MIDDLE})),
                               spec))["d"]["verdict"] == NOT_SUPPORTED
    assert by_key(judge_claims(summary(full_grid(**{"m = n/2": STRONG})), spec))["d"][
        "verdict"] == NOT_SEPARABLE


def test_claims_without_runs_have_no_data_and_partial_grids_say_how_many_tasks(
    spec: ExperimentSpec,
) -> None:
    grid = full_grid()
    del grid["smax:2s3z"]
    for label in ("last", "CMAT-ft"):
        del grid["smax:3m"][label]
    claims = by_key(judge_claims(summary(grid), spec))
    assert claims["c"]["verdict"] == NO_DATA and coverage(claims["c"]) == ""
    assert claims["CMAT"]["verdict"] == SUPPORTED
    assert coverage(claims["CMAT"]) == " (on 1 of 2 tasks; 2 of 4 per-task comparisons)"
    assert claims["CMAT-ft"]["verdict"] == NO_DATA and not claims["CMAT-ft"]["comparisons"]
    nothing = judge_claims(summary({}), spec)
    assert [claim["key"] for claim in nothing] == ["a", "b", "c", "d", "e"]
    assert {claim["verdict"] for claim in nothing} == {NO_DATA}


@pytest.mark.parametrize("seed", range(5))
def test_swapping_the_lines_mirrors_the_probability(seed: int) -> None:
    rng = np.random.default_rng(seed)
    scores = {task: {"X": list(rng.random(3)), "Y": list(rng.random(4))}
              for task in ("t1", "t2")}
    forward, backward = compare("X", "Y", scores, 500), compare("Y", "X", scores, 500)
    assert forward is not None and backward is not None
    assert forward.probability + backward.probability == pytest.approx(1.0)
    for f, b in zip(forward.per_task, backward.per_task, strict=True):
        assert {f.outcome, b.outcome} in ({"x", "y"}, {"tie"})
    assert forward.ci[0] <= forward.probability <= forward.ci[1]


@pytest.mark.parametrize("runs", [3, 5, 8])
def test_each_task_reports_both_lines_iqm_within_its_interval(runs: int) -> None:
    rng = np.random.default_rng(runs)
    scores = {task: {"X": list(rng.random(runs)), "Y": list(rng.random(runs + 1))}
              for task in ("t1", "t2")}
    comparison = compare("X", "Y", scores, 400)
    assert comparison is not None
    for task in comparison.per_task:
        for label, point, ci in (("X", task.iqm_x, task.iqm_x_ci),
                                 ("Y", task.iqm_y, task.iqm_y_ci)):
            values = np.sort(scores[task.task][label])
            cut = int(0.25 * len(values))  # scipy's trim_mean: the interquartile runs
            assert point == pytest.approx(values[cut:len(values) - cut].mean())
            assert min(values) <= ci[0] <= point <= ci[1] <= max(values)


def test_the_claims_table_shows_every_claim_and_its_evidence(spec: ExperimentSpec) -> None:
    data = summary(full_grid())
    data["claims"] = judge_claims(data, spec)
    text = "\n".join(claims_section(data, "each seed's last greedy evaluation", 3))
    assert "## The paper's claims" in text
    for key in "abcde":
        assert f"| ({key}) " in text
    assert "CMAT vs MAT: 1.00 [1.00, 1.00]" in text
    assert ("| (c) | CMAT | last | smax:3m | 1.00 [1.00, 1.00] | X | 0.950 [0.900, 1.000] | "
            "0.200 [0.100, 0.300] |") in text


def test_claims_are_judged_from_the_scores_named_and_both_verdicts_are_shown(
    spec: ExperimentSpec,
) -> None:
    data = summary(full_grid())
    for task in data["tasks"]:  # the last evaluations alone tie every line
        for line in task["lines"].values():
            line["finals"] = [0.5, 0.5, 0.5]
    data["claims"] = judge_claims(data, spec)
    data["claims_from_finals"] = judge_claims(data, spec, scores="finals")
    assert by_key(data["claims"])["CMAT"]["verdict"] == SUPPORTED
    assert by_key(data["claims_from_finals"])["CMAT"]["verdict"] == TIED
    text = "\n".join(claims_section(data, "each seed's mean over the last 10%", 3))
    assert "from this grid's scores (each seed's mean over the last 10%)" in text
    start = f"| (a) {CLAIMS['a']} (CMAT) (this grid runs no PMAT, Triple-BERT, HAPPO) |"
    row = next(line for line in text.splitlines() if line.startswith(start))
    assert row.endswith(f"| {TIED} |") and f"| {SUPPORTED} | CMAT vs MAT" in row
    data.pop("claims_from_finals")
    assert "verdict from last evaluations" not in "\n".join(claims_section(data, "x", 3))


def test_a_claim_says_how_many_of_its_per_task_comparisons_are_still_missing(
    spec: ExperimentSpec,
) -> None:
    assert {coverage(claim) for claim in judge_claims(summary(full_grid()), spec)} == {""}
    grid = full_grid()
    for label in ("MAT", "m = n/2"):
        del grid["smax:2s3z"][label]
    claims = by_key(judge_claims(summary(grid), spec))
    assert coverage(claims["CMAT"]) == " (3 of 4 per-task comparisons)"
    assert coverage(claims["d"]) == " (on 1 of 2 tasks; 1 of 2 per-task comparisons)"
    assert coverage(claims["c"]) == "" and coverage(claims["e"]) == ""
    for task in ("smax:3m", "smax:2s3z"):  # a baseline with no benchmark score yet still counts
        grid[task].pop("MAPPO")
    assert coverage(by_key(judge_claims(summary(grid), spec))["CMAT"]) == (
        " (on 1 of 2 tasks; 1 of 4 per-task comparisons)")


def test_equal_scores_in_every_seed_are_tied_and_one_differing_seed_is_not(
    spec: ExperimentSpec,
) -> None:
    grid = full_grid()
    claims = by_key(judge_claims(summary(grid), spec))
    mat = next(c for c in claims["e"]["comparisons"] if c["y"] == "MAT")
    assert [t["outcome"] for t in mat["per_task"]] == ["same"]
    data = summary(grid)
    data["claims"] = judge_claims(data, spec)
    assert "| (e) | CMAT | MAT | matrix:fig1 | 0.50 [0.50, 0.50] | neither (equal scores) |" in (
        "\n".join(claims_section(data, "x", 3)))
    grid["matrix:fig1"]["MAT"] = [100.0, 100.0, 0.0]
    assert by_key(judge_claims(summary(grid), spec))["e"]["verdict"] == NOT_SEPARABLE


def test_a_claim_without_comparisons_says_what_it_needs(spec: ExperimentSpec) -> None:
    grid = {"matrix:fig1": full_grid()["matrix:fig1"]}
    data = summary(grid)
    data["claims"] = judge_claims(data, spec)
    rows = {line[3]: line for line in claims_section(data, "x", 3)
            if line.startswith("| (") and line[6] != "|"}
    assert "CMAT vs MAT: 0.50 [0.50, 0.50]" in rows["e"] and "needs" not in rows["e"]
    assert "`consensus_source: last`" in rows["c"] and "another m" in rows["d"]
    for key in "abcd":
        assert f"| {NO_DATA} | none: needs complete runs of" in rows[key]


def test_the_compute_line_counts_a_run_that_trained_in_two_places_once_overall() -> None:
    runs = [{"seconds": {"2 cores": 3600.0, "1 core": 1800.0}},
            {"seconds": {"1 core": 7200.0}}, {"seconds": {}}]
    text = compute_text({"runs": runs, "compute": compute_totals(runs)})
    assert "1.0 h on 2 cores over 1 runs; 2.5 h on 1 core over 2 runs" in text
    assert text.endswith("(2 distinct runs: a run that trained in more than one place counts "
                         "in each).")
    one_place = runs[1:]
    assert "distinct" not in compute_text({"runs": one_place,
                                           "compute": compute_totals(one_place)})
    assert compute_text({"runs": [], "compute": {}}) == ""


def test_claim_a_compares_cmat_only_with_lines_at_its_budget(tmp_path: Path) -> None:
    """A MAPPO line given 4x the budget (its variant's own `steps`) beats a CMAT line it would
    not have beaten at CMAT's budget: it is left out of CMAT's claim (a), not counted against
    it."""
    path = tmp_path / "budgets.yaml"
    path.write_text(yaml.safe_dump({
        "envs": ["smax:3m"], "algos": ["cmat", "mappo"], "steps": 1000,
        "variants": {"default": {}, "long": {"algos": ["mappo"], "steps": 4000,
                                             "label": "(long)"}},
    }))
    budgets = load_spec(path)
    lines = {label: {"variant": variant, "algo": algo, "figures": ["main"], "scores": scores,
                     "finals": scores, "iterations": 3 if algo == "cmat" else None,
                     "consensus_source": "mixture" if algo == "cmat" else None}
             for label, variant, algo, scores in (("CMAT", "default", "cmat", STRONG),
                                                  ("MAPPO", "default", "mappo", WEAK),
                                                  ("MAPPO (long)", "long", "mappo", [1.0] * 3))}
    grid = {"tasks": [{"env": "smax:3m", "label": "3m", "metric": "win_rate", "lines": lines}]}
    claim = by_key(judge_claims(grid, budgets))["CMAT"]
    assert [c["y"] for c in claim["comparisons"]] == ["MAPPO"]
    assert claim["verdict"] == SUPPORTED
