"""Environment-only throughput: random legal actions, `vmap` over envs, jitted `scan` over steps.

    python benchmarks/env_throughput.py                       # the default configurations
    python benchmarks/env_throughput.py --env-ids smax:3m --envs 64 256 --steps 200

Steps/s counts environment transitions (envs x steps) after compilation; compile time is reported
separately.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import jax
from machine import describe

from cmat.envs import make_env
from cmat.envs.random_policy import random_rollout

DEFAULT_CONFIGS = [
    ("smax:3m", 64),
    ("smax:3m", 512),
    ("smax:3s5z_vs_3s6z", 64),
    ("smax:3s5z_vs_3s6z", 512),
    ("mpe:simple_spread", 64),
]


def measure(env_id: str, num_envs: int, num_steps: int, repeats: int) -> dict[str, Any]:
    """Compile once, then time `repeats` runs and keep the fastest."""
    env = make_env(env_id)
    start = time.perf_counter()
    compiled = jax.jit(random_rollout(env, num_envs, num_steps)).lower(jax.random.key(0)).compile()
    compile_s = time.perf_counter() - start
    times: list[float] = []
    for i in range(repeats):
        start = time.perf_counter()
        _, episodes = jax.block_until_ready(compiled(jax.random.key(i + 1)))
        times.append(time.perf_counter() - start)
    return {
        "env": env_id,
        "agents": env.spec.num_agents,
        "envs": num_envs,
        "steps": num_steps,
        "compile_s": compile_s,
        "run_s": min(times),
        "steps_per_s": num_envs * num_steps / min(times),
        "episodes": int(episodes),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env-ids", nargs="+", help="environment ids (default: the standard set)")
    parser.add_argument("--envs", nargs="+", type=int, help="parallel environment counts")
    parser.add_argument("--steps", type=int, default=200, help="scan length of each timed run")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs; the fastest counts")
    args = parser.parse_args()
    if args.env_ids or args.envs:
        env_ids = args.env_ids or sorted({env_id for env_id, _ in DEFAULT_CONFIGS})
        configs = [(env_id, n) for env_id in env_ids for n in args.envs or [64]]
    else:
        configs = DEFAULT_CONFIGS

    print(describe())
    print(f"steps={args.steps}, repeats={args.repeats} (fastest), random legal actions")
    header = f"{'env':<20} {'agents':>6} {'envs':>5} {'compile s':>9} {'run s':>7} " \
             f"{'steps/s':>10} {'episodes':>8}"
    print(header)
    print("-" * len(header))
    for env_id, num_envs in configs:
        r = measure(env_id, num_envs, args.steps, args.repeats)
        print(f"{r['env']:<20} {r['agents']:>6} {r['envs']:>5} {r['compile_s']:>9.1f} "
              f"{r['run_s']:>7.3f} {r['steps_per_s']:>10,.0f} {r['episodes']:>8}")


if __name__ == "__main__":
    main()
