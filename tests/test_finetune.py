"""Fine-tuning freezes exactly the paper's blocks; m as n/2, 2n; `cmat eval --iterations K`."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pytest
import yaml

from cmat.algorithms.cmat.algorithm import CMAT
from cmat.algorithms.cmat.blocks import CMAT_BLOCKS, FINETUNE_TRAINABLE, with_iterations
from cmat.algorithms.cmat.network import ConsensusDecoder
from cmat.algorithms.cmat.options import (
    LARGE_TEAM,
    LARGE_TEAM_ITERATIONS,
    CMATOptions,
    resolve_iterations,
)
from cmat.cli import main
from cmat.config import NetworkConfig
from cmat.configfile import CONFIG_LAYOUT
from cmat.envs.protocol import EnvSpec
from cmat.networks.layers import Compressor
from cmat.resolve import load_config
from cmat.rundir import RunDir
from cmat.runners.trainer import JaxTrainer

pytestmark = pytest.mark.quick_compiles

TINY = ["num_envs=4", "rollout_length=25", "log_interval=5", "ppo.epochs=2", "eval_episodes=4"]
BASE = ["train", "--env", "matrix:fig1", "--steps", "500", "--seeds", "2", "--set", *TINY]


def one_error_line(stderr: str) -> str:
    assert "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cmat: error: "), stderr
    return lines[0]


def params_of(run: Path) -> Any:
    run_dir = RunDir.open(run)
    return JaxTrainer(run_dir.config()).from_bytes(
        run_dir.load_checkpoint()[0]).learner.params["params"]


def leaves(block: Any) -> list[np.ndarray]:
    return [np.asarray(leaf) for leaf in jax.tree.leaves(block)]


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("finetune") / "base"
    assert main([*BASE, "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def finetuned(base: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Both stages from `base`, 500 steps each (action with a changed learning rate)."""
    runs = {}
    for mode, extra in (("consensus", []), ("action", ["--set", "ppo.lr=1e-3"])):
        runs[mode] = tmp_path_factory.mktemp("stage") / mode
        assert main(["finetune", "--from", str(base), "--mode", mode, "--steps", "500",
                     "--out", str(runs[mode]), *extra]) == 0
    return runs


@pytest.mark.parametrize("mode", ["consensus", "action"])
def test_finetuning_trains_exactly_the_named_blocks(
    base: Path, finetuned: dict[str, Path], mode: str
) -> None:
    out = finetuned[mode]
    config = RunDir.open(out).config()
    assert (config.finetune, config.finetune_from, config.total_steps) == (mode, str(base), 500)
    recorded = yaml.safe_load((out / "config.yaml").read_text())
    assert recorded["finetune"] == mode and recorded["finetune_from"] == str(base)
    sources = RunDir.open(out).sources()
    assert sources["finetune"] == sources["total_steps"] == "cmat finetune"
    assert sources["env"] == "command line" and sources["ppo.clip_eps"] == "default"
    assert sources["ppo.lr"] == ("command line" if mode == "action" else "default")
    assert RunDir.open(out).load_checkpoint()[1] == 500
    assert {r["env_steps"] for r in RunDir.open(out).read_metrics()} == {"500"}

    before, after = params_of(base), params_of(out)
    assert set(before) == set(after) == set(CMAT_BLOCKS) - {"latent_consensus"}
    for name in before:
        pairs = list(zip(leaves(before[name]), leaves(after[name]), strict=True))
        if name in FINETUNE_TRAINABLE[mode]:
            changed = [not np.array_equal(b, a) for b, a in pairs if b.size]
            assert all(changed), f"{name}: a trainable leaf did not change ({mode})"
        else:
            for b, a in pairs:
                assert b.tobytes() == a.tobytes(), f"{name}: a frozen leaf changed ({mode})"


def test_resumed_finetuning_keeps_its_mask(
    base: Path, finetuned: dict[str, Path], tmp_path: Path
) -> None:
    out = Path(shutil.copytree(finetuned["action"], tmp_path / "ft"))
    assert RunDir.open(out).config().ppo.lr == 1e-3
    assert main(["train", "--resume", str(out), "--steps", "1000"]) == 0
    before, after = params_of(base), params_of(out)
    for name in ("encoder", "critic_compressor", "decoder", "actor_compressor"):
        assert all(b.tobytes() == a.tobytes()
                   for b, a in zip(leaves(before[name]), leaves(after[name])))


def as_algorithm(config: dict, algo: str) -> str:
    """A CMAT run's config.yaml contents made another algorithm's (`algo` set, CMAT's section
    replaced by the other algorithm's defaults), as config.yaml text of today's layout."""
    if algo != "cmat":
        config = {**{k: v for k, v in config.items() if k != "cmat"}, "algo": algo, algo: {}}
    return f"# config layout {CONFIG_LAYOUT}\n" + yaml.safe_dump(config)


