"""The classical dispatch baselines as lines of an experiment: evaluated per seed on the task's
evaluation episodes and options, in the scores and statistics beside the learned lines, with
the environment's metrics per line, and reused from disk while their setting holds."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml

from cmat.cli import main
from cmat.envs.dispatch.baselines import baseline_env, evaluate_means

pytestmark = pytest.mark.quick_compiles

OPTIONS = {"grid_size": 3, "episode_minutes": 10}
SPEC = {
    "name": "fleet", "steps": 120, "seeds": 2,
    "set": ["env_kwargs.grid_size=3", "env_kwargs.episode_minutes=10", "num_envs=2",
            "rollout_length=10", "eval_episodes=3"],
    "envs": [{"id": "dispatch:grid-6-high", "label": "small fleet"}],
    "algos": ["mappo"], "baselines": ["random", "hungarian"], "bootstrap_reps": 200,
}


@pytest.fixture(scope="module")
def grid(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("fleet")
    (root / "spec.yaml").write_text(yaml.safe_dump(SPEC))
    assert main(["experiment", str(root / "spec.yaml"), "--out", str(root / "out"),
                 "--parallel", "1"]) == 0
    return root / "out"


def test_baselines_are_lines_scored_per_seed(grid: Path) -> None:
    summary = json.loads((grid / "results.json").read_text())
    lines = summary["tasks"][0]["lines"]
    assert list(lines) == ["MAPPO", "random (legal)", "Hungarian"]
    env = baseline_env("dispatch:grid-6-high", OPTIONS)
    for name, label in (("random", "random (legal)"), ("hungarian", "Hungarian")):
        expected = [evaluate_means(env, name, 3, seed) for seed in (0, 1)]
        assert lines[label]["scores"] == pytest.approx(
            [e["episode_return"] for e in expected], rel=1e-6)
        assert lines[label]["metrics"]["service_rate"] == pytest.approx(
            sum(e["service_rate"] for e in expected) / 2, rel=1e-6)
    assert lines["Hungarian"]["metrics"]["conflicts_per_step"] == 0
    assert 0 < lines["MAPPO"]["metrics"]["service_rate"] <= 1
    assert set(summary["aggregate"]["lines"]) == set(lines)
    table = (grid / "results.md").read_text()
    assert "| MAPPO | random (legal) | Hungarian |" in table
    assert "## Environment metrics" in table and "service_rate" in table


def test_a_second_report_reuses_the_baselines_until_their_setting_changes(
        grid: Path, tmp_path: Path) -> None:
    saved = grid / "baselines" / "dispatch_grid-6-high" / "hungarian.json"
    data = json.loads(saved.read_text())
    data["rows"][0]["episode_return"] = "1234.5"
    saved.write_text(json.dumps(data))
    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump(SPEC))
    assert main(["experiment", str(spec), "--out", str(grid), "--report-only"]) == 0
    lines = json.loads((grid / "results.json").read_text())["tasks"][0]["lines"]
    assert lines["Hungarian"]["scores"][0] == 1234.5
    data["setting"]["episodes"] = 99
    saved.write_text(json.dumps(data))
    assert main(["experiment", str(spec), "--out", str(grid), "--report-only"]) == 0
    lines = json.loads((grid / "results.json").read_text())["tasks"][0]["lines"]
    assert lines["Hungarian"]["scores"][0] != 1234.5
    assert json.loads(saved.read_text())["setting"]["episodes"] == 3


def test_an_export_takes_the_baselines_evaluations_along(
        grid: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump(SPEC))
    assert main(["experiment", str(spec), "--out", str(grid), "--report-only"]) == 0

    def evaluated_again(*_: object) -> None:
        raise AssertionError("the export evaluated a baseline again")

    monkeypatch.setattr("cmat.envs.dispatch.baselines.evaluate_means", evaluated_again)
    exported = tmp_path / "committed"
    assert main(["experiment", str(spec), "--out", str(grid), "--report-only",
                 "--export", str(exported)]) == 0
    for name in ("random", "hungarian"):
        saved = Path("baselines") / "dispatch_grid-6-high" / f"{name}.json"
        assert (exported / saved).read_bytes() == (grid / saved).read_bytes()
    lines = json.loads((exported / "results.json").read_text())["tasks"][0]["lines"]
    assert lines["Hungarian"] == json.loads(
        (grid / "results.json").read_text())["tasks"][0]["lines"]["Hungarian"]

    not_trained = tmp_path / "not_trained"
    shutil.copytree(grid / "baselines", not_trained / "baselines")
    assert main(["experiment", str(spec), "--out", str(not_trained), "--report-only",
                 "--export", str(tmp_path / "baselines_only")]) == 0
    lines = json.loads((tmp_path / "baselines_only" / "results.json").read_text())[
        "tasks"][0]["lines"]
    assert list(lines) == ["random (legal)", "Hungarian"]
