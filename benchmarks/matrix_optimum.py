"""How many of 10 seeds end at a matrix game's optimum, per method: the paper's Fig. 1 argument
(`matrix:fig1`, optimum (B, B)) and the penalty game (`matrix:penalty`, optima (0,0), (2,2)).

    python benchmarks/matrix_optimum.py [--env matrix:penalty] [--method cmat --method mat ...]
        [--steps N] [--seeds 10] [--set KEY=VALUE ...]

Every method trains with the same budget, seeds and the matrix suite's settings (16 envs x 25
steps, 5 epochs, cmat.envs.suites; --steps defaults to the suite's budget), otherwise with its
own defaults; `--set` applies to all of them. The greedy joint action of each seed is printed.
"""

from __future__ import annotations

import argparse

from cmat.envs.suites import MATRIX_BUDGET
from cmat.errors import CmatError
from cmat.experiments.matrix_games import train_and_count_optimum
from cmat.resolve import load_config

METHODS: dict[str, list[str]] = {
    "cmat": ["algo=cmat"],
    "cmat-categorical": ["algo=cmat", "cmat.consensus_policy=categorical"],
    "cmat-gaussian": ["algo=cmat", "cmat.consensus_policy=gaussian"],
    "mat": ["algo=mat"],
    "pmat": ["algo=pmat"],
    "triple_bert": ["algo=triple_bert"],
    "mappo": ["algo=mappo"],
    "happo": ["algo=happo"],
    "sable": ["algo=sable"],
    "ff_sable": ["algo=ff_sable"],
}
"""Method label -> config overrides."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="matrix:fig1", choices=["matrix:fig1", "matrix:penalty"])
    parser.add_argument("--method", choices=list(METHODS), action="append")
    parser.add_argument("--steps", type=int, default=MATRIX_BUDGET)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    print(f"{args.env}, {args.seeds} seeds x {args.steps} steps, the matrix suite's settings"
          + (f", {' '.join(args.set)}" if args.set else ""))
    print(f"{'method':<17} {'at optimum':>10}  greedy joint actions")
    for method in args.method or list(METHODS):
        config = load_config(overrides=[
            f"env={args.env}", *METHODS[method], f"total_steps={args.steps}",
            f"seeds={args.seeds}", f"log_interval={max(1, args.steps // 400)}", *args.set,
        ])
        try:
            count, joint = train_and_count_optimum(config)
        except CmatError as error:
            print(f"{method:<17} unavailable: {error}")
            continue
        actions = " ".join("".join(map(str, a)) for a in joint)
        print(f"{method:<17} {count:>7}/{args.seeds}  {actions}", flush=True)


if __name__ == "__main__":
    main()
