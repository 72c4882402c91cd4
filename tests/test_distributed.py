"""One run across two processes (cmat.runners.distributed), each a `cmat train` with one CPU
device, joined over the loopback: it trains what one process with two devices trains, resumes,
only process 0 writes, and a killed process stops the other with one line, not a hang."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytestmark = pytest.mark.quick_compiles

RUN = ["--env", "matrix:fig1", "--algo", "mappo", "--seeds", "1",
       "--set", "num_envs=4", "rollout_length=8", "log_interval=16", "ppo.epochs=2"]
"""One seed and four environments: the environments are sharded over the two processes, so
every update's gradient is reduced across them."""


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def environment(devices: int) -> dict[str, str]:
    return {**os.environ, "JAX_PLATFORMS": "cpu",
            "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} "
                         f"--xla_force_host_platform_device_count={devices}"}


def start_pair(arguments: list[str], logs: Path) -> list[subprocess.Popen[bytes]]:
    """Processes 0 and 1 of one run, stdout and stderr in logs/process-I.log."""
    port = free_port()
    logs.mkdir(parents=True, exist_ok=True)
    return [
        subprocess.Popen(
            [sys.executable, "-m", "cmat", "train", *arguments, "--coordinator",
             f"127.0.0.1:{port}", "--processes", "2", "--process-id", str(index)],
            stdout=(logs / f"process-{index}.log").open("wb"), stderr=subprocess.STDOUT,
            env=environment(1))
        for index in (0, 1)]


def finish_pair(processes: list[subprocess.Popen[bytes]], logs: Path) -> None:
    for index, process in enumerate(processes):
        assert process.wait(timeout=600) == 0, (logs / f"process-{index}.log").read_text()[-3000:]


@pytest.mark.slow
def test_two_processes_train_what_two_devices_train(tmp_path: Path) -> None:
    """Slow suite (80 s on 2 cores: three sessions, two of two processes; the fast suite starts
    two processes in the tests below). 512 steps, then --resume to 1,024, over two processes;
    against 1,024 steps in one process with two devices: every metric within 1e-5 (floating-
    point order), apart from the absolute-metric row the first session wrote at its budget of
    512."""
    one = tmp_path / "one"
    done = subprocess.run([sys.executable, "-m", "cmat", "train", *RUN, "--steps", "1024",
                           "--out", str(one)], env=environment(2), capture_output=True,
                          text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    two = tmp_path / "two"
    finish_pair(start_pair([*RUN, "--steps", "512", "--out", str(two)], tmp_path / "first"),
                tmp_path / "first")
    finish_pair(start_pair(["--resume", str(two), "--steps", "1024"], tmp_path / "resumed"),
                tmp_path / "resumed")
    expected, got = pd.read_csv(one / "metrics.csv"), pd.read_csv(two / "metrics.csv")
    first_budget = (got["kind"] == "absolute") & (got["env_steps"] == 512)
    assert first_budget.sum() == 1
    got = got[~first_budget].reset_index(drop=True)
    assert list(got["kind"]) == list(expected["kind"])
    assert list(got["env_steps"]) == list(expected["env_steps"])
    numbers = expected.select_dtypes("number").columns
    np.testing.assert_allclose(got[numbers].to_numpy(float), expected[numbers].to_numpy(float),
                               rtol=1e-5, atol=1e-6)
    sessions = (two / "sessions.jsonl").read_text().splitlines()
    assert len(sessions) == 2 and all('"processes": 2' in line for line in sessions)
    assert "process 0 writes the run" in (tmp_path / "first" / "process-1.log").read_text()
    assert sorted(path.name for path in tmp_path.iterdir()) == ["first", "one", "resumed", "two"]


@pytest.mark.parametrize("victim", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_a_killed_process_stops_the_other_with_one_line(tmp_path: Path, victim: int) -> None:
    """Kill one process once the run has a checkpoint with metrics: the other exits with
    status 2 within a minute, its last line the error, and the run keeps its checkpoint.
    Process 0, which also serves the coordinator, is the harder case; killing process 1 is in
    the slow suite."""
    run = tmp_path / "run"
    processes = start_pair([*RUN, "--steps", "10000000", "--out", str(run)], tmp_path)
    deadline = time.monotonic() + 300
    while not ((run / "metrics.csv").is_file()
               and len((run / "metrics.csv").read_text().splitlines()) >= 3):
        assert time.monotonic() < deadline and all(p.poll() is None for p in processes), \
            (tmp_path / "process-0.log").read_text()[-3000:]
        time.sleep(0.5)
    processes[victim].send_signal(signal.SIGKILL)
    survivor = 1 - victim
    try:
        code = processes[survivor].wait(timeout=60)
    finally:
        processes[survivor].kill()
    log = (tmp_path / f"process-{survivor}.log").read_text()
    last = log.strip().splitlines()[-1]
    assert code == 2, log[-3000:]
    assert last.startswith(f"cmat: error: process {survivor} of 2"), log[-3000:]
    assert "another process of the run stopped" in last and f"--resume {run}" in last
    assert "Check failure" not in log and "coordination_service" not in log  # no C++ log
    assert (run / "checkpoints" / "latest.ckpt").is_file()


@pytest.mark.parametrize(("flags", "message"), [
    (["--coordinator", "localhost"], "--coordinator must be HOST:PORT or auto"),
    (["--coordinator", "127.0.0.1:1234"], "needs --processes N and --process-id I"),
    (["--coordinator", "127.0.0.1:1234", "--processes", "2", "--process-id", "2"],
     "--process-id must be in 0..1"),
    (["--coordinator", "auto", "--processes", "2"], "takes neither --processes"),
    (["--process-id", "0"], "need --coordinator HOST:PORT"),
    (["--coordinator", "127.0.0.1:1234", "--dry-run"], "--dry-run takes no --coordinator"),
])
def test_cluster_flags_out_of_shape_give_one_line(
    flags: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from cmat.cli import main

    assert main(["train", *flags]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("cmat: error: ") and message in error and "\n" not in error


def test_a_training_child_ended_by_a_signal_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`supervise` where the runtime aborts the child (here a stand-in that sends itself
    SIGABRT): status 2 and one line naming the signal, the runtime's log and how to resume."""
    from cmat.runners.distributed import supervise

    child = tmp_path / "python"
    child.write_text("#!/bin/sh\nkill -ABRT $$\n")
    child.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(child))
    assert supervise(["train"], "process 1 of 2", tmp_path / "run") == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("cmat: error: process 1 of 2: stopped by SIGABRT") and "\n" not in error
    assert f"--resume {tmp_path / 'run'}" in error and "cmat-runtime-" in error
