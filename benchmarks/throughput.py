"""Training throughput and peak memory of each algorithm's compiled program, one process each.

    python benchmarks/throughput.py                              # every algorithm, SMAX 3s5z_vs_3s6z
    python benchmarks/throughput.py --algo cmat --preset reference --preset mava

Steps/s counts environment steps of all seeds, rollout and PPO update together, timed on the
second chunk (after compilation, which is reported on its own). Peak memory is the process's
maximum resident set size. The `mava` preset is the configuration at which Mava's MAT was
measured on this kind of machine (shared/reference/README.md: about 169 steps/s, 13.2 GB peak on
3s5z_vs_3s6z), so the two can be compared at equal work per step.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

from cmat.config import ALGORITHMS

PRESETS: dict[str, list[str]] = {
    "reference": [],
    "mava": [
        "num_envs=128", "rollout_length=128", "network.n_block=3", "network.n_embd=128",
        "ppo.epochs=5", "ppo.num_minibatches=1",
    ],
}


def measure(env: str, algo: str, overrides: list[str], updates: int) -> dict[str, float]:
    import jax

    from cmat.config import load_config
    from cmat.runners.trainer import Trainer

    config = load_config(
        overrides=[f"env={env}", f"algo={algo}", f"log_interval={updates}", *overrides]
    )
    trainer = Trainer(config)
    state = trainer.init()
    start = time.perf_counter()
    state, _ = trainer.train_chunk(state)
    first = time.perf_counter() - start
    start = time.perf_counter()
    state, _ = trainer.train_chunk(state)
    jax.block_until_ready(state)
    run = time.perf_counter() - start
    steps = updates * config.steps_per_update * config.seeds
    return {
        "steps_per_second": steps / run,
        "compile_seconds": first - run,
        "seconds_per_update": run / updates,
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="smax:3s5z_vs_3s6z")
    parser.add_argument("--algo", choices=ALGORITHMS, action="append")
    parser.add_argument("--preset", choices=sorted(PRESETS), action="append",
                        help="default: reference")
    parser.add_argument("--updates", type=int, default=2, help="updates per timed chunk")
    parser.add_argument("--set", nargs="*", default=[], help="extra config overrides")
    parser.add_argument("--single", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.single:
        print(json.dumps(measure(args.env, args.algo[0], args.set, args.updates)))
        return
    print(f"Training throughput on {args.env} ({args.updates} updates per timed chunk; "
          "each algorithm with its own defaults from cmat.config)")
    print(f"{'algo':<12} {'preset':<10} {'steps/s':>9} {'s/update':>9} {'compile s':>10} "
          f"{'peak RSS GB':>12}  overrides")
    for algo in args.algo or ALGORITHMS:
        for preset in args.preset or ["reference"]:
            overrides = [*PRESETS[preset], *args.set]
            command = [sys.executable, __file__, "--single", "--env", args.env, "--algo", algo,
                       "--updates", str(args.updates), "--set", *overrides]
            done = subprocess.run(command, capture_output=True, text=True)
            if done.returncode != 0:
                reason = (done.stderr.strip().splitlines() or ["failed"])[-1]
                print(f"{algo:<12} {preset:<10} failed: {reason}")
                continue
            result = json.loads(done.stdout.strip().splitlines()[-1])
            print(f"{algo:<12} {preset:<10} {result['steps_per_second']:>9.0f} "
                  f"{result['seconds_per_update']:>9.2f} {result['compile_seconds']:>10.1f} "
                  f"{result['peak_rss_gb']:>12.2f}  {' '.join(overrides) or '-'}", flush=True)


if __name__ == "__main__":
    main()
