"""The Python API (cmat.api): `cmat.train` resolves and checks what `cmat train` does, learns,
and gives its run's metrics, evaluation and policy; `cmat.experiment` reports a grid."""

import shutil
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest

import cmat
from cmat.resolve import nested

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.quick_compiles


def test_import_needs_no_jax_and_exports_the_api() -> None:
    code = ("import sys, cmat; [getattr(cmat, name) for name in ('train', 'Run', 'open_run', "
            "'experiment', 'Experiment')]; print('jax' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            check=True)
    assert result.stdout.strip() == "False"
    assert set(cmat.__all__) >= {"train", "open_run", "Run", "experiment", "load_policy"}


def test_version_is_one_number_everywhere() -> None:
    result = subprocess.run([sys.executable, "-m", "cmat", "--version"], capture_output=True,
                            text=True, check=True)
    assert result.stdout.strip() == f"cmat {cmat.__version__}"
    assert version("cmat-marl") == cmat.__version__


def test_nested_settings() -> None:
    assert nested({"num_envs": 4, "ppo.lr": 1e-3, "ppo": {"epochs": 2}, "network.n_head": 2}) == {
        "num_envs": 4, "ppo": {"lr": 1e-3, "epochs": 2}, "network": {"n_head": 2}}
    with pytest.raises(cmat.CmatError, match="a section"):
        nested({"ppo": 3, "ppo.lr": 1e-3})


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> cmat.Run:
    out = tmp_path_factory.mktemp("api") / "fig1"
    return cmat.train(env="matrix:fig1", algo="cmat", steps=1600, seeds=2, out=out,
                      num_envs=8, ppo={"lr": 1e-3}, **{"network.n_embd": 32})


def test_train_layers_arguments_over_the_algorithm(trained: cmat.Run) -> None:
    config = trained.config
    assert (config.env, config.seeds, config.num_envs) == ("matrix:fig1", 2, 8)
    assert config.ppo.lr == 1e-3 and config.network.n_embd == 32
    assert trained.sources["ppo.lr"] == "arguments"
    assert trained.sources["ppo.epochs"] != "arguments"
    assert trained.complete and trained.env_steps == config.budget_steps


def test_train_learns_and_metrics_are_a_frame(trained: cmat.Run) -> None:
    metrics = trained.metrics
    evaluations = metrics[metrics["kind"] == "eval"]
    assert sorted(evaluations["seed"].unique()) == [0, 1]
    assert evaluations["env_steps"].max() == trained.config.budget_steps
    last = evaluations[evaluations["env_steps"] == evaluations["env_steps"].max()]
    # Fig. 1's optimum is 100 for the team, a miscoordinated pair gets at most 10.
    assert (last["episode_return"] > 50).all(), last


def test_evaluate_and_policy(trained: cmat.Run) -> None:
    frame = trained.evaluate(episodes=4, seed=5)
    assert list(frame["seed"]) == [0, 1]
    assert frame.attrs["episode_seed"] == 5 and frame.attrs["episodes_per_seed"] == 4
    assert np.isnan(frame["win_rate"]).all() and (frame["episode_return"] > 50).all()
    policy = trained.policy(seed=1)
    assert policy.seed == 1
    obs = np.zeros((policy.spec.num_agents, policy.spec.obs_dim), np.float32)
    assert np.asarray(policy.greedy(obs)).shape == (policy.spec.num_agents,)
    with pytest.raises(cmat.CmatError, match="episodes"):
        trained.evaluate(episodes=0)
    with pytest.raises(cmat.CmatError, match="actions"):
        trained.evaluate(actions="best")


def test_user_errors_are_one_line_exceptions(trained: cmat.Run, tmp_path: Path) -> None:
    problems = [
        (dict(env="matrix:fig1", out=trained.path), "already holds a run"),
        (dict(env="matrix:fig1", ppo={"lrx": 1.0}), "unknown key ppo.lrx"),
        (dict(env="matrix:fig1", num_envs="many"), "num_envs: expected an integer"),
        (dict(env="matrix:fig1", preset="fastest"), "unknown preset 'fastest'"),
        (dict(resume=trained.path, seeds=3), "resume takes no other option"),
        (dict(env="nowhere:3m", out=tmp_path / "new"), "nowhere"),
    ]
    for kwargs, message in problems:
        with pytest.raises(cmat.CmatError, match=message) as caught:
            cmat.train(**kwargs)  # type: ignore[arg-type]
        assert "\n" not in str(caught.value)
    assert not (tmp_path / "new").exists()
    with pytest.raises(cmat.CmatError, match="no run"):
        cmat.open_run(tmp_path)


def test_experiment_reports_a_grid(tmp_path: Path) -> None:
    exported = REPO / "experiments" / "results" / "dispatch"
    out = tmp_path / "dispatch"
    shutil.copytree(exported, out, ignore=shutil.ignore_patterns("*.png", "*.md"))
    result = cmat.experiment(out / "spec.yaml", out=out, report_only=True)
    assert result.report.is_file() and (out / "figure_main.png").is_file()
    assert result.results["name"] == "dispatch" and "claims" not in result.results
    assert "The paper's claims" not in result.report.read_text()  # the spec asks for none
    runs = result.runs
    assert "dispatch_grid-100-mid/default/cmat-s0-2" in runs
    assert runs["dispatch_grid-100-mid/default/cmat-s0-2"].config.algo == "cmat"
