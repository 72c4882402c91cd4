"""Defaults per suite: each suite's settings resolve, are recorded with their source, and lose
to every later layer (algorithm, preset, file, command line); `cmat train --dry-run`."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from cmat.algorithms import algorithm_names, reference_defaults
from cmat.cli import main
from cmat.configfile import (
    field_names,
    from_yaml,
    layer_fields,
    read_sources,
    to_mapping,
    to_yaml,
)
from cmat.envs import probe_env
from cmat.envs.host import grf
from cmat.envs.suites import SUITES
from cmat.errors import CmatError, SuiteUnavailable
from cmat.resolve import load_config, resolve_config

IDS = {
    "matrix": "matrix:penalty", "smax": "smax:2s3z", "mpe": "mpe:simple_spread",
    "mamujoco": "mamujoco:Ant-4x2", "grf": "grf:academy_counterattack_easy",
    "pettingzoo": "pettingzoo:my_pkg.envs:make_env", "jumanji": "jumanji:rware-tiny-2ag",
    "mabrax": "mabrax:hopper_3x1", "jax": "jax:my_pkg.envs:make_env",
    "dispatch": "dispatch:grid-100-mid",
}


def value(config: object, dotted: str) -> object:
    return value_at(to_mapping(config), dotted)


def flat(settings: dict, algo: str = "cmat") -> dict[str, object]:
    """The dotted names and values of `settings` that apply to `algo`'s runs (a section named by
    another algorithm does not)."""
    own = {key: value for key, value in settings.items()
           if key == algo or key not in algorithm_names()}
    return {name: value_at(own, name) for name in layer_fields(own, algo)}


def value_at(settings: dict, dotted: str) -> object:
    outer, _, inner = dotted.partition(".")
    return settings[outer][inner] if inner else settings[outer]


@pytest.mark.unit
def test_every_suite_is_named() -> None:
    assert set(IDS) == set(SUITES)


@pytest.mark.unit
@pytest.mark.parametrize("suite", list(SUITES))
def test_a_suites_settings_resolve_with_their_source(suite: str) -> None:
    config, sources = resolve_config(overrides=[f"env={IDS[suite]}"])
    expected = flat(SUITES[suite].settings)
    assert expected, suite
    for name, setting in expected.items():
        assert value(config, name) == setting, name
        assert sources[name] == f"suite {suite}", name
    algorithm = set(flat(reference_defaults("cmat"))) - set(expected)
    assert {sources[name] for name in algorithm} <= {"algorithm cmat"}
    untouched = set(field_names()) - set(expected) - algorithm - {"env"}
    assert {sources[name] for name in untouched} == {"default"}
    for algo in set(SUITES[suite].settings) & set(algorithm_names()) - {"cmat"}:
        config, sources = resolve_config(overrides=[f"env={IDS[suite]}", f"algo={algo}"])
        own = {name: setting for name, setting in flat(SUITES[suite].settings, algo).items()
               if name.startswith(f"{algo}.")}
        assert own, algo
        for name, setting in own.items():
            assert (value(config, name), sources[name]) == (setting, f"suite {suite}"), name


@pytest.mark.parametrize("suite", ["smax", "mamujoco", "grf"])
def test_every_later_layer_beats_the_suite(suite: str, tmp_path: Path) -> None:
    """algorithm > suite; preset > algorithm; file > preset; command line > file."""
    env = f"env={IDS[suite]}"
    mappo, sources = resolve_config(overrides=[env, "algo=mappo"])
    assert (mappo.ppo.epochs, sources["ppo.epochs"]) == (5, "algorithm mappo")
    assert sources["ppo.lr"] == f"suite {suite}"
    paper, sources = resolve_config(overrides=[env, "preset=paper", "algo=mappo"])
    assert (paper.num_envs, sources["num_envs"]) == (8, "preset paper")
    file = tmp_path / "run.yaml"
    file.write_text(yaml.safe_dump({"num_envs": 6, "ppo": {"lr": 3e-4, "epochs": 7}}))
    mine, sources = resolve_config(file, [env, "preset=paper", "algo=mappo", "ppo.epochs=9"])
    assert (mine.num_envs, sources["num_envs"]) == (6, f"file {file}")
    assert (mine.ppo.lr, sources["ppo.lr"]) == (3e-4, f"file {file}")
    assert (mine.ppo.epochs, sources["ppo.epochs"]) == (9, "command line")


@pytest.mark.parametrize("overrides", [
    [], ["env=mamujoco:Hopper-3x1", "algo=happo"], ["env=smax:3m", "preset=paper"],
    ["env=matrix:fig1", "env_kwargs.payoff=[[1,2],[3,4]]", "cmat.consensus_iterations=n/2"],
    ["env=grf:academy_3_vs_1_with_keeper", "algo=mat", "ppo.target_kl=0.02", "seed=7"],
])
@pytest.mark.unit
def test_an_annotated_config_reads_back_as_the_same_config_and_sources(
    overrides: list[str],
) -> None:
    config, sources = resolve_config(overrides=overrides)
    text = to_yaml(config, sources)
    assert from_yaml(text) == config
    assert read_sources(text) == sources
    assert read_sources(to_yaml(config)) == {}


@pytest.mark.unit
def test_the_default_budget_of_each_suite() -> None:
    assert load_config(overrides=["env=matrix:fig1"]).total_steps == 4_000
    for suite in ("smax", "mamujoco", "grf", "pettingzoo", "jax"):
        assert load_config(overrides=[f"env={IDS[suite]}"]).total_steps == 10_000_000


def test_dry_run_prints_the_resolved_config_and_starts_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    argv = ["train", "--env", "smax:3m", "--algo", "mat", "--dry-run", "--set", "ppo.lr=1e-4"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "  lr: 0.0001  # command line" in out
    assert "  epochs: 15  # suite smax" in out
    assert "  per_agent_gae: true  # algorithm mat" in out
    assert "# smax:3m: 3 agents" in out and "8 discrete actions" in out
    config_text = out[:out.rindex("# smax:3m")]
    assert from_yaml(config_text) == load_config(overrides=["env=smax:3m", "algo=mat",
                                                            "ppo.lr=1e-4"])
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("env, message", [
    ("smax:3mm", "unknown SMAX scenario '3mm'"),
    ("nope:x", "unknown environment prefix 'nope'"),
    ("matrix", "unknown matrix game ''"),
])
def test_dry_run_rejects_an_environment_it_cannot_build(
    env: str, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["train", "--env", env, "--dry-run"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], captured.err


@pytest.mark.parametrize("env, options, message", [
    ("nope:x", {}, "unknown environment prefix 'nope'"),
    ("smax:3s5zz", {}, "unknown SMAX scenario '3s5zz'"),
    ("smax:0m", {}, "Nm (N marines a side, 1 <= N <= 999)"),
    ("smax:1000m", {}, "unknown SMAX scenario '1000m'"),
    ("matrix:fig2", {}, "unknown matrix game 'fig2'"),
    ("matrix:penalty", {"payoff": 3}, "unknown option 'payoff'"),
    ("matrix:fig1", {"payoff": 3}, "payoff"),
    ("mpe:simple_spreadd", {}, "unknown MPE environment 'simple_spreadd'"),
    ("mamujoco:Cheetah-2x3", {}, "unknown MaMuJoCo scenario 'Cheetah'"),
    ("mamujoco:HalfCheetah-7x1", {}, "unknown MaMuJoCo factorization '7x1'"),
    ("grf:academy_4_vs_1", {}, "unknown GRF scenario 'academy_4_vs_1'"),
    ("host:x", {}, "unknown environment prefix 'host'"),
])
def test_an_environment_wrong_on_any_machine_is_an_error_wherever_it_is_probed(
    env: str, options: dict, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(CmatError, match=re.escape(message)):
        probe_env(env, options)
    settings = [f"--set=env_kwargs.{k}={v}" for k, v in options.items()]
    assert main(["config", "--check-env", "--env", env, *settings]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert captured.out == "" and len(lines) == 1 and message in lines[0], captured.err


def test_a_known_environment_whose_suite_is_missing_is_unavailable_not_unknown(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def missing_suite() -> None:
        raise SuiteUnavailable("GRF needs gfootball (No module named 'gfootball')")

    monkeypatch.setattr(grf, "import_gfootball", missing_suite)
    assert probe_env("grf:academy_3_vs_1_with_keeper", {}) == (
        None, "GRF needs gfootball (No module named 'gfootball')")
    assert probe_env("matrix:fig1", {}) == (2, None)
    assert main(["config", "--check-env", "--env", "grf:academy_3_vs_1_with_keeper"]) == 0
    out = capsys.readouterr().out
    assert "ppo.epochs = " in out
    assert out.splitlines()[-1] == ("# grf:academy_3_vs_1_with_keeper cannot be built on this "
                                    "machine: GRF needs gfootball (No module named 'gfootball')")


def test_dry_run_of_a_resume_prints_the_runs_config_and_trains_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    run.mkdir()
    config, sources = resolve_config(overrides=["env=matrix:fig1", "seeds=2"])
    (run / "config.yaml").write_text(to_yaml(config, sources))
    before = (run / "config.yaml").read_bytes()
    assert main(["train", "--resume", str(run), "--steps", "8000", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "total_steps: 8000  # command line (--resume --steps)" in out
    assert "seeds: 2  # command line" in out and "# matrix:fig1: 2 agents" in out
    assert (run / "config.yaml").read_bytes() == before
    assert sorted(path.name for path in run.iterdir()) == ["config.yaml"]
