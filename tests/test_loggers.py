"""Loggers: Weights & Biases runs offline into the run directory unless the user asked for
online logging, and receives the same scalars as TensorBoard; an unknown logger is one error."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from cmat.cli import main
from cmat.rundir import RunDir
from cmat.runners import loop

pytestmark = pytest.mark.quick_compiles


def test_wandb_logs_offline_into_the_run_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("wandb")
    for name in ("WANDB_MODE", "WANDB_API_KEY", "WANDB_PROJECT"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("WANDB_BASE_URL", "http://127.0.0.1:9")  # nothing listens: no upload
    logged: list[tuple[int, dict[str, float]]] = []
    flush = loop.WandbWriter.flush

    def recording_flush(self: Any) -> None:
        logged.extend((step, dict(values)) for step, values in self.pending.items())
        flush(self)

    monkeypatch.setattr(loop.WandbWriter, "flush", recording_flush)
    out = tmp_path / "run"
    assert main(["train", "--env", "matrix:fig1", "--steps", "800", "--out", str(out),
                 "--set", "logger=wandb", "log_interval=1", "algo=mappo"]) == 0

    offline = list((out / "wandb").glob("offline-run-*/run-*.wandb"))
    assert len(offline) == 1 and offline[0].stat().st_size > 0
    assert not list((out / "wandb").glob("run-*"))  # no online run
    evaluations = {int(r["env_steps"]): float(r["episode_return"])
                   for r in RunDir(out).read_metrics() if r["kind"] == "eval"}
    assert [step for step, _ in logged] == sorted(evaluations) == [400, 800]
    for step, values in logged:
        assert values["eval/episode_return/seed_0"] == pytest.approx(evaluations[step])
        assert "losses/policy_loss/seed_0" in values and "charts/steps_per_second" in values
    assert RunDir(out).config().logger == "wandb"


def test_an_unknown_logger_is_one_error_line(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["train", "--env", "matrix:fig1", "--out", str(tmp_path / "r"),
                 "--set", "logger=mlflow"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert error == ["cmat: error: invalid config: logger must be one of tensorboard, wandb, "
                     "got 'mlflow'"]
    assert not (tmp_path / "r").exists()
