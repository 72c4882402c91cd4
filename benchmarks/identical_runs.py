"""Whether two checkouts of cmat train every algorithm to the same numbers: a refactor's check.

    python benchmarks/identical_runs.py --before ../cmat-old --after . --out /tmp/identical

Each checkout (its own code on `PYTHONPATH`) trains each algorithm briefly on one SMAX map with
the same command (`--set`, `--steps`), and the two `metrics.csv` files (training rows: losses,
diagnostics, gradient norms; evaluation rows: returns, win rates) are compared value by value
as text. A refactor that changes no computation prints `identical` for every algorithm; a
config key that exists in one checkout only must be left out of `--set`.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
from pathlib import Path

ALGOS = ("cmat", "mat", "pmat", "triple_bert", "mappo", "happo", "sable", "ff_sable")
SETTINGS = ("num_envs=4", "rollout_length=50", "network.n_embd=16", "eval_episodes=2",
            "log_interval=1", "ppo.epochs=2")


def train(checkout: Path, algo: str, env: str, steps: int, out: Path) -> None:
    """One short run of `algo` with `checkout`'s code into `out`; SystemExit if it fails."""
    environment = {**os.environ, "PYTHONPATH": str(checkout.resolve())}
    command = [sys.executable, "-m", "cmat", "train", "--env", env, "--algo", algo,
               "--steps", str(steps), "--out", str(out), "--set", *SETTINGS]
    done = subprocess.run(command, env=environment, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{checkout} {algo}: {done.stderr.strip().splitlines()[-1]}")


def rows(path: Path) -> list[dict[str, str]]:
    with path.open() as file:
        return list(csv.DictReader(file))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True)
    parser.add_argument("--after", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--env", default="smax:3m")
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--algo", action="append", choices=ALGOS)
    args = parser.parse_args()
    print(f"| algorithm | rows | columns | {args.before} vs {args.after} |\n|---|---|---|---|")
    different = 0
    for algo in args.algo or ALGOS:
        for name, checkout in (("before", args.before), ("after", args.after)):
            train(checkout, algo, args.env, args.steps, args.out / name / algo)
        before, after = (rows(args.out / name / algo / "metrics.csv")
                         for name in ("before", "after"))
        columns = [key for key in before[0] if key in after[0]]
        changed = [(index, key) for index, (old, new) in enumerate(zip(before, after))
                   for key in columns if old[key] != new[key]]
        same = len(before) == len(after) and set(before[0]) == set(after[0]) and not changed
        different += not same
        verdict = "identical" if same else f"differ (first: row {changed[:1]})"
        print(f"| {algo} | {len(before)} | {len(columns)} | {verdict} |")
    sys.exit(1 if different else 0)


if __name__ == "__main__":
    main()
