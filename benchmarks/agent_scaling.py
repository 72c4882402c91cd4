"""Training steps/s and peak memory as the team grows: CMAT (m = n, and m fixed), MAT, Sable,
MAPPO, HAPPO.

    python benchmarks/agent_scaling.py --out DIR [--teams 3m 8m 25m 27m_vs_30m 50m 100m]
        [--lines cmat mat ...] [--envs 8] [--rollout 25] [--updates 2] [--repeats 1]
        [--merge OLD.json ...]

Every team is a SMAX map (`smax:Nm` beyond SMAX's own: N marines a side, built with SMAX's
scenario API), or any environment id with its suite (`dispatch:grid-1000-mid`). One config
for every point: the reference PPO settings (15 epochs, one
minibatch) with `--envs` environments × `--rollout` steps per update. Each point is one fresh
process: it compiles a chunk of `--updates` updates, times `--repeats` further chunks (training
steps/s, all of one seed's env steps over wall time; the point's figure is their median) and
reports its peak memory: the accelerator allocator's peak on a GPU, else the process's peak
resident memory (which includes compilation). CMAT's decoder runs m
iterations: the 'cmat' line sets the paper's m = n (cmat's own default fixes m for teams above
32 agents, `cmat.algorithms.cmat.options.LARGE_TEAM`, to m = 2, the 'cmat m=2' line); the
'cmat m=4' line fixes m = 4 to show what the knob buys. `k=16`: the encoder's agents attend
through 16 inducing points (`inducing_points`); 'sable' is the recurrent Sable.

Growth with the team: for each line, the exponent b of time per env step ∝ n^b is the
least-squares slope of log(1 / steps/s) on log n over the line's points, and for every other
line the difference of its exponent from MAT's over the teams both have: whether CMAT's time
per step grows faster than MAT's. Their 95% intervals come from a bootstrap over the timed
chunks (each point's chunk times resampled, the median refitted; `--repeats` ≥ 2 gives an
interval, one chunk per point gives the exponent alone): they measure timing noise, not how
well a power law fits.

Writes DIR/agent_scaling.json (the points, after each one, so that a run cut short keeps what
it measured), then DIR/agent_scaling.png and DIR/agent_scaling.md, and prints the table and
exponents. `--merge` adds the points of earlier runs' JSON files (this
run's points replace theirs), so one table can gather points that took several sessions (at
the same --envs/--rollout/--updates); the table names the run (output directory name) each
row's points came from. `--teams` with no names measures nothing and only redraws the merged
points (and refits their exponents). `--compile-only` compiles every point's program and
measures nothing: with JAX's persistent compilation cache set (`JAX_COMPILATION_CACHE_DIR`),
the points can be compiled side by side first and timed one at a time after
(`benchmarks/gpu.sh`).
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
    "cmat": ("cmat", ["cmat.consensus_iterations=n"]),
    "cmat m=2": ("cmat", ["cmat.consensus_iterations=2"]),
    "cmat m=4": ("cmat", ["cmat.consensus_iterations=4"]),
    "cmat m=4 blocks": ("cmat", ["cmat.consensus_iterations=4",
                                 "cmat.attention_block=128"]),
    "cmat m=2 k=16": ("cmat", ["cmat.consensus_iterations=2", "cmat.inducing_points=16"]),
    "mat": ("mat", []),
    "mat k=16": ("mat", ["mat.inducing_points=16"]),
    "sable": ("sable", []),
    "triple_bert": ("triple_bert", []),
    "mappo": ("mappo", []),
    "happo": ("happo", []),
    "env only": ("env", []),
}
"""Lines: name -> (algorithm, config overrides). `env only` steps the environment alone with
uniformly random legal actions in one compiled scan over the same envs x rollout: the
environment's own share of a training step."""

Points = dict[str, dict[str, Any] | str]
"""One line's points by team: the measured point, or the error it failed with."""

