"""The paper's Fig. 1 argument, measured: how many of 10 seeds end at the optimum (B, B).

    python benchmarks/fig1_optimum.py [--algo cmat --algo mat ...] [--steps 12000]

Every algorithm trains `matrix:fig1` with the same budget, seeds and rollout settings, otherwise
with its own defaults from cmat.config; the greedy joint action of each seed is reported.
"""

from __future__ import annotations

import argparse

from cmat.config import ALGORITHMS, load_config
from cmat.errors import CmatError
from cmat.experiments.matrix_games import train_and_count_optimum


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algo", choices=ALGORITHMS, action="append")
    parser.add_argument("--steps", type=int, default=12000)
    parser.add_argument("--seeds", type=int, default=10)
    args = parser.parse_args()
    print(f"matrix:fig1, {args.seeds} seeds x {args.steps} steps, 16 envs x 25 steps, 5 epochs")
    print(f"{'algo':<12} {'at (B,B)':>9}  greedy joint actions (0 = A, 1 = B)")
    for algo in args.algo or ALGORITHMS:
        config = load_config(overrides=[
            "env=matrix:fig1", f"algo={algo}", f"total_steps={args.steps}", "num_envs=16",
            "rollout_length=25", "ppo.epochs=5", f"seeds={args.seeds}",
            f"log_interval={args.steps // 400}",
        ])
        try:
            count, joint = train_and_count_optimum(config, optimum=(1, 1))
        except CmatError as error:
            print(f"{algo:<12} unavailable: {error}")
            continue
        print(f"{algo:<12} {count:>6}/{args.seeds}  {' '.join(''.join(map(str, a)) for a in joint)}",
              flush=True)


if __name__ == "__main__":
    main()
