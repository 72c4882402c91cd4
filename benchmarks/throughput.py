"""Where CMAT's training time goes, and training steps/s of every algorithm.

    python benchmarks/throughput.py                       # CMAT breakdown, SMAX 3m and 3s5z_vs_3s6z
    python benchmarks/throughput.py --envs 128 --scenarios smax:3m
    python benchmarks/throughput.py --compare-algorithms  # every algorithm on 3s5z_vs_3s6z
    python benchmarks/throughput.py --compare-algorithms --algo cmat --algo mat --preset mava
    python benchmarks/throughput.py --compare-algorithms --algo sable \
        --algo sable:ppo.epochs=4                    # an algorithm with its own overrides

Breakdown (one process, default config but `--envs` environments): env-only steps/s (random
legal actions in the same kind of scan), collection steps/s (CMAT acting + env, no update), full
training steps/s (collect, target values, GAE, PPO epochs), and the update's achieved FLOP/s
beside a large matmul's FLOP/s measured in the same process. The update's FLOPs are XLA's cost
analysis of one compiled gradient step times epochs × minibatches: exact up to m = 16
consensus iterations, which are unrolled; above, the iterations are one scan
(`cmat.networks.layers.SCAN_LENGTH`), whose body the cost analysis may count once,
so the FLOP/s figure is a lower bound there. Everything is timed after
compilation, fastest of `--repeats` runs. Env-only and collection runs alternate, so a change in
the shared machine's load hits both; besides the ratio of the fastest runs, the table gives the
median and range of the ratios of the `--repeats` alternating pairs. `XLA_FLAGS` from the
environment applies to every program and is printed in the header.

Algorithm comparison (one process per algorithm, each with its defaults from cmat.config;
`--algo ALGO:KEY=VALUE,...` adds overrides for that line alone, after `--set`'s):
training steps/s counting all seeds' environment steps, timed on the second chunk. The `mava`
preset is the configuration at which Mava's MAT was measured on this kind of machine
(about 169 steps/s and 13.2 GB peak on 3s5z_vs_3s6z on a slower machine; docs/speed.md compares
Mava's own MAT run beside cmat on one machine).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from machine import describe, matmul_gflops

from cmat.algorithms import algorithm_names

PRESETS: dict[str, list[str]] = {
    "reference": [],
    "mava": [
        "num_envs=128", "rollout_length=128", "network.n_block=3", "network.n_embd=128",
        "ppo.epochs=5", "ppo.num_minibatches=1",
    ],
}


def fastest(function: Callable[[], Any], repeats: int) -> float:
    import jax

    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function())
        times.append(time.perf_counter() - start)
    return min(times)


def compiled_flops(compiled: Any) -> float:
    analysis = compiled.cost_analysis()
    if isinstance(analysis, list):
        analysis = analysis[0]
    return float(analysis["flops"])


def breakdown(env_id: str, num_envs: int, repeats: int) -> dict[str, float]:
    """Env-only, collection, training steps/s and update FLOP/s of CMAT's default config."""
    import jax

    from cmat.envs.random_policy import random_rollout
    from cmat.resolve import load_config
    from cmat.runners import trainer as trainer_lib
    from cmat.runners.learner import make_batch
    from cmat.runners.learner import optimise as optimise_batch

    config = load_config(overrides=[f"env={env_id}", f"num_envs={num_envs}"])
    setup = trainer_lib.build_setup(config)
    steps = config.steps_per_update
    state = jax.jit(lambda key: trainer_lib.init_state(setup, key))(jax.random.PRNGKey(0))

    env_only = jax.jit(random_rollout(setup.collector.env, num_envs, config.rollout_length))
    params, key = state.learner.params, state.learner.rng
    collect = jax.jit(lambda envs: setup.collector.collect(params, envs, key))
    envs, _ = collect(state.envs)
    jax.block_until_ready(env_only(jax.random.PRNGKey(1)))
    env_only_times, collect_times = [], []
    for _ in range(repeats):
        env_only_times.append(fastest(lambda: env_only(jax.random.PRNGKey(1)), 1))
        collect_times.append(fastest(lambda: collect(envs), 1))
    env_only_s, collect_s = min(env_only_times), min(collect_times)
    pair_ratios = np.array(env_only_times) / np.array(collect_times)
    envs, rollout = collect(envs)

    learner = state.learner
    _, batch = jax.jit(lambda s, r: make_batch(setup.learner, s, r))(learner, rollout)
    optimise = jax.jit(lambda p, o, b, k: optimise_batch(setup.learner, p, o, b, k))
    key = jax.random.PRNGKey(2)
    jax.block_until_ready(optimise(learner.params, learner.opt_state, batch, key))
    update_s = fastest(lambda: optimise(learner.params, learner.opt_state, batch, key), repeats)
    minibatch = jax.tree.map(lambda x: x[: x.shape[0] // config.ppo.num_minibatches], batch)
    algorithm = setup.learner.algorithm
    gradient = jax.jit(jax.grad(lambda p, b: algorithm.loss(p, b, config.ppo)[0]))
    step_flops = compiled_flops(gradient.lower(learner.params, minibatch).compile())
    update_flops = step_flops * config.ppo.epochs * config.ppo.num_minibatches

    train = jax.jit(lambda s: trainer_lib.update_step(setup, s))
    jax.block_until_ready(train(state))
    train_s = fastest(lambda: train(state), repeats)

    matmul = matmul_gflops() * 1e9
    return {
        "env_only_sps": steps / env_only_s,
        "collect_sps": steps / collect_s,
        "train_sps": steps / train_s,
        "update_s": update_s,
        "update_gflops": update_flops / update_s / 1e9,
        "matmul_gflops": matmul / 1e9,
        "collect_ratio": env_only_s / collect_s,
        "collect_ratio_median": float(np.median(pair_ratios)),
        "collect_ratio_range": (float(pair_ratios.min()), float(pair_ratios.max())),
        "update_flops_ratio": update_flops / update_s / matmul,
    }


def device_peak_gb() -> float | None:
    """Peak bytes the accelerators' allocators held (GB, largest device); None on CPU."""
    import jax

    stats = [device.memory_stats() or {} for device in jax.local_devices()]
    peaks = [entry["peak_bytes_in_use"] for entry in stats if "peak_bytes_in_use" in entry]
    return max(peaks) / 1e9 if peaks and jax.default_backend() != "cpu" else None


def measure_training(env: str, algo: str, overrides: list[str], updates: int,
                     compile_only: bool = False) -> dict[str, Any]:
    """Training steps/s of one algorithm, timed on the second chunk; with `compile_only`, the
    chunk's compilation alone (which fills JAX's persistent cache where one is set)."""
    import jax

    from cmat.resolve import load_config
    from cmat.runners.trainer import JaxTrainer

    config = load_config(
        overrides=[f"env={env}", f"algo={algo}", f"log_interval={updates}", *overrides]
    )
    trainer = JaxTrainer(config)
    state = trainer.init()
    start = time.perf_counter()
    if compile_only:
        trainer.compile_chunk(state)
        return {"compile_seconds": time.perf_counter() - start}
    state, _ = trainer.train_chunk(state)
    first = time.perf_counter() - start
    start = time.perf_counter()
    state, _ = trainer.train_chunk(state)
    jax.block_until_ready(state)
    run = time.perf_counter() - start
    return {
        "steps_per_second": updates * config.steps_per_update * config.seeds / run,
        "compile_seconds": first - run,
        "seconds_per_update": run / updates,
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
        "peak_device_gb": device_peak_gb(),
    }


def compare_algorithms(args: argparse.Namespace) -> None:
    print(describe(with_matmul=False))
    print(f"Training throughput on {args.env} ({args.updates} updates per timed chunk; "
          "each algorithm with its own defaults from cmat.config)")
    print(f"{'algo':<12} {'preset':<10} {'steps/s':>9} {'s/update':>9} {'compile s':>10} "
          f"{'peak RSS GB':>12} {'device GB':>10}  overrides")
    for line in args.algo or algorithm_names():
        algo, _, own = line.partition(":")
        for preset in args.preset or ["reference"]:
            overrides = [*PRESETS[preset], *args.set, *filter(None, own.split(","))]
            command = [sys.executable, __file__, "--single", "--env", args.env, "--algo", algo,
                       "--updates", str(args.updates), "--set", *overrides]
            if args.compile_only:
                command.append("--compile-only")
            done = subprocess.run(command, check=False, capture_output=True, text=True)
            if done.returncode != 0:
                reason = (done.stderr.strip().splitlines() or ["failed"])[-1]
                print(f"{line:<12} {preset:<10} failed: {reason}")
                continue
            result = json.loads(done.stdout.strip().splitlines()[-1])
            if args.compile_only:
                print(f"{line:<12} {preset:<10} compiled in {result['compile_seconds']:.1f} s",
                      flush=True)
                continue
            device_gb = result["peak_device_gb"]
            print(f"{line:<12} {preset:<10} {result['steps_per_second']:>9.0f} "
                  f"{result['seconds_per_update']:>9.2f} {result['compile_seconds']:>10.1f} "
                  f"{result['peak_rss_gb']:>12.2f} "
                  f"{'-' if device_gb is None else f'{device_gb:.2f}':>10}  "
                  f"{' '.join(overrides) or '-'}", flush=True)


def algorithm_line(text: str) -> str:
    """An `--algo` value: a known algorithm, optionally with `:KEY=VALUE,...` of its own."""
    algo, _, own = text.partition(":")
    if algo not in algorithm_names():
        raise argparse.ArgumentTypeError(
            f"unknown algorithm {algo!r}; available: {', '.join(algorithm_names())}")
    if any("=" not in item for item in filter(None, own.split(","))):
        raise argparse.ArgumentTypeError(f"{text!r}: overrides after ':' are KEY=VALUE,...")
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=["smax:3m", "smax:3s5z_vs_3s6z"])
    parser.add_argument("--envs", type=int, default=64, help="parallel environments (breakdown)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--compare-algorithms", action="store_true")
    parser.add_argument("--env", default="smax:3s5z_vs_3s6z", help="env of the comparison")
    parser.add_argument("--algo", type=algorithm_line, action="append",
                        help="ALGO or ALGO:KEY=VALUE,... (repeatable)")
    parser.add_argument("--preset", choices=sorted(PRESETS), action="append",
                        help="comparison config (default: reference)")
    parser.add_argument("--updates", type=int, default=1, help="updates per timed chunk")
    parser.add_argument("--set", nargs="*", default=[], help="extra config overrides")
    parser.add_argument("--compile-only", action="store_true",
                        help="compile each line's training chunk and stop (with "
                             "JAX_COMPILATION_CACHE_DIR set, later runs load it)")
    parser.add_argument("--single", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.single:
        print(json.dumps(measure_training(args.env, args.algo[0], args.set, args.updates,
                                          args.compile_only)))
        return
    if args.compare_algorithms:
        compare_algorithms(args)
        return
    print(describe())
    print(f"CMAT default config (32 -> {args.envs} envs x 100 steps, 15 epochs, 1 minibatch, "
          f"d=64, 1 block, m=n); fastest of {args.repeats}; "
          f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    print(f"{'env':<20} {'env-only sps':>12} {'collect sps':>12} {'train sps':>10} "
          f"{'collect/env':>11} {'pairs: median [range]':>22} {'update GFLOP/s':>15} "
          f"{'matmul GFLOP/s':>15} {'ratio':>6}")
    results = {}
    for env_id in args.scenarios:
        r = results[env_id] = breakdown(env_id, args.envs, args.repeats)
        low, high = r["collect_ratio_range"]
        print(f"{env_id:<20} {r['env_only_sps']:>12,.0f} {r['collect_sps']:>12,.0f} "
              f"{r['train_sps']:>10,.0f} {r['collect_ratio']:>11.2f} "
              f"{r['collect_ratio_median']:>8.2f} [{low:.2f}-{high:.2f}]{'':>6} "
              f"{r['update_gflops']:>15.1f} "
              f"{r['matmul_gflops']:>15.1f} {r['update_flops_ratio']:>6.2f}", flush=True)
    for env_id, r in results.items():
        print(f"RESULT env={env_id} envs={args.envs} env_only_sps={r['env_only_sps']:.0f} "
              f"collect_sps={r['collect_sps']:.0f} train_sps={r['train_sps']:.0f} "
              f"collect_ratio={r['collect_ratio']:.3f} "
              f"update_flops_ratio={r['update_flops_ratio']:.3f} "
              f"collect_ratio_median={r['collect_ratio_median']:.3f}")


if __name__ == "__main__":
    main()
