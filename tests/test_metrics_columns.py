"""Every metric a run emits reaches metrics.csv: each algorithm's own (CMAT's consensus entropy,
PMAT's order term, HAPPO's critic norm, per-block gradient norms…), and a metric that first
appears after the header was written. CMAT runs with a categorical consensus, the setting under
which it emits the consensus entropy."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from cmat.algorithms import algorithm_names
from cmat.cli import main
from cmat.rundir import Row, RunDir

pytestmark = pytest.mark.quick_compiles


OWN_METRICS = ("cmat", "pmat", "happo", "sable")
"""The algorithms whose losses emit metrics of their own (consensus entropy, order term,
per-agent phases, sequences), run in the fast suite; the others emit MAPPO's or MAT's set and
run in the slow suite (15-25 s each on 2 cores, nearly all compiling)."""


@pytest.mark.parametrize("algo", [
    pytest.param(algo, marks=[] if algo in OWN_METRICS else pytest.mark.slow)
    for algo in algorithm_names()
])
def test_every_emitted_metric_reaches_metrics_csv(
    algo: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    emitted: list[Row] = []
    append = RunDir.append_metrics

    def recording(self: RunDir, rows: list[Row]) -> None:
        emitted.extend(rows)
        append(self, rows)

    monkeypatch.setattr(RunDir, "append_metrics", recording)
    out = tmp_path / "run"
    own = ["cmat.consensus_policy=categorical"] if algo == "cmat" else []
    assert main(["train", "--env", "matrix:fig1", "--algo", algo, "--steps", "100",
                 "--out", str(out), "--set", "num_envs=2", "rollout_length=25",
                 "log_interval=1", "ppo.epochs=1", "network.n_embd=8", "eval_episodes=2",
                 *own]) == 0
    written = list(csv.DictReader((out / "metrics.csv").open()))
    assert len(written) == len(emitted) and {row["kind"] for row in written} >= {"train", "eval"}
    for sent, row in zip(emitted, written, strict=True):
        missing = set(sent) - set(row)
        assert not missing, f"{algo} emits {sorted(missing)} that metrics.csv lacks"
        for key, value in sent.items():
            if isinstance(value, float):
                assert float(row[key]) == pytest.approx(value, nan_ok=True), key
            else:
                assert row[key] == str(value), key
    names = set(written[0])
    if algo == "cmat":
        assert "consensus_entropy" in names
    if algo == "pmat":
        assert any("order" in name for name in names), sorted(names)


@pytest.mark.unit
def test_a_metric_that_appears_later_widens_the_header(tmp_path: Path) -> None:
    run = RunDir(tmp_path)
    run.append_metrics([{"kind": "train", "seed": 0, "env_steps": 10, "loss": 1.5}])
    run.append_metrics([{"kind": "train", "seed": 0, "env_steps": 20, "loss": 1.0,
                         "epochs_run": 3.0}])
    rows = run.read_metrics()
    assert run.metrics_header()[-1] == "epochs_run"
    assert [(row["env_steps"], row["loss"], row["epochs_run"]) for row in rows] == [
        ("10", "1.5", ""), ("20", "1.0", "3.0")]
