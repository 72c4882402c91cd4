"""Measures the target-critic soft-update rate τ (the paper gives none) on two tasks.

    python benchmarks/target_tau.py --taus 1.0 0.1 0.01

matrix:fig1: how many of 10 seeds end with the greedy joint action at the optimum (B, B).
smax:3m: greedy return and win rate (mean ± std over seeds, 64 episodes each) after a fixed budget.
"""

from __future__ import annotations

import argparse

import numpy as np

from cmat.experiments.matrix_games import train_and_count_optimum
from cmat.resolve import load_config
from cmat.runners.trainer import JaxTrainer


def fig1_optimum_count(tau: float, steps: int) -> int:
    config = load_config(overrides=[
        "env=matrix:fig1", f"total_steps={steps}", "num_envs=16", "rollout_length=25",
        "ppo.epochs=5", "seeds=10", f"log_interval={steps // 400}", f"ppo.target_tau={tau}",
    ])
    return train_and_count_optimum(config)[0]


def smax_result(tau: float, steps: int, seeds: int) -> dict[str, np.ndarray]:
    config = load_config(overrides=[
        "env=smax:3m", f"total_steps={steps}", f"seeds={seeds}", f"ppo.target_tau={tau}",
        f"log_interval={steps // 3200}",
    ])
    trainer = JaxTrainer(config)
    state, _ = trainer.train_chunk(trainer.init())
    return trainer.evaluate(state, 64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--taus", type=float, nargs="+", default=[1.0, 0.1, 0.01])
    parser.add_argument("--fig1-steps", type=int, default=12000)
    parser.add_argument("--smax-steps", type=int, default=160000)
    parser.add_argument("--smax-seeds", type=int, default=3)
    args = parser.parse_args()
    print(f"fig1: 10 seeds x {args.fig1_steps} steps; smax:3m: {args.smax_seeds} seeds x "
          f"{args.smax_steps} steps, default config otherwise")
    print(f"{'tau':>6} {'fig1 optimum /10':>17} {'3m return':>14} {'3m win rate':>14}")
    for tau in args.taus:
        optimum = fig1_optimum_count(tau, args.fig1_steps)
        smax = smax_result(tau, args.smax_steps, args.smax_seeds)
        ret, win = smax["episode_return"], smax["win_rate"]
        print(f"{tau:>6} {optimum:>17} {ret.mean():>7.2f} ± {ret.std():<4.2f} "
              f"{win.mean():>7.2f} ± {win.std():<4.2f}", flush=True)


if __name__ == "__main__":
    main()
