"""Kill-and-resume soak: SIGKILL a training run at random points, resume it, check what is left.

    python benchmarks/kill_resume_soak.py                                  # SMAX 3m and HalfCheetah
    python benchmarks/kill_resume_soak.py --envs smax:3m --kills 8 --seed 3

For each environment, in one run of this script:
1. a reference run trains uninterrupted (in-graph environments only: host simulators restart
   their episodes on resume, so a host run cannot match one);
2. the soak run starts the same command, and `--kills` times: waits until it has written two
   checkpoints past the one it started from, sends SIGKILL to its process group at a uniformly
   random point of the next chunk, verifies the checkpoint left behind (header, size, sha256),
   and resumes it with `cmat train --resume`; then it runs to the end.
Checked at the end: the final checkpoint is at the run's budget; `metrics.csv` has, per kind
and seed, exactly one row per log point, in increasing env steps; and (in-graph) every metric
of every row equals the reference run's. Prints one line per kill and a summary table; exits 1
when a check fails.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cmat.envs.host import is_host_env
from cmat.errors import CmatError
from cmat.resolve import load_config
from cmat.rundir import RunDir

SETTINGS = {
    "smax:3m": ["num_envs=16", "rollout_length=50", "log_interval=4", "eval_episodes=8",
                "network.n_embd=32", "ppo.epochs=5"],
    "mamujoco:HalfCheetah-6x1": ["num_envs=4", "rollout_length=100", "log_interval=2",
                                 "eval_episodes=1", "network.n_embd=16", "ppo.epochs=2",
                                 "env_kwargs.agent_id=true"],
}
STEPS = {"smax:3m": 32_000, "mamujoco:HalfCheetah-6x1": 8_000}


def train_command(env: str, steps: int, seeds: int, out: Path, settings: list[str]) -> list[str]:
    return [sys.executable, "-m", "cmat", "train", "--env", env, "--steps", str(steps),
            "--seeds", str(seeds), "--out", str(out), "--set", *settings]


def resume_command(out: Path) -> list[str]:
    return [sys.executable, "-m", "cmat", "train", "--resume", str(out)]


def checkpoint_steps(run: Path) -> int:
    """Env steps of the run's checkpoint (-1 where there is none yet); raises CmatError if it
    does not verify."""
    if not (run / "checkpoints" / "latest.ckpt").is_file():
        return -1
    return RunDir(run).load_checkpoint()[1]


def run_to_end(command: list[str], log: Path) -> None:
    with log.open("a") as file:
        done = subprocess.run(command, stdout=file, stderr=subprocess.STDOUT, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} exited {done.returncode}; see {log}")


def wait_for_progress(process: subprocess.Popen, run: Path, past: int, deadline: float,
                      log: Path) -> int | None:
    """The run's checkpoint steps once past `past`; None if the process ended first."""
    while True:
        steps = checkpoint_steps(run)
        if steps > past:
            return steps
        if process.poll() is not None:
            return None
        if time.monotonic() > deadline:
            os.killpg(process.pid, signal.SIGKILL)
            raise SystemExit(f"no checkpoint past {past} steps in time; see {log}")
        time.sleep(0.05)


def kill_at_random(command: list[str], run: Path, log: Path, rng: random.Random,
                   timeout: float) -> tuple[int, int, bool]:
    """Start `command`; once it has written two checkpoints past the one it started from, SIGKILL
    it at a uniformly random point of its next chunk (its length measured between those two).
    Returns the checkpoint steps before and after, and whether it was killed (it may finish
    first)."""
    start = checkpoint_steps(run)
    with log.open("a") as file:
        process = subprocess.Popen(command, stdout=file, stderr=subprocess.STDOUT,
                                   start_new_session=True)
    deadline = time.monotonic() + timeout
    first = wait_for_progress(process, run, max(start, 0), deadline, log)
    first_at = time.monotonic()
    second = None if first is None else wait_for_progress(process, run, first, deadline, log)
    killed = False
    if second is not None:
        time.sleep(rng.uniform(0.0, time.monotonic() - first_at))
        killed = process.poll() is None
        if killed:
            os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    return start, checkpoint_steps(run), killed


def metric_problems(run: Path, budget: int, per_log: int, seeds: int) -> tuple[int, list[str]]:
    """Rows checked and what is wrong with `run`'s metrics.csv (duplicates, gaps, order)."""
    with (run / "metrics.csv").open(newline="") as file:
        rows = list(csv.DictReader(file))
    expected = list(range(per_log, budget + 1, per_log))
    if not expected or expected[-1] != budget:
        expected.append(budget)
    problems = []
    for kind in ("train", "eval"):
        for seed in range(seeds):
            steps = [int(r["env_steps"]) for r in rows
                     if r["kind"] == kind and int(r["seed"]) == seed]
            if steps != expected:
                problems.append(f"{kind} rows of seed {seed}: env steps {steps}, expected "
                                f"{expected}")
    return len(rows), problems