@pytest.mark.parametrize(
    ("edit", "args", "message"),
    [
        ({"algo": "mat"}, [], "is supported only for algo cmat, got 'mat'"),
        ({}, ["--set", "network.n_embd=32"], "fine-tuning cannot change network"),
        ({}, ["--set", "cmat.compressor_heads=2"],
         "fine-tuning cannot change cmat.compressor_heads"),
        ({}, ["--set", "seeds=3"], "fine-tuning cannot change seeds"),
        ({}, ["--set", "algo=mat"], "fine-tuning cannot change algo"),
        ({}, ["--set", "finetune=consensus"], "--set finetune: a fine-tuning stage is named by"),
        ({}, ["--steps", "0"], "--steps must be > 0"),
    ],
)
def test_bad_finetuning_is_one_error_line(
    base: Path, tmp_path: Path, edit: dict, args: list[str], message: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    source = Path(shutil.copytree(base, tmp_path / "source"))
    config = yaml.safe_load((source / "config.yaml").read_text())
    edited = {**config, **edit}
    (source / "config.yaml").write_text(as_algorithm(edited, edited["algo"]))
    out = tmp_path / "out"
    assert main(["finetune", "--from", str(source), "--mode", "action", "--out", str(out),
                 *args]) == 2
    assert message in one_error_line(capsys.readouterr().err)
    assert not out.exists()


def test_finetune_setting_is_cmat_only(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["train", "--env", "matrix:fig1", "--algo", "mat", "--set", "finetune=action",
                 "--out", str(tmp_path / "x")]) == 2
    assert "supported only for algo cmat" in one_error_line(capsys.readouterr().err)
    assert main(["train", "--env", "matrix:fig1", "--set", "finetune=all",
                 "--out", str(tmp_path / "x")]) == 2
    assert "finetune must be one of consensus, action" in one_error_line(capsys.readouterr().err)


@pytest.mark.parametrize(("m", "expected"), [(None, 6), ("n", 6), ("n/2", 3), ("2n", 12), (4, 4)])
def test_iterations_relative_to_the_number_of_agents(m: object, expected: int) -> None:
    assert resolve_iterations(m, 6) == expected
    assert resolve_iterations("n/2", 5) == 2


@pytest.mark.parametrize(("m", "agents", "expected"), [
    (None, LARGE_TEAM, LARGE_TEAM), (None, LARGE_TEAM + 1, LARGE_TEAM_ITERATIONS),
    (None, 1000, LARGE_TEAM_ITERATIONS), ("n", 1000, 1000), (64, 1000, 64),
])
def test_large_teams_default_to_a_fixed_m(m: object, agents: int, expected: int) -> None:
    """Unset m is n up to LARGE_TEAM agents and LARGE_TEAM_ITERATIONS above; an m set
    explicitly ('n' as in --preset paper, or a number) is kept at any size."""
    assert resolve_iterations(m, agents) == expected
    assert load_config(overrides=["preset=paper"]).options.consensus_iterations == "n"


@pytest.mark.parametrize("value", ["n/2", "2n", "n", "0", "7"])
def test_iterations_parse_from_overrides(value: str) -> None:
    config = load_config(overrides=[f"cmat.consensus_iterations={value}"])
    assert config.options.consensus_iterations == (int(value) if value.isdigit() else value)


def test_bad_iterations_are_one_error_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["train", "--env", "matrix:fig1", "--set", "cmat.consensus_iterations=3n",
                 "--out", str(tmp_path / "x")]) == 2
    assert "must be >= 0, got '3n' (or one of n, n/2, 2n" in one_error_line(capsys.readouterr().err)


@pytest.mark.parametrize("source", ["mixture", "last"])
def test_stopping_the_refinement_early_equals_the_first_iterations(source: str) -> None:
    spec = EnvSpec("test", 2, 5, 3, True, 10, False)
    network_config = NetworkConfig(n_embd=16)
    options = CMATOptions(consensus_iterations="2n", consensus_source=source)
    full = CMAT.build(network_config, spec, options=options).network
    obs = jax.random.normal(jax.random.PRNGKey(1), (2, 2, 5))
    mask = np.ones((2, 2, 3), bool)
    params = jax.jit(full.init)(jax.random.PRNGKey(0), obs, mask)
    _, captured = jax.jit(lambda p: full.apply(
        p, obs, mask,
        capture_intermediates=lambda module, _: isinstance(module, ConsensusDecoder),
        mutable=["intermediates"],
    ))(params)
    vectors = captured["intermediates"]["decoder"]["__call__"][0]
    assert vectors.shape == (2, 5, 16)
    for k in (0, 1, 4):
        short = CMAT.build(network_config, spec,
                           options=dataclasses.replace(options, consensus_iterations=k))
        output = jax.jit(short.network.apply)(with_iterations(params, k), obs, mask)
        expected = vectors[:, k] if source == "last" else Compressor(16, 4, 16).apply(
            {"params": params["params"]["actor_compressor"]}, vectors[:, : k + 1]
        )
        np.testing.assert_allclose(output.consensus, expected, rtol=1e-5, atol=1e-6)
    with pytest.raises(Exception, match="exceeds the m = 4"):
        with_iterations(params, 5)


def test_eval_iterations_override(base: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "--run", str(base), "--episodes", "4"]) == 0
    trained = json.loads(capsys.readouterr().out)
    assert trained["consensus_iterations"] == 2
    assert main(["eval", "--run", str(base), "--episodes", "4", "--iterations", "2"]) == 0
    assert json.loads(capsys.readouterr().out) == trained
    for k in (0, 1):
        assert main(["eval", "--run", str(base), "--episodes", "4", "--iterations", str(k)]) == 0
        result = json.loads(capsys.readouterr().out)
        assert result["consensus_iterations"] == k and len(result["per_seed"]) == 2
    assert main(["eval", "--run", str(base), "--iterations", "3"]) == 2
    assert "--iterations must be in 0..2" in one_error_line(capsys.readouterr().err)


def test_eval_iterations_is_cmat_only(
    base: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    source = Path(shutil.copytree(base, tmp_path / "mat"))
    config = yaml.safe_load((source / "config.yaml").read_text())
    (source / "config.yaml").write_text(as_algorithm(config, "mat"))
    assert main(["eval", "--run", str(source), "--iterations", "1"]) == 2
    assert "--iterations applies to cmat runs only" in one_error_line(capsys.readouterr().err)
