"""`cmat train | eval | plot` end to end with the real trainer on a tiny matrix-game budget."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_rundir import lock_held_elsewhere

from cmat.cli import main
from cmat.config import load_yaml, validate
from cmat.resolve import load_config
from cmat.rundir import RunDir
from cmat.runners.base import TrainerState
from cmat.runners.trainer import JaxTrainer

pytestmark = pytest.mark.quick_compiles

TINY = ["num_envs=4", "rollout_length=25", "log_interval=5", "ppo.epochs=2", "eval_episodes=4"]
TRAIN = ["train", "--env", "matrix:fig1", "--steps", "2000", "--seeds", "2", "--set", *TINY]
CHUNK_STEPS = 500
SEEDS = (0, 1)


def rows(run: Path) -> list[dict[str, str]]:
    with (run / "metrics.csv").open(newline="") as file:
        return list(csv.DictReader(file))


def snapshot(path: Path) -> dict[str, bytes]:
    """Every file under `path` with its bytes."""
    return {str(f.relative_to(path)): f.read_bytes() for f in path.rglob("*") if f.is_file()}


def one_error_line(stderr: str) -> str:
    """The single `cmat: error:` line a failing command must print, and nothing else."""
    assert "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cmat: error: "), stderr
    return lines[0]


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cli") / "run"
    assert main([*TRAIN, "--out", str(out)]) == 0
    return out


@pytest.fixture
def run_copy(trained: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(trained, tmp_path / "run"))


def test_train_writes_a_complete_run_directory(trained: Path) -> None:
    expected = validate(dataclasses.replace(
        load_config(overrides=TINY), env="matrix:fig1", total_steps=2000, seeds=2
    ))
    assert RunDir.open(trained).config() == expected
    sources = RunDir.open(trained).sources()
    assert sources["env"] == sources["ppo.epochs"] == sources["total_steps"] == "command line"
    assert sources["ppo.lr"] == "default" and sources["ppo.target_tau"] == "algorithm cmat"

    written = rows(trained)
    chunks = range(CHUNK_STEPS, 2000 + 1, CHUNK_STEPS)
    for kind in ("train", "eval"):
        keys = sorted((int(r["seed"]), int(r["env_steps"])) for r in written if r["kind"] == kind)
        assert keys == sorted((seed, steps) for seed in SEEDS for steps in chunks)
    assert {r["kind"] for r in written} == {"train", "eval", "absolute"}
    absolute = [r for r in written if r["kind"] == "absolute"]
    assert sorted(int(r["seed"]) for r in absolute) == list(SEEDS)
    assert all(int(r["env_steps"]) == 2000 and r["best_env_steps"] for r in absolute)
    assert all(r["win_rate"] == "nan" for r in written)
    assert all(float(r["episode_return"]) >= 0 for r in written if r["kind"] == "eval")
    assert all(r["policy_loss"] and r["entropy"] for r in written if r["kind"] == "train")

    events = b"".join(f.read_bytes() for f in (trained / "tb").glob("events.out.tfevents.*"))
    for tag in ("train/episode_return/seed_1", "eval/episode_return/seed_0",
                "losses/approx_kl/seed_0", "charts/steps_per_second"):
        assert tag.encode() in events
    assert b"eval/win_rate" not in events

    data, steps = RunDir.open(trained).load_checkpoint()
    assert steps == 2000 and len(data) > 0
    assert (trained / "curve.png").read_bytes().startswith(b"\x89PNG")


def test_eval_shows_progress_on_a_terminal_only(
    trained: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert main(["eval", "--run", str(trained), "--episodes", "2"]) == 0
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert lines[0].startswith(f"cmat: evaluating {trained}: 2 episodes for each of 2 seeds")
    assert re.fullmatch(r"cmat: evaluated in \d+ s", lines[1]) and len(lines) == 2
    assert json.loads(captured.out)["episodes_per_seed"] == 2


def test_eval_prints_one_json_object_with_an_entry_per_seed(
    trained: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["eval", "--run", str(trained)]) == 0
    result = json.loads(capsys.readouterr().out)
    assert [entry["seed"] for entry in result["per_seed"]] == list(SEEDS)
    assert result["episodes_per_seed"] == 4
    final = {int(r["seed"]): float(r["episode_return"])
             for r in rows(trained) if r["kind"] == "eval" and r["env_steps"] == "2000"}
    for entry in result["per_seed"]:
        assert set(entry) == {"seed", "episode_return", "win_rate"}
        assert entry["win_rate"] is None
        assert entry["episode_return"] == pytest.approx(final[entry["seed"]], rel=1e-6)


def test_plot_writes_a_png(trained: Path, run_copy: Path, tmp_path: Path) -> None:
    out = tmp_path / "plots" / "curves.png"
    assert main(["plot", str(trained), str(run_copy), "--out", str(out)]) == 0
    assert out.read_bytes().startswith(b"\x89PNG")


def test_an_interrupt_that_python_drops_still_stops_the_run_after_its_chunk(
    run_copy: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    train_chunk = JaxTrainer.train_chunk

    def chunk_that_swallows_an_interrupt(
        self: JaxTrainer, state: TrainerState, updates: int | None = None
    ) -> tuple[TrainerState, dict[str, np.ndarray]]:
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        except KeyboardInterrupt:
            pass  # as Python does with one raised inside a garbage-collection callback
        return train_chunk(self, state, updates)

    monkeypatch.setattr(JaxTrainer, "train_chunk", chunk_that_swallows_an_interrupt)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # xdist ignores SIGINT
    try:
        assert main(["train", "--resume", str(run_copy), "--steps", "3000"]) == 130
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)
    assert "--resume" in capsys.readouterr().err
    assert RunDir.open(run_copy).load_checkpoint()[1] == 2500
    assert max(int(r["env_steps"]) for r in rows(run_copy)) == 2500


def test_a_new_run_interrupted_before_its_first_chunk_leaves_no_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def interrupted(self: JaxTrainer, state: TrainerState, updates: int | None = None) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(JaxTrainer, "train_chunk", interrupted)
    out = tmp_path / "new"
    assert main(["train", "--env", "matrix:fig1", "--steps", "400", "--out", str(out)]) == 130
    assert f"the new run directory {out} was removed" in capsys.readouterr().err
    assert not out.exists()


def test_an_interrupted_process_ends_without_python_finalisation() -> None:
    """`cmat.cli.run` leaves with os._exit(130) after an interrupt: finalising the interpreter
    while XLA's threads still run crashed the process. atexit handlers mark finalisation."""
    probe = ("import atexit\nimport cmat.cli\n"
             "atexit.register(lambda: print('finalised'))\n"
             "cmat.cli.main = lambda: int(__import__('sys').argv[1])\ncmat.cli.run()\n")
    interrupted = subprocess.run([sys.executable, "-c", probe, "130"], capture_output=True,
                                 text=True, timeout=60)
    finished = subprocess.run([sys.executable, "-c", probe, "2"], capture_output=True,
                              text=True, timeout=60)
    assert (interrupted.returncode, interrupted.stdout) == (130, "")
    assert (finished.returncode, finished.stdout) == (2, "finalised\n")


