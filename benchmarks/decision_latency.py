"""Decision latency: one greedy team decision, as a fleet operator would call it.

    python benchmarks/decision_latency.py --out DIR [--teams 10 100 300 1000]
        [--lines "cmat m=5" mat sable mappo ...] [--batches 1 64] [--calls 50] [--timeout 600]
        [--merge OLD.json ...]

Every team is a dispatch fleet (`dispatch:grid-N-mid`, one agent per vehicle; the observation
does not grow with N). Each point (line × team) is one fresh process: it builds the line's
algorithm at its suite settings with fresh parameters, takes `--batches` teams' observations
and masks from the environment's reset, compiles the greedy decision (`Algorithm.greedy`,
jitted; a recurrent line's `greedy_with_memory` from its initial memory) and reports the
compile seconds, then calls it `--calls` times (after one warm-up call) and reports the median
and 99th-percentile milliseconds per call (a call decides every vehicle of every team of the
batch). A point that fails or passes `--timeout` seconds (compile included) is reported with
the reason.

Lines: 'cmat m=n' is the paper's setting (m = number of agents), 'cmat m=2' what cmat runs on
teams above 32 agents when m is unset (`cmat.algorithms.cmat.options.LARGE_TEAM`; the dispatch
suite's setting since 2026-12-08), 'cmat m=2 k=16' the same with inducing points, 'cmat m=5'
the CMAT authors' ride-sharing setting (consensus length 5 on 1,000 vehicles); 'sable' is the
recurrent Sable (one decision from its initial memory), 'sable (feed-forward)' Mava's ff_sable
(results dated before 2026-12-06 call the feed-forward one 'sable'); 'mat' and both Sables
decode the agents one after another, 'mappo' is one MLP per agent (fully parallel).

Writes DIR/decision_latency.json after each point (a run cut short keeps what it measured),
then DIR/decision_latency.png and DIR/decision_latency.md, and prints the table with the
machine's line and, at the largest team every line reached, each line's median against
'cmat m=2'.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from machine import describe

LINES = {
    "cmat m=n": ("cmat", ["cmat.consensus_iterations=n"]),
    "cmat m=2": ("cmat", ["cmat.consensus_iterations=2"]),
    "cmat m=5": ("cmat", ["cmat.consensus_iterations=5"]),
    "cmat m=2 k=16": ("cmat", ["cmat.consensus_iterations=2", "cmat.inducing_points=16"]),
    "mat": ("mat", []),
    "sable": ("sable", []),
    "sable (feed-forward)": ("ff_sable", []),
    "mappo": ("mappo", []),
}
REFERENCE = "cmat m=2"

POINT = r"""
import json, statistics, sys, time
import jax, jax.numpy as jnp, numpy as np
from cmat.algorithms import build_algorithm
from cmat.algorithms.base import is_recurrent, with_memory
from cmat.envs import make_env
from cmat.resolve import load_config
team, algo, batch, calls, *extra = sys.argv[1:]
batch, calls = int(batch), int(calls)
config = load_config(overrides=[f"env=dispatch:grid-{team}-mid", f"algo={algo}", *extra])
env = make_env(config.env, **config.env_kwargs)
algorithm = build_algorithm(config.algo, config.network, env.spec, config.ppo, config.options)
_, timestep = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(1), batch))
params = algorithm.init(jax.random.PRNGKey(0), timestep.obs[0], timestep.action_mask[0])
obs, mask = timestep.obs, timestep.action_mask
if is_recurrent(algorithm):
    stepper = with_memory(algorithm)
    memory = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)),
                          stepper.initial_memory())
    start = jnp.ones(batch, bool)
    decide = jax.jit(lambda p, o, m: jax.vmap(stepper.greedy_with_memory,
                                              (None, 0, 0, 0, 0))(p, memory, o, m, start)[0])
else:
    decide = jax.jit(lambda p, o, m: jax.vmap(algorithm.greedy, (None, 0, 0))(p, o, m))
begin = time.perf_counter()
compiled = decide.lower(params, obs, mask).compile()
compile_s = time.perf_counter() - begin
jax.block_until_ready(compiled(params, obs, mask))
times = []
for _ in range(calls):
    begin = time.perf_counter()
    jax.block_until_ready(compiled(params, obs, mask))
    times.append((time.perf_counter() - begin) * 1000)
print(json.dumps({"n": env.spec.num_agents, "batch": batch, "compile_s": compile_s,
                  "median_ms": statistics.median(times),
                  "p99_ms": float(np.percentile(times, 99)), "calls": calls}))
