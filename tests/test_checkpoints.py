"""The checkpoints a run keeps (cmat.runners.checkpoints): each seed's best, periodic ones with
their retention rule, the best policy's absolute evaluation, and `--checkpoint` everywhere."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import jax
import numpy as np
import pytest

import cmat
from cmat.cli import main
from cmat.experiments.marl_eval import runs_of
from cmat.rundir import RunDir

pytestmark = pytest.mark.quick_compiles

SETTINGS = ["num_envs=4", "rollout_length=25", "ppo.epochs=1", "log_interval=1",
            "network.n_embd=16", "eval_episodes=4", "eval_actions=sample"]
"""Fig. 1 with sampled evaluation: each seed's evaluated return moves from chunk to chunk."""


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("checkpoints") / "fig1"
    assert main(["train", "--env", "matrix:fig1", "--steps", "1000", "--seeds", "3",
                 "--out", str(out), "--set", *SETTINGS, "checkpoint_interval=100",
                 "keep_checkpoints=0"]) == 0
    return out


def evaluations(out: Path) -> dict[int, list[tuple[int, float]]]:
    by_seed: dict[int, list[tuple[int, float]]] = {}
    for row in RunDir(out).read_metrics():
        if row["kind"] == "eval":
            by_seed.setdefault(int(row["seed"]), []).append(
                (int(row["env_steps"]), float(row["episode_return"])))
    return by_seed


def seed_params(out: Path, checkpoint: str | int, seed: int) -> list[np.ndarray]:
    return [np.asarray(leaf) for leaf in
            jax.tree.leaves(cmat.load_policy(out, seed, checkpoint).params)]


def test_best_holds_each_seeds_parameters_at_its_best_evaluation(run: Path) -> None:
    header = RunDir(run).checkpoint_header("best")
    assert header is not None and header["best"]["metric"] == "episode_return"
    for seed, rows in evaluations(run).items():
        best_steps, best_score = max(rows, key=lambda row: (row[1], -row[0]))
        assert header["best"]["env_steps"][seed] == best_steps
        assert header["best"]["scores"][seed] == pytest.approx(best_score)
        assert cmat.load_policy(run, seed, "best").env_steps == best_steps
        for best, periodic in zip(seed_params(run, "best", seed),
                                  seed_params(run, best_steps, seed)):
            np.testing.assert_array_equal(best, periodic)
    assert len(set(header["best"]["env_steps"])) > 1, "the seeds should peak at other steps"


def test_periodic_checkpoints_and_their_retention(run: Path, tmp_path: Path) -> None:
    assert RunDir(run).checkpoints() == ["latest", "best", *range(100, 1001, 100)]
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    assert main(["train", "--resume", str(copy), "--steps", "1600"]) == 0
    assert RunDir(copy).periodic_checkpoints() == [*range(100, 1601, 100)]
    other = tmp_path / "kept"
    assert main(["train", "--env", "matrix:fig1", "--steps", "700", "--out", str(other),
                 "--set", *SETTINGS, "checkpoint_interval=200", "keep_checkpoints=2"]) == 0
    assert RunDir(other).checkpoints() == ["latest", "best", 400, 600]


def test_a_complete_run_evaluates_its_best_checkpoint_on_ten_times_the_episodes(
    run: Path,
) -> None:
    rows = [row for row in RunDir(run).read_metrics() if row["kind"] == "absolute"]
    header = RunDir(run).checkpoint_header("best")
    assert header is not None
    assert [int(row["seed"]) for row in rows] == [0, 1, 2]
    assert all(int(row["env_steps"]) == 1000 for row in rows)
    assert [int(float(row["best_env_steps"])) for row in rows] == header["best"]["env_steps"]
    marl = runs_of(RunDir(run).read_metrics())
    for row in rows:
        absolute = marl[row["seed"]]["absolute_metrics"]
        assert absolute["episode_return"] == [float(row["episode_return"])]


def test_checkpoint_option_of_eval_render_finetune_and_the_api(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["eval", "--run", str(run), "--checkpoint", "best", "--episodes", "2"]) == 0
    result = json.loads(capsys.readouterr().out)
    header = RunDir(run).checkpoint_header("best")
    assert header is not None
    assert result["checkpoint"] == "best"
    assert result["best_env_steps"] == header["best"]["env_steps"]
    assert main(["eval", "--run", str(run), "--checkpoint", "300", "--episodes", "2"]) == 0
    assert json.loads(capsys.readouterr().out)["env_steps"] == 300
    assert main(["eval", "--run", str(run), "--checkpoint", "350"]) == 2
    error = capsys.readouterr().err
    assert "no checkpoint 350" in error and "latest, best, 100, 200" in error
    assert main(["finetune", "--from", str(run), "--checkpoint", "best", "--mode", "action",
                 "--steps", "100", "--out", str(tmp_path / "tuned")]) == 0
    assert "best checkpoint" in capsys.readouterr().err
    frame = cmat.open_run(run).evaluate(episodes=2, checkpoint=200)
    assert frame.attrs["env_steps"] == 200 and frame.attrs["checkpoint"] == 200
    assert cmat.open_run(run).checkpoints[:2] == ["latest", "best"]


def test_a_run_without_a_best_checkpoint_starts_one_when_resumed(
    run: Path, tmp_path: Path
) -> None:
    copy = tmp_path / "old"
    shutil.copytree(run, copy)
    for path in (copy / "checkpoints").glob("*.ckpt"):
        if path.name != "latest.ckpt":
            path.unlink()
    with pytest.raises(cmat.CmatError, match="no checkpoint 'best'"):
        cmat.load_policy(copy, 0, "best")
    assert main(["train", "--resume", str(copy), "--steps", "1200"]) == 0
    header = RunDir(copy).checkpoint_header("best")
    assert header is not None and min(header["best"]["env_steps"]) >= 1100