POINT = r"""
import json, resource, statistics, sys, time
import jax
from cmat.resolve import load_config
from cmat.runners.trainer import JaxTrainer
env, algo, envs, rollout, updates, repeats, *extra = sys.argv[1:]
env_id = env if ":" in env else f"smax:{env}"
config = load_config(overrides=[f"env={env_id}", f"algo={'mappo' if algo == 'env' else algo}",
                                f"num_envs={envs}", f"rollout_length={rollout}",
                                f"log_interval={updates}", *extra])
if algo == "env":
    import jax.numpy as jnp
    from cmat.envs import make_env
    marl = make_env(env_id, **config.env_kwargs)

    def steps(key):
        state, timestep = jax.vmap(marl.reset)(jax.random.split(key, int(envs)))
        def one(carry, key):
            state, timestep = carry
            keys = jax.random.split(key, int(envs))
            logits = jnp.where(timestep.action_mask, 0.0, -1e9)
            actions = jax.vmap(lambda k, l: jax.random.categorical(k, l))(keys, logits)
            state, timestep = jax.vmap(marl.step)(keys, state, actions)
            return (state, timestep), timestep.reward.sum()
        return jax.lax.scan(one, (state, timestep),
                            jax.random.split(key, int(rollout) * int(updates)))[1]

    program = jax.jit(steps)
    start = time.perf_counter()
    jax.block_until_ready(program(jax.random.PRNGKey(0)))
    first = time.perf_counter() - start
    runs = []
    for repeat in range(max(1, int(repeats))):
        start = time.perf_counter()
        jax.block_until_ready(program(jax.random.PRNGKey(repeat + 1)))
        runs.append(int(envs) * int(rollout) * int(updates) / (time.perf_counter() - start))
    print(json.dumps({"n": marl.spec.num_agents, "sps": statistics.median(runs),
                      "sps_runs": runs, "compile_s": first - statistics.median(
                          [int(envs) * int(rollout) * int(updates) / r for r in runs]),
                      "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "device_peak_mb": None}))
    sys.exit()
trainer = JaxTrainer(config)
state = trainer.init()
if int(repeats) == 0:
    start = time.perf_counter()
    trainer.compile_chunk(state)
    print(json.dumps(f"compiled in {time.perf_counter() - start:.1f} s"))
    sys.exit()
start = time.perf_counter()
state, _ = trainer.train_chunk(state)
jax.block_until_ready(state.learner.params)
first = time.perf_counter() - start
runs = []
for _ in range(int(repeats)):
    start = time.perf_counter()
    state, _ = trainer.train_chunk(state)
    jax.block_until_ready(state.learner.params)
    runs.append(int(updates) * config.steps_per_update / (time.perf_counter() - start))
device_peaks = [(d.memory_stats() or {}).get("peak_bytes_in_use", 0) for d in jax.local_devices()]
chunk = int(updates) * config.steps_per_update / statistics.median(runs)
print(json.dumps({"n": trainer.env_spec.num_agents, "sps": statistics.median(runs),
                  "sps_runs": runs, "compile_s": first - chunk,
                  "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "device_peak_mb": (max(device_peaks) / 2**20
                                     if jax.default_backend() != "cpu" else None)}))
"""


def measure(team: str, algo: str, extra: list[str], envs: int, rollout: int,
            updates: int, repeats: int, timeout: float | None = None) -> dict[str, Any] | str:
    """One point in its own process; the error's last line where it failed (e.g. memory) or
    that it ran past `timeout` seconds, and with `repeats` 0 the chunk's compile time, as
    text. A point's `compile_s` is its first chunk's time less a timed chunk's."""
    try:
        done = subprocess.run(
            [sys.executable, "-c", POINT, team, algo, str(envs), str(rollout), str(updates),
             str(repeats), *extra],
            capture_output=True, text=True, check=False, env={**os.environ}, timeout=timeout,
        )
    except subprocess.TimeoutExpired:
        return f"did not finish in {timeout:.0f} s"
    if done.returncode != 0:
        return (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1][:120]
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--teams", nargs="*",
                        default=["3m", "8m", "25m", "27m_vs_30m", "50m", "100m"])
    parser.add_argument("--lines", nargs="+", default=list(LINES), choices=list(LINES))
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--rollout", type=int, default=25)
    parser.add_argument("--updates", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=1,
                        help="timed chunks per point (median reported; >= 2 for intervals)")
    parser.add_argument("--point-timeout", type=float, metavar="SECONDS",
                        help="give up a point after this long (it is reported as such)")
    parser.add_argument("--compile-only", action="store_true",
                        help="compile each point's training chunk and stop (with "
                             "JAX_COMPILATION_CACHE_DIR set, later runs load it)")
    parser.add_argument("--merge", type=Path, nargs="*", default=[],
                        help="agent_scaling.json files of earlier runs to include")
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error(f"--repeats must be at least 1, got {args.repeats}")
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict[str, Points] = {}
    for path in args.merge:
        try:
            earlier = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            parser.error(f"--merge {path}: {error}")
        for line, points in earlier.items():
            results.setdefault(line, {}).update(points)
    run = args.out.name
    machine = describe(with_matmul=False)
    print(machine, flush=True)
    for team in args.teams:
        for line in args.lines:
            algo, extra = LINES[line]
            point = measure(team, algo, extra, args.envs, args.rollout, args.updates,
                            0 if args.compile_only else args.repeats, args.point_timeout)
            if args.compile_only:
                print(f"{team:12} {line:10} {point}", flush=True)
                continue
            if not isinstance(point, str):
                point["run"], point["machine"] = run, machine
            results.setdefault(line, {})[team] = point
            shown = point if isinstance(point, str) else (
                f"n={point['n']:.0f} {rate(point['sps'])} steps/s {memory_mb(point):.0f} MB")
            print(f"{team:12} {line:10} {shown}", flush=True)
            (args.out / "agent_scaling.json").write_text(json.dumps(results, indent=1))
    if not args.compile_only:
        write(results, args)