def test_interrupted_then_resumed_run_continues_without_duplicates(
    run_copy: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    original = (run_copy / "metrics.csv").read_bytes()
    train_chunk = JaxTrainer.train_chunk
    calls: list[int] = []

    def interrupted_second_chunk(
        self: JaxTrainer, state: TrainerState, updates: int | None = None
    ) -> tuple[TrainerState, dict[str, np.ndarray]]:
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return train_chunk(self, state, updates)

    monkeypatch.setattr(JaxTrainer, "train_chunk", interrupted_second_chunk)
    assert main(["train", "--resume", str(run_copy), "--steps", "3000"]) == 130
    monkeypatch.undo()
    assert "--resume" in capsys.readouterr().err
    assert RunDir.open(run_copy).load_checkpoint()[1] == 2500
    assert max(int(r["env_steps"]) for r in rows(run_copy)) == 2500
    assert (run_copy / "metrics.csv").read_bytes().startswith(original)

    with (run_copy / "metrics.csv").open("a") as file:
        file.write("eval,0,3000,99.0,,,,,,\neval,1,30")
    assert main(["train", "--resume", str(run_copy), "--steps", "3000"]) == 0
    assert RunDir.open(run_copy).sources()["total_steps"] == "command line (--resume --steps)"
    assert RunDir.open(run_copy).sources()["num_envs"] == "command line"

    assert (run_copy / "metrics.csv").read_bytes().startswith(original)
    written = rows(run_copy)
    keys = Counter((r["kind"], r["seed"], r["env_steps"]) for r in written)
    assert max(keys.values()) == 1
    assert {int(r["env_steps"]) for r in written} == set(range(CHUNK_STEPS, 3000 + 1, CHUNK_STEPS))
    assert len([r for r in written if r["kind"] != "absolute"]) == 2 * len(SEEDS) * 6
    absolute = sorted(int(r["env_steps"]) for r in written if r["kind"] == "absolute")
    assert absolute == [2000] * len(SEEDS) + [3000] * len(SEEDS)  # each time it completed
    assert RunDir.open(run_copy).config().total_steps == 3000
    assert RunDir.open(run_copy).load_checkpoint()[1] == 3000


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--env", "nope:x"], "unknown environment prefix 'nope'"),
        (["--env", "smax:nope"], "unknown SMAX scenario 'nope'"),
        (["--env", "matrix:fig1", "--set", "network.foo=1"],
         "invalid config: unknown key network.foo"),
        (["--env", "matrix:fig1", "--set", "ppo.epochs=abc"],
         "invalid config: ppo.epochs: expected an integer, got 'abc'"),
        (["--env", "matrix:fig1", "--set", "ppo.lr=2.5.1"],
         "invalid config: ppo.lr: expected a number, got '2.5.1'"),
        (["--env", "matrix:fig1", "--set", "ppo.value_norm=sometimes"],
         "invalid config: ppo.value_norm: expected true or false, got 'sometimes'"),
        (["--env", "matrix:fig1", "--set", "network=64"],
         "invalid config: network: a section (set its keys as network.KEY=VALUE), got 64"),
        (["--env", "matrix:fig1", "--set", "ppo.epoch=3"],
         "invalid config: unknown key ppo.epoch. Did you mean: 'epochs'?"),
        (["--env", "matrix:fig1", "--set", "cmat.consensus_iterations=-1"],
         "consensus_iterations (m) must be >= 0, got -1"),
        (["--env", "matrix:fig1", "--set", "network.n_embd=10", "network.n_head=3"],
         "n_embd (10) must be divisible by network.n_head (3)"),
        (["--env", "matrix:fig1", "--steps", "0"], "steps must be > 0, got 0"),
        (["--env", "matrix:fig1", "--seeds", "0"], "seeds must be > 0, got 0"),
        (["--env", "matrix:fig1", "--set", "num_envs=0"], "num_envs must be > 0, got 0"),
        (["--env", "matrix:fig1", "--set", "rollout_length=0"], "rollout_length must be > 0"),
        (["--env", "matrix:fig1", "--set", "ppo.num_minibatches=0"],
         "ppo.num_minibatches must be > 0, got 0"),
        (["--env", "matrix:fig1", "--algo", "sable", "--set", "ppo.num_minibatches=0"],
         "ppo.num_minibatches must be > 0, got 0"),
        (["--env", "matrix:fig1", "--algo", "nope"], "unknown algorithm 'nope'"),
        (["--env", "smax: 3m"], "unknown SMAX scenario ' 3m'"),
        (["--env", "pettingzoo:"], "'pettingzoo:' must look like pettingzoo:package.module"),
        (["--env", "true"], "unknown environment prefix 'true' in 'true'"),
        (["--env", "matrix:fig1", "--algo", "1.5"], "unknown algorithm '1.5'"),
        (["--env", "matrix:fig1", "--set", "ppo.lr=fast"], "invalid config"),
        (["--config", "missing.yaml"], "config file not found: missing.yaml"),
        (["--env", "matrix:fig1", "--steps", str(10**20)],
         "must each be at most 2,147,483,647: the trainer counts env steps in int32"),
        (["--env", "matrix:fig1", "--set", "num_envs=3000000", "rollout_length=1000"],
         "num_envs * rollout_length * seeds (3,000,000,000)"),
        (["--env", "matrix:fig1", "--seeds", "2", "--set", "num_envs=1100000000"],
         "num_envs * rollout_length * seeds (55,000,000,000)"),
        (["--env", "matrix:fig1", "--set", "eval_episodes=4294967296"],
         "eval_episodes must be within ±2,147,483,647 (JAX computes in int32), "
         "got 4,294,967,296"),
        (["--env", "matrix:fig1", "--set", "network.n_embd=8589934592"],
         "network.n_embd must be within ±2,147,483,647"),
    ],
)
def test_bad_training_input_is_one_error_line(
    args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert main(["train", *args, "--out", str(out)]) == 2
    assert message in one_error_line(capsys.readouterr().err)
    assert not out.exists()


def test_bad_yaml_is_one_error_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "bad.yaml"
    config.write_text("ppo: [unclosed\n")
    assert main(["train", "--config", str(config), "--out", str(tmp_path / "out")]) == 2
    assert "is not valid YAML" in one_error_line(capsys.readouterr().err)
    config.write_text("ppo:\n  epochs: abc\n")
    assert main(["train", "--config", str(config), "--out", str(tmp_path / "out")]) == 2
    assert ("invalid config: ppo.epochs: expected an integer, got 'abc'"
            in one_error_line(capsys.readouterr().err))
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("text", "key", "line"), [
    ("ppo:\n  lr: 0.001\n  epochs: 3\n  lr: 0.002\n", "lr", 4),
    ("env: smax:3m\nseeds: 2\nenv: smax:8m\n", "env", 3),
    ("env_kwargs: {k: -5, k: -6}\n", "k", 1),
])
def test_a_key_given_twice_is_one_error_line_in_configs_and_specs(
    text: str, key: str, line: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "twice.yaml"
    config.write_text(text)
    duplicate = f"key {key!r} appears twice in one mapping (line {line})"
    assert main(["train", "--config", str(config), "--out", str(tmp_path / "out")]) == 2
    assert (f"config file {config} is not valid YAML: {duplicate}"
            in one_error_line(capsys.readouterr().err))
    assert main(["experiment", str(config), "--out", str(tmp_path / "grid")]) == 2
    assert (f"experiment spec {config} is not valid YAML: {duplicate}"
            in one_error_line(capsys.readouterr().err))
    assert not (tmp_path / "out").exists() and not (tmp_path / "grid").exists()


def test_yaml_merge_keys_still_override(tmp_path: Path) -> None:
    config = tmp_path / "merge.yaml"
    config.write_text("base: &base {epochs: 3, lr: 0.001}\nppo:\n  <<: *base\n  lr: 0.002\n")
    assert load_yaml(config.read_text())["ppo"] == {"epochs": 3, "lr": 0.002}


def test_files_that_are_not_utf8_text_are_one_error_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"ppo:\n  lr: 0.001\n\xff\xfe\x00")
    assert main(["train", "--config", str(binary), "--out", str(tmp_path / "out")]) == 2
    assert (f"config file {binary} is not UTF-8 text (byte 17)"
            in one_error_line(capsys.readouterr().err))
    assert main(["experiment", str(binary), "--out", str(tmp_path / "grid")]) == 2
    assert (f"experiment spec {binary} is not UTF-8 text (byte 17)"
            in one_error_line(capsys.readouterr().err))
    assert not (tmp_path / "out").exists() and not (tmp_path / "grid").exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        ([], "the following arguments are required: command (see `cmat --help`)"),
        (["fly"], "invalid choice: 'fly'"),
        (["train", "--steps", "many"],
         "argument --steps: invalid int value: 'many' (see `cmat train --help`)"),
        (["plot", "x"], "the following arguments are required: --out (see `cmat plot --help`)"),
        (["finetune", "--from", "x", "--mode", "bogus"], "argument --mode: invalid choice"),
        (["eval"], "cmat eval needs --run DIR (or --baseline NAME with --env ID or --run)"),
    ],
)
def test_usage_errors_are_one_error_line(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(argv) == 2
    assert message in one_error_line(capsys.readouterr().err)


@pytest.mark.parametrize(("argv", "code"), [
    (["--help"], 0),
    (["train", "--help"], 0),
    (["train", "--algo", "nosuch"], 2),
    (["train", "--config", "{bad}"], 2),
    (["train", "--set", "ppo.epochs=abc"], 2),
    (["experiment", "{bad}"], 2),
    (["experiment", "{spec}", "--out", "{tmp}/grid"], 2),
    (["eval", "--run", "{tmp}/missing"], 2),
    (["finetune", "--from", "{tmp}/missing", "--mode", "consensus"], 2),
    (["plot", "{tmp}/missing", "--out", "{tmp}/plot.png"], 2),
])
def test_input_errors_and_help_come_before_jax_is_imported(
    argv: list[str], code: int, tmp_path: Path
) -> None:
    """Importing JAX and the networks takes seconds: the CLI's help and its reports of bad
    input (configs, specs, missing runs) must not wait for it."""
    bad = tmp_path / "bad.yaml"
    bad.write_text("ppo: [unclosed\n")
    spec = tmp_path / "spec.yaml"
    spec.write_text("name: x\nsteps: 100\nenvs: [matrix:fig1]\nalgos: [cmat, nosuch]\n")
    argv = [a.format(bad=bad, spec=spec, tmp=tmp_path) for a in argv]
    probe = ("import sys\nfrom cmat.cli import main\n"
             "try:\n    code = main(sys.argv[1:])\nexcept SystemExit as exit:\n"
             "    code = exit.code\n"
             "print('jax imported' if 'jax' in sys.modules else 'no jax', code)\n")
    result = subprocess.run([sys.executable, "-c", probe, *argv], capture_output=True,
                            text=True, timeout=120)
    assert result.stdout.splitlines()[-1] == f"no jax {code}", result.stderr


def test_out_pointing_at_a_run_changes_nothing(
    trained: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = snapshot(trained)
    assert main([*TRAIN, "--out", str(trained)]) == 2
    assert "already holds a run; use --resume" in one_error_line(capsys.readouterr().err)
    assert snapshot(trained) == before


def test_resume_accepts_only_steps(trained: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = snapshot(trained)
    assert main(["train", "--resume", str(trained), "--seeds", "3"]) == 2
    assert "--resume takes no other option than --steps" in one_error_line(capsys.readouterr().err)
    assert main(["train", "--resume", str(trained), "--steps", "1000"]) == 2
    assert "below the 2000 env steps already done" in one_error_line(capsys.readouterr().err)
    assert snapshot(trained) == before


def test_missing_run_or_checkpoint_is_reported(
    trained: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["eval", "--run", str(tmp_path)]) == 2
    assert "holds no run" in one_error_line(capsys.readouterr().err)
    for episodes in (0, 2**31, 10**20):
        assert main(["eval", "--run", str(trained), "--episodes", str(episodes)]) == 2
        assert (f"--episodes must be in [1, 2,147,483,647], got {episodes:,}"
                in one_error_line(capsys.readouterr().err))
    shutil.copy(trained / "config.yaml", tmp_path / "config.yaml")
    for argv in (["eval", "--run", str(tmp_path)], ["train", "--resume", str(tmp_path)]):
        assert main(argv) == 2
        assert f"no checkpoint in {tmp_path}" in one_error_line(capsys.readouterr().err)


@pytest.mark.parametrize("damage", ["truncate", "garble"])
def test_corrupt_checkpoint_is_reported_and_changes_nothing(
    run_copy: Path, damage: str, capsys: pytest.CaptureFixture[str]
) -> None:
    checkpoint = run_copy / "checkpoints" / "latest.ckpt"
    raw = checkpoint.read_bytes()
    middle = len(raw) // 2
    checkpoint.write_bytes(raw[:middle] if damage == "truncate"
                           else raw[:middle] + bytes(b ^ 0xFF for b in raw[middle:]))
    before = snapshot(run_copy)
    for argv in (["eval", "--run", str(run_copy)],
                 ["train", "--resume", str(run_copy), "--steps", "3000"]):
        assert main(argv) == 2
        assert f"corrupt checkpoint: {checkpoint}" in one_error_line(capsys.readouterr().err)
    assert snapshot(run_copy) == before


def test_console_script(trained: Path) -> None:
    script = Path(sys.executable).parent / "cmat"
    done = subprocess.run([script, "eval", "--run", trained, "--episodes", "2"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    assert len(json.loads(done.stdout)["per_seed"]) == len(SEEDS)

    failed = subprocess.run([script, "train", "--env", "smax:nope"],
                            capture_output=True, text=True, timeout=300)
    assert failed.returncode == 2
    assert "unknown SMAX scenario" in one_error_line(failed.stderr)


@pytest.mark.parametrize(("edit", "reason"), [
    (("num_envs: 4", "num_envs: 8"), "shapes differ"),
    (("rollout_length: 25", "rollout_length: 50"), "would count as 4,000"),
    (("n_embd: 64", "n_embd: 32"), "shapes differ: state/"),
    (("n_block: 1", "n_block: 2"), "state differs: state/"),
])
def test_a_config_edited_against_its_checkpoint_is_reported_and_changes_nothing(
    run_copy: Path, tmp_path: Path, edit: tuple[str, str], reason: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    config = run_copy / "config.yaml"
    text = config.read_text()
    assert text.count(edit[0]) == 1
    config.write_text(text.replace(*edit))
    before = snapshot(run_copy)
    for argv in (["eval", "--run", str(run_copy)],
                 ["train", "--resume", str(run_copy), "--steps", "4000"],
                 ["finetune", "--from", str(run_copy), "--mode", "action",
                  "--out", str(tmp_path / "stage")]):
        assert main(argv) == 2
        line = one_error_line(capsys.readouterr().err)
        assert reason in line and str(config if "count" in reason else run_copy) in line, line
    assert snapshot(run_copy) == before
    assert not (tmp_path / "stage").exists()


def test_a_run_in_training_elsewhere_or_complete_is_left_as_it_is(
    run_copy: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    before = snapshot(run_copy)
    with monkeypatch.context() as patch:  # the budget is checked before anything compiles
        patch.setattr("cmat.cli.build_trainer", lambda config: pytest.fail("trainer built"))
        assert main(["train", "--resume", str(run_copy)]) == 0
        assert "is complete at 2,000 env steps per seed" in capsys.readouterr().err
        assert main(["train", "--resume", str(run_copy), "--steps", "1000"]) == 2
        assert ("steps (1000) is below the 2000 env steps already done"
                in one_error_line(capsys.readouterr().err))
    assert snapshot(run_copy) == before
    with lock_held_elsewhere(run_copy) as pid:
        held = snapshot(run_copy)
        assert main(["train", "--resume", str(run_copy), "--steps", "3000"]) == 2
        line = one_error_line(capsys.readouterr().err)
        assert f"in use by another cmat process (pid {pid})" in line
        assert main(["eval", "--run", str(run_copy), "--episodes", "2"]) == 0
        assert snapshot(run_copy) == held


@pytest.mark.parametrize(("argv", "note"), [
    (["--steps", "500"], "training 800 env steps per seed (1 seed); total_steps 500 from "
     "command line, rounded up to whole updates of num_envs × rollout_length = 400 steps"),
    (["--seeds", "2"], "training 4,000 env steps per seed (2 seeds); total_steps 4,000 from "
     "suite matrix"),
])
def test_train_says_what_budget_it_starts_and_where_it_comes_from(
    argv: list[str], note: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from cmat import api

    monkeypatch.setattr(api, "train_into", lambda *args, **kwargs: None)
    assert main(["train", "--env", "matrix:fig1", *argv, "--out", str(tmp_path / "run")]) == 0
    assert capsys.readouterr().out.splitlines()[0] == note
    assert main(["train", "--env", "matrix:fig1", *argv, "--dry-run"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"# {note}"  # before anything compiles


@pytest.mark.parametrize(("field", "value"), [("n_head", 2)])
def test_a_network_edited_in_config_yaml_is_refused_not_evaluated_with_old_weights(
    run_copy: Path, field: str, value: object, capsys: pytest.CaptureFixture[str]
) -> None:
    """A field that leaves the parameters' shapes alone (heads split the same width) would
    otherwise restore silently."""
    config = yaml.safe_load((run_copy / "config.yaml").read_text())
    assert config["network"][field] != value
    config["network"][field] = value
    (run_copy / "config.yaml").write_text(yaml.safe_dump(config))
    for argv in (["eval", "--run", str(run_copy)],
                 ["train", "--resume", str(run_copy), "--steps", "3000"]):
        assert main(argv) == 2
        line = one_error_line(capsys.readouterr().err)
        assert f"network.{field} is {value!r} there" in line
        assert "a run's network cannot change" in line


def full_disk_at(monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    """Every write of a file called `name` in a run directory fails as a full disk does: an
    OSError that names no file."""
    import tempfile

    from cmat import rundir

    real = tempfile.mkstemp

    def mkstemp(*args: object, **kwargs: object) -> tuple[int, str]:
        if str(kwargs.get("prefix", "")).startswith(f".{name}."):
            raise OSError(28, "No space left on device")
        return real(*args, **kwargs)  # type: ignore[call-overload, no-any-return]

    monkeypatch.setattr(rundir.tempfile, "mkstemp", mkstemp)


@pytest.mark.parametrize("name", ["config.yaml", "latest.ckpt"])
def test_a_full_disk_names_the_file_and_leaves_no_dead_end(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    out = tmp_path / "run"
    argv = ["train", "--env", "matrix:fig1", "--steps", "200", "--out", str(out), "--set",
            "num_envs=4", "rollout_length=25", "ppo.epochs=1"]
    with monkeypatch.context() as patch:
        full_disk_at(patch, name)
        assert main(argv) == 2
    error = one_error_line(capsys.readouterr().err)
    assert name in error and "No space left on device" in error
    assert not out.exists()  # the same --out starts the run once there is room
    assert main(argv) == 0 and RunDir.open(out).checkpoint_steps()[0] == 200


def test_a_full_disk_during_a_run_keeps_the_last_checkpoint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "run"
    settings = ["--set", "num_envs=4", "rollout_length=25", "ppo.epochs=1", "log_interval=1"]
    assert main(["train", "--env", "matrix:fig1", "--steps", "200", "--out", str(out),
                 *settings]) == 0
    with monkeypatch.context() as patch:
        full_disk_at(patch, "latest.ckpt")
        assert main(["train", "--resume", str(out), "--steps", "400"]) == 2
    stderr = capsys.readouterr().err  # the progress bar of the chunks before, then the error
    error = stderr.strip().splitlines()[-1]
    assert "Traceback" not in stderr and error.startswith("cmat: error: cannot write ")
    assert "latest.ckpt" in error and f"cmat train --resume {out}" in error
    assert RunDir.open(out).checkpoint_steps()[0] == 200
    assert main(["train", "--resume", str(out), "--steps", "400"]) == 0
    assert RunDir.open(out).checkpoint_steps()[0] == 400
