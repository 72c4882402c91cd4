"""Training steps/s and peak memory as the team grows: CMAT (m = n, and m fixed), MAT, MAPPO.

    python benchmarks/agent_scaling.py --out DIR [--teams 3m 8m 25m 27m_vs_30m 50m 100m]
        [--lines cmat mat ...] [--envs 8] [--rollout 25] [--updates 2] [--merge OLD.json ...]

Every team is a SMAX map (`smax:Nm` beyond SMAX's own: N marines a side, built with SMAX's
scenario API). One config for every point: the reference PPO settings (15 epochs, one
minibatch) with `--envs` environments × `--rollout` steps per update. Each point is one fresh
process: it compiles a chunk of `--updates` updates, times a second chunk (training steps/s,
all of one seed's env steps over wall time) and reports the process's peak resident memory
(which includes compilation). CMAT's decoder runs m iterations, m = n by default; the
'cmat m=4' line fixes m = 4 to show what the knob buys. Writes DIR/agent_scaling.png,
DIR/agent_scaling.md and DIR/agent_scaling.json (the points) and prints the table. `--merge`
adds the points of earlier runs' JSON files (this run's points replace theirs), so one table
can gather points that took several sessions (at the same --envs/--rollout/--updates); the
table names the run (output directory name) each row's points came from.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

LINES = {
    "cmat": ("cmat", []),
    "cmat m=4": ("cmat", ["network.consensus_iterations=4"]),
    "mat": ("mat", []),
    "mappo": ("mappo", []),
}

POINT = r"""
import json, resource, sys, time
import jax
from cmat.resolve import load_config
from cmat.runners.trainer import JaxTrainer
env, algo, envs, rollout, updates, *extra = sys.argv[1:]
config = load_config(overrides=[f"env=smax:{env}", f"algo={algo}", f"num_envs={envs}",
                                f"rollout_length={rollout}", f"log_interval={updates}", *extra])
trainer = JaxTrainer(config)
state = trainer.init()
state, _ = trainer.train_chunk(state)
jax.block_until_ready(state.learner.params)
start = time.perf_counter()
state, _ = trainer.train_chunk(state)
jax.block_until_ready(state.learner.params)
seconds = time.perf_counter() - start
print(json.dumps({"n": trainer.env_spec.num_agents,
                  "sps": int(updates) * config.steps_per_update / seconds,
                  "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def measure(team: str, algo: str, extra: list[str], envs: int, rollout: int,
            updates: int) -> dict[str, Any] | str:
    """One point in its own process; the error's last line where it failed (e.g. memory)."""
    done = subprocess.run(
        [sys.executable, "-c", POINT, team, algo, str(envs), str(rollout), str(updates), *extra],
        capture_output=True, text=True, check=False, env={**os.environ},
    )
    if done.returncode != 0:
        return (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1][:120]
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--teams", nargs="+",
                        default=["3m", "8m", "25m", "27m_vs_30m", "50m", "100m"])
    parser.add_argument("--lines", nargs="+", default=list(LINES), choices=list(LINES))
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--rollout", type=int, default=25)
    parser.add_argument("--updates", type=int, default=2)
    parser.add_argument("--merge", type=Path, nargs="*", default=[],
                        help="agent_scaling.json files of earlier runs to include")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[str, dict[str, Any] | str]] = {}
    for path in args.merge:
        try:
            earlier = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            parser.error(f"--merge {path}: {error}")
        for line, points in earlier.items():
            results.setdefault(line, {}).update(points)
    run = args.out.name
    for team in args.teams:
        for line in args.lines:
            algo, extra = LINES[line]
            point = measure(team, algo, extra, args.envs, args.rollout, args.updates)
            if not isinstance(point, str):
                point["run"] = run
            results.setdefault(line, {})[team] = point
            shown = point if isinstance(point, str) else (
                f"n={point['n']:.0f} {point['sps']:.0f} steps/s {point['peak_mb']:.0f} MB")
            print(f"{team:12} {line:10} {shown}", flush=True)
    (args.out / "agent_scaling.json").write_text(json.dumps(results, indent=1))
    write(results, args)


def write(results: dict[str, dict[str, dict[str, Any] | str]], args: argparse.Namespace) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    header = (f"SMAX teams, {args.envs} envs × {args.rollout} steps per update, reference PPO "
              f"settings, one seed; training steps/s / peak resident MB per process")
    lines = [line for line in LINES if line in results]
    def agents(team: str) -> float:
        sizes = [p["n"] for line in lines if isinstance(p := results[line].get(team), dict)]
        return sizes[0] if sizes else float("inf")

    teams = sorted({team for points in results.values() for team in points}, key=agents)
    rows = ["| team | n | " + " | ".join(lines) + " | measured in |",
            "|---|---|" + "---|" * (len(lines) + 1)]
    for team in teams:
        points = [results[line].get(team, "not run") for line in lines]
        ns = [p["n"] for p in points if not isinstance(p, str)]
        cells = [p if isinstance(p, str) else f"{p['sps']:.0f} / {p['peak_mb']:.0f}"
                 for p in points]
        rows.append(f"| {team} | {ns[0]:.0f} | " if ns else f"| {team} | ? | ")
        runs = sorted({str(p.get("run", "?")) for p in points if isinstance(p, dict)})
        rows[-1] += " | ".join(cells) + f" | {', '.join(runs)} |"
    table = "\n".join([header, "", *rows]) + "\n"
    (args.out / "agent_scaling.md").write_text(table)
    print(table)
    figure, (speed, memory) = plt.subplots(1, 2, figsize=(10, 4))
    for line in lines:
        points = sorted((p["n"], p["sps"], p["peak_mb"]) for p in results[line].values()
                        if not isinstance(p, str))
        if points:
            n, sps, mb = zip(*points, strict=True)
            speed.plot(n, sps, marker="o", label=line)
            memory.plot(n, mb, marker="o", label=line)
    for axis, label in ((speed, "training steps/s"), (memory, "peak resident memory (MB)")):
        axis.set(xscale="log", yscale="log", xlabel="agents per team n", ylabel=label)
        axis.grid(alpha=0.3)
    speed.legend()
    figure.suptitle(header, fontsize=8)
    figure.tight_layout()
    figure.savefig(args.out / "agent_scaling.png", dpi=120)


if __name__ == "__main__":
    main()