def growth_exponent(points: list[dict[str, Any]], rng: Any,
                    draws: int = 2000) -> tuple[float, Any]:
    """b of time per env step ∝ n^b over `points` (least squares on log-log), and the bootstrap
    draws of b (each point's chunk times resampled with replacement, their median refitted).
    Points of earlier runs without per-chunk times count as one chunk."""
    import numpy as np

    log_n = np.log([point["n"] for point in points])
    runs = [np.asarray(point.get("sps_runs", [point["sps"]])) for point in points]

    def slope(sps: Any) -> float:
        return float(np.polyfit(log_n, -np.log(sps), 1)[0])

    estimate = slope(np.array([np.median(r) for r in runs]))
    resampled = np.array([[np.median(rng.choice(r, size=len(r))) for r in runs]
                          for _ in range(draws)])
    return estimate, np.array([slope(row) for row in resampled])


def exponents(results: dict[str, Points], lines: list[str]) -> list[str]:
    """One line of text per algorithm line: its growth exponent, and for every other line the
    difference from MAT's exponent (the first line's without MAT) over their common teams,
    with 95% bootstrap intervals where a point has more than one timed chunk."""
    import numpy as np

    rng = np.random.default_rng(0)
    measured = {line: {team: p for team, p in results[line].items() if isinstance(p, dict)}
                for line in lines}

    def interval(draws: Any) -> str:
        low, high = np.percentile(draws, [2.5, 97.5])
        return "" if low == high else f" [{low:.2f}, {high:.2f}]"

    reference = "mat" if "mat" in lines else lines[0]
    text = []
    for line in lines:
        points = measured[line]
        if len(points) < 2:
            continue
        b, draws = growth_exponent(list(points.values()), rng)
        text.append(f"{line}: time per step ∝ n^{b:.2f}{interval(draws)} ({len(points)} teams)")
        common = [team for team in points if team in measured[reference]]
        if line != reference and len(common) >= 2:
            b_line, draws_line = growth_exponent([points[t] for t in common], rng)
            b_reference, draws_reference = growth_exponent(
                [measured[reference][t] for t in common], rng)
            text.append(f"  {line} − {reference}: {b_line - b_reference:+.2f}"
                        f"{interval(draws_line - draws_reference)} over {len(common)} teams")
    return text


def rate(steps_per_second: float) -> str:
    """Steps/s for a table: whole numbers from 10 up, two significant digits below."""
    return f"{steps_per_second:.0f}" if steps_per_second >= 10 else f"{steps_per_second:.2g}"


def memory_mb(point: dict[str, Any]) -> float:
    """The accelerator allocator's peak where the point ran on one, else peak resident memory."""
    return float(point.get("device_peak_mb") or point["peak_mb"])


def write(results: dict[str, Points], args: argparse.Namespace) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    header = (f"Teams (SMAX `Nm` or an env id), {args.envs} envs × {args.rollout} steps per "
              f"update, reference PPO settings, one seed; training steps/s / peak MB "
              f"(accelerator memory where the point ran on one, else the process's resident "
              f"memory) / compile s (the first chunk less a timed one); `env only`: the "
              f"environment stepped with random legal actions")
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
        cells = [p if isinstance(p, str) else
                 f"{rate(p['sps'])} / {memory_mb(p):.0f}"
                 + (f" / {p['compile_s']:.0f}" if "compile_s" in p else "") for p in points]
        rows.append(f"| {team} | {ns[0]:.0f} | " if ns else f"| {team} | ? | ")
        runs = sorted({str(p.get("run", "?")) for p in points if isinstance(p, dict)})
        rows[-1] += " | ".join(cells) + f" | {', '.join(runs)} |"
    growth = exponents(results, lines)
    machines = sorted({f"- {p['run']}: {p['machine']}" for points in results.values()
                       for p in points.values() if isinstance(p, dict) and "machine" in p})
    table = "\n".join([header, "", *rows, "", *growth, "", *machines]) + "\n"
    (args.out / "agent_scaling.md").write_text(table)
    print(table)
    figure, (speed, memory) = plt.subplots(1, 2, figsize=(10, 4))
    for line in lines:
        curve = sorted((p["n"], p["sps"], memory_mb(p)) for p in results[line].values()
                       if not isinstance(p, str))
        if curve:
            n, sps, mb = zip(*curve, strict=True)
            speed.plot(n, sps, marker="o", label=line)
            memory.plot(n, mb, marker="o", label=line)
    for axis, label in ((speed, "training steps/s"), (memory, "peak memory (MB)")):
        axis.set(xscale="log", yscale="log", xlabel="agents per team n", ylabel=label)
        axis.grid(alpha=0.3)
    speed.legend()
    figure.suptitle(header, fontsize=8)
    figure.tight_layout()
    figure.savefig(args.out / "agent_scaling.png", dpi=120)


if __name__ == "__main__":
    main()