def same_metrics(run: Path, reference: Path) -> list[str]:
    """Rows of `run` whose values differ from `reference`'s (relative tolerance 1e-5)."""
    def read(path: Path) -> list[dict[str, str]]:
        with (path / "metrics.csv").open(newline="") as file:
            return list(csv.DictReader(file))

    problems = []
    got, want = read(run), read(reference)
    if len(got) != len(want):
        return [f"{len(got)} rows, the uninterrupted run has {len(want)}"]
    for index, (a, b) in enumerate(zip(got, want)):
        for key, value in b.items():
            x, y = a.get(key, ""), value
            if x == y:
                continue
            try:
                close = math.isclose(float(x), float(y), rel_tol=1e-5, abs_tol=1e-7)
            except ValueError:
                close = False
            if not close:
                problems.append(f"row {index} ({b['kind']}, seed {b['seed']}, {b['env_steps']} "
                                f"steps) {key}: {x} vs {y}")
    return problems


def soak(env: str, kills: int, seeds: int, steps: int, settings: list[str], rng: random.Random,
         workdir: Path, timeout: float) -> dict[str, object]:
    config = load_config(overrides=[f"env={env}", f"total_steps={steps}", f"seeds={seeds}",
                                    *settings])
    per_log = config.updates_per_log * config.steps_per_update
    log = workdir / f"{env.replace(':', '_')}.log"
    reference = None
    started = time.perf_counter()
    if not is_host_env(env):
        reference = workdir / f"{env.replace(':', '_')}-reference"
        run_to_end(train_command(env, steps, seeds, reference, settings), log)
    run = workdir / f"{env.replace(':', '_')}-soak"
    command = train_command(env, steps, seeds, run, settings)
    killed = 0
    for attempt in range(kills):
        before, after, was_killed = kill_at_random(command, run, log, rng, timeout)
        killed += was_killed
        print(f"{env}: attempt {attempt + 1}/{kills}: "
              f"{'killed' if was_killed else 'finished first'}, checkpoint {before} -> {after} "
              f"env steps, verified", flush=True)
        command = resume_command(run)
        if after >= config.budget_steps:
            break
    if checkpoint_steps(run) < config.budget_steps:
        run_to_end(command, log)
    final = checkpoint_steps(run)
    rows, problems = metric_problems(run, config.budget_steps, per_log, seeds)
    if final != config.budget_steps:
        problems.append(f"final checkpoint at {final} env steps, budget {config.budget_steps}")
    if reference is not None:
        problems += same_metrics(run, reference)
    return {"env": env, "kills": killed, "resumes": killed, "rows": rows, "final": final,
            "budget": config.budget_steps, "matches": "yes" if reference and not problems
            else ("n/a (host)" if reference is None else "no"), "problems": problems,
            "seconds": time.perf_counter() - started}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="+", default=list(SETTINGS))
    parser.add_argument("--kills", type=int, default=5)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--steps", type=int, help="env steps per seed (default: per env)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill points")
    parser.add_argument("--timeout", type=float, default=900.0,
                        help="seconds to wait for a checkpoint before giving up")
    parser.add_argument("--workdir", type=Path, help="keep the runs here (default: a temp dir)")
    args = parser.parse_args()
    rng = random.Random(args.seed)
    results = []
    with tempfile.TemporaryDirectory() as temp:
        workdir = args.workdir or Path(temp)
        workdir.mkdir(parents=True, exist_ok=True)
        for env in args.envs:
            try:
                steps = args.steps or STEPS.get(env, 20_000)
                results.append(soak(env, args.kills, args.seeds, steps,
                                    SETTINGS.get(env, []), rng, workdir, args.timeout))
            except CmatError as error:
                print(f"{env}: {error}", file=sys.stderr)
                return 1
    print("\nenv                        kills  resumes  rows  final/budget     "
          "same as uninterrupted  s")
    failed = False
    for r in results:
        print(f"{r['env']:<26} {r['kills']:>5}  {r['resumes']:>7}  {r['rows']:>4}  "
              f"{r['final']:>6}/{r['budget']:<8}  {r['matches']:<21}  {r['seconds']:.0f}")
        for problem in r["problems"]:  # type: ignore[attr-defined]
            print(f"  problem: {problem}")
            failed = True
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
