"""Training steps/s of two checkouts of cmat, measured in alternation (A B A B ...).

    python benchmarks/ab_throughput.py --before ../cmat-old --after . --algo cmat --algo mappo
    python benchmarks/ab_throughput.py --before OLD --after NEW --env smax:3m --pairs 3 \
        --set cmat.joint_clip=joint ppo.target_tau=0.1
    python benchmarks/ab_throughput.py --before . --after . --after-python \
        .venv-latest/bin/python --env smax:6h_vs_8z      # the same code on two JAX installs

Each measurement is one `benchmarks/throughput.py --single` process of that checkout (its own
code on `PYTHONPATH`): one algorithm's training chunk timed after compilation. Alternating the
two checkouts pair by pair keeps the ratio meaningful on a shared machine whose speed drifts;
the table gives each checkout's median steps/s and the median and range of the per-pair ratios
after / before. A refactor that costs nothing shows ratios around 1.

With `--programs` it first prints, per algorithm, a hash of each checkout's lowered program of
one whole update (rollout, GAE, PPO epochs, target update; StableHLO text without source
locations, a small config). Equal hashes mean XLA receives the same program from both, so any
difference in the timings is the machine's noise.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from machine import describe


def steps_per_second(tree: Path, python: str, env: str, algo: str, updates: int,
                     overrides: list[str]) -> float:
    """One `--single` measurement of checkout `tree` run by interpreter `python`."""
    script = tree / "benchmarks" / "throughput.py"
    command = [python, str(script), "--single", "--env", env, "--algo", algo,
               "--updates", str(updates), "--set", *overrides]
    environment = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run(command, check=False, capture_output=True, text=True, env=environment)
    if done.returncode != 0:
        reason = (done.stderr.strip().splitlines() or ["failed"])[-1]
        raise SystemExit(f"{tree} {algo}: {reason}")
    return float(json.loads(done.stdout.strip().splitlines()[-1])["steps_per_second"])


PROGRAM_HASH = """
import hashlib, re, sys
import jax
try:
    from cmat.resolve import load_config
except ImportError:
    from cmat.config import load_config
from cmat.runners import trainer
config = load_config(overrides=[f"env={sys.argv[1]}", f"algo={sys.argv[2]}", "num_envs=4",
                                "rollout_length=8", "ppo.epochs=2", *sys.argv[3:]])
setup = trainer.build_setup(config)
state = trainer.init_state(setup, jax.random.PRNGKey(0))
text = jax.jit(lambda s: trainer.update_step(setup, s)).lower(state).as_text()
print(hashlib.sha256(re.sub(r"loc\\([^)]*\\)", "", text).encode()).hexdigest()[:16])
"""
"""Run in a checkout: the hash of its lowered update program for ENV ALGO OVERRIDES..."""


def program_hash(tree: Path, python: str, env: str, algo: str, overrides: list[str]) -> str:
    environment = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run([python, "-c", PROGRAM_HASH, env, algo, *overrides],
                          check=False, capture_output=True, text=True, env=environment)
    if done.returncode != 0:
        raise SystemExit(f"{tree} {algo}: {(done.stderr.strip().splitlines() or ['failed'])[-1]}")
    return done.stdout.strip().splitlines()[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--before", type=Path, required=True, help="checkout A (the baseline)")
    parser.add_argument("--after", type=Path, required=True, help="checkout B")
    parser.add_argument("--before-python", default=sys.executable,
                        help="interpreter (hence JAX install) of A (default: this one)")
    parser.add_argument("--after-python", default=sys.executable,
                        help="interpreter of B (default: this one)")
    parser.add_argument("--algo", action="append", help="algorithm (repeatable; default cmat)")
    parser.add_argument("--env", default="smax:3m")
    parser.add_argument("--pairs", type=int, default=3,
                        help="alternating pairs per algorithm (0: compare programs only)")
    parser.add_argument("--updates", type=int, default=1, help="updates per timed chunk")
    parser.add_argument("--set", nargs="*", default=[], help="config overrides for both")
    parser.add_argument("--programs", action="store_true",
                        help="first compare the lowered update programs of the two checkouts")
    args = parser.parse_args()
    if args.programs:
        for algo in args.algo or ["cmat"]:
            hash_a = program_hash(args.before, args.before_python, args.env, algo, args.set)
            hash_b = program_hash(args.after, args.after_python, args.env, algo, args.set)
            verdict = "identical" if hash_a == hash_b else "DIFFERENT"
            print(f"{algo:<12} update program before {hash_a}  after {hash_b}  {verdict}")
    if args.pairs <= 0:
        return
    print(describe(with_matmul=False))
    print(f"Training steps/s on {args.env}, {args.pairs} alternating pairs, overrides: "
          f"{' '.join(args.set) or '-'}")
    print(f"{'algo':<12} {'before':>9} {'after':>9} {'after/before median [range]':>30}")
    for algo in args.algo or ["cmat"]:
        before, after = [], []
        for _ in range(args.pairs):
            before.append(steps_per_second(args.before, args.before_python, args.env, algo,
                                           args.updates, args.set))
            after.append(steps_per_second(args.after, args.after_python, args.env, algo,
                                          args.updates, args.set))
        ratios = np.array(after) / np.array(before)
        print(f"{algo:<12} {np.median(before):>9.0f} {np.median(after):>9.0f} "
              f"{np.median(ratios):>14.3f} [{ratios.min():.3f}, {ratios.max():.3f}]", flush=True)


if __name__ == "__main__":
    main()