"""


def measure(team: int, line: str, batch: int, calls: int, timeout: int) -> dict[str, Any] | str:
    """One point in its own process: its figures, or why it has none (the error's last line,
    or the timeout)."""
    algo, extra = LINES[line]
    try:
        done = subprocess.run(
            [sys.executable, "-c", POINT, str(team), algo, str(batch), str(calls), *extra],
            capture_output=True, text=True, check=False, env={**os.environ}, timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"over {timeout} s (compile included)"
    if done.returncode != 0:
        return (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1][:120]
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


Points = dict[str, dict[str, dict[str, Any] | str]]
"""line -> 'TEAM/BATCH' -> the measured point or why it has none."""


def table(points: Points, teams: list[int], batches: list[int]) -> list[str]:
    """A markdown table: per team and batch, each line's median / p99 ms and compile s."""
    lines = [name for name in LINES if name in points]
    out = ["| team | batch | " + " | ".join(lines) + " |", "|---" * (2 + len(lines)) + "|"]
    for team in teams:
        for batch in batches:
            cells = []
            for name in lines:
                point = points[name].get(f"{team}/{batch}")
                if point is None:
                    cells.append("—")
                elif isinstance(point, str):
                    cells.append(f"failed: {point}")
                else:
                    cells.append(f"{point['median_ms']:.3g} / {point['p99_ms']:.3g} ms "
                                 f"(compile {point['compile_s']:.1f} s)")
            out.append(f"| {team} | {batch} | " + " | ".join(cells) + " |")
    return out


def ratios(points: Points, teams: list[int], batches: list[int]) -> list[str]:
    """Per batch, at the largest team where the reference line and another line both have a
    point: that line's median over the reference's."""
    out = []
    for batch in batches:
        for name in LINES:
            if name == REFERENCE or name not in points or REFERENCE not in points:
                continue
            both = [t for t in teams if isinstance(points[name].get(f"{t}/{batch}"), dict)
                    and isinstance(points[REFERENCE].get(f"{t}/{batch}"), dict)]
            if both:
                team = max(both)
                other = points[name][f"{team}/{batch}"]
                ours = points[REFERENCE][f"{team}/{batch}"]
                assert isinstance(other, dict) and isinstance(ours, dict)
                out.append(f"batch {batch}, n = {team}: {name} / {REFERENCE} = "
                           f"{other['median_ms'] / ours['median_ms']:.2f}")
    return out


def draw(points: Points, teams: list[int], batches: list[int], path: Path, machine: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, len(batches), figsize=(5.5 * len(batches), 4.2),
                                squeeze=False)
    for ax, batch in zip(axes[0], batches):
        for name in LINES:
            measured = [(t, p) for t in teams
                        if isinstance(p := points.get(name, {}).get(f"{t}/{batch}"), dict)]
            if measured:
                ax.plot([t for t, _ in measured], [p["median_ms"] for _, p in measured],
                        marker="o", label=name)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("vehicles (agents) per team")
        ax.set_ylabel("median ms per greedy decision")
        ax.set_title(f"batch of {batch} team(s)", fontsize="medium")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize="small")
    figure.suptitle(f"decision latency, dispatch fleets; {machine}", fontsize="x-small")
    figure.tight_layout()
    figure.savefig(path, dpi=150)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--teams", type=int, nargs="*", default=[10, 100, 300, 1000])
    parser.add_argument("--lines", nargs="+", default=list(LINES), choices=list(LINES))
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    parser.add_argument("--calls", type=int, default=50)
    parser.add_argument("--timeout", type=int, default=600,
                        help="seconds per point, compile included")
    parser.add_argument("--merge", type=Path, nargs="*", default=[],
                        help="decision_latency.json files of earlier runs to include")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    machine = describe(with_matmul=False)
    points: Points = {}
    for old in args.merge:
        for name, by_point in json.loads(old.read_text())["points"].items():
            points.setdefault(name, {}).update(by_point)
    record = args.out / "decision_latency.json"
    for team in args.teams:
        for name in args.lines:
            for batch in args.batches:
                point = measure(team, name, batch, args.calls, args.timeout)
                points.setdefault(name, {})[f"{team}/{batch}"] = point
                print(f"{name:18s} n={team:5d} batch={batch:3d}: {point}", flush=True)
                record.write_text(json.dumps({"machine": machine, "calls": args.calls,
                                              "points": points}, indent=1))
    teams = sorted({int(key.split("/")[0]) for by_point in points.values() for key in by_point})
    batches = sorted({int(key.split("/")[1]) for by_point in points.values() for key in by_point})
    text = [f"# Decision latency ({machine})", "",
            "median / 99th-percentile milliseconds per greedy decision of every vehicle of "
            "the batch's teams, and compile seconds; `benchmarks/decision_latency.py`", "",
            *table(points, teams, batches), "", *[f"- {line}" for line in
                                                  ratios(points, teams, batches)]]
    (args.out / "decision_latency.md").write_text("\n".join(text) + "\n")
    draw(points, teams, batches, args.out / "decision_latency.png", machine)
    print("\n".join(text))


if __name__ == "__main__":
    main()
