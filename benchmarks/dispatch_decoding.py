"""How a trained dispatch policy's decisions are decoded changes what it earns: sampled (the
dispatch suite's evaluation), greedy, and matched (`cmat eval --actions matched`: the most likely
claims in which no order goes to two vehicles), beside the Hungarian baseline on the episodes
matched decoding plays.

    python benchmarks/dispatch_decoding.py runs/fleet_mappo runs/fleet_cmat --episodes 32
    python benchmarks/dispatch_decoding.py --time-matching dispatch:manhattan-1000-mid

Every trained seed of every run is evaluated on `--episodes` episodes of `--seed`; a table row per
run and decoding gives the mean ± std over seeds (population std) of the return, service rate,
empty-driving share and conflicts per minute, then the Hungarian and greedy baselines of the
first run's task on that seed's episodes. `--time-matching TASK` times the matching alone
(`matched_plan`, on the host) for one fleet of TASK over one episode of random legal play, with
random log-probabilities.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from machine import describe

FIGURES = ("episode_return", "service_rate", "empty_share", "conflicts_per_step")
DECODINGS = ("sample", "greedy", "matched")


def cell(values: list[float]) -> str:
    return f"{np.mean(values):.3g} ± {np.std(values):.2g}" if len(values) > 1 \
        else f"{values[0]:.3g}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, nargs="*", help="run directories on one dispatch task")
    parser.add_argument("--time-matching", metavar="TASK")
    parser.add_argument("--episodes", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    import cmat
    from cmat.envs.dispatch.baselines import baseline_env, evaluate_means

    print(f"{describe()}\n")
    if args.time_matching:
        time_matching(args.time_matching)
    if not args.runs:
        return
    print("| run | decoding | " + " | ".join(FIGURES) + " | seconds |")
    print("|---|---|" + "---|" * (len(FIGURES) + 1))
    for path in args.runs:
        run = cmat.open_run(path)
        for decoding in DECODINGS:
            start = time.perf_counter()
            frame = run.evaluate(episodes=args.episodes, actions=decoding, seed=args.seed)
            seconds = time.perf_counter() - start
            cells = [cell(frame[name].astype(float).tolist()) for name in FIGURES]
            print(f"| {path.name} ({run.config.algo}) | {decoding} | " + " | ".join(cells)
                  + f" | {seconds:.0f} |", flush=True)
    config = cmat.open_run(args.runs[0]).config
    env = baseline_env(config.env, config.env_kwargs)
    for baseline in ("hungarian", "greedy"):
        figures = evaluate_means(env, baseline, args.episodes, args.seed)
        print(f"| {config.env} | {baseline} baseline | "
              + " | ".join(f"{figures[name]:.3g}" for name in FIGURES) + " | |")


def time_matching(task: str) -> None:
    """Milliseconds of `matched_plan` per minute of one episode of `task`, the fleet stepped by
    the matched claims of random log-probabilities."""
    import jax

    from cmat.envs.dispatch.baselines import baseline_env
    from cmat.envs.dispatch.matched import matched_plan

    env = baseline_env(task, {})
    state, timestep = jax.jit(env.reset)(jax.random.PRNGKey(0))
    step = jax.jit(env.step_in_episode)
    rng, key, times, claimable = np.random.default_rng(0), jax.random.PRNGKey(1), [], []
    for _ in range(env.episode_minutes):
        mask, candidates = np.asarray(timestep.action_mask), np.asarray(state.candidates)
        logits = np.where(mask, rng.normal(0.0, 1.0, mask.shape), -np.inf)
        log_probs = logits - np.logaddexp.reduce(logits, axis=1, keepdims=True)
        start = time.perf_counter()
        actions = matched_plan(log_probs, mask, candidates)
        times.append(1e3 * (time.perf_counter() - start))
        claimable.append(int(mask[:, 1:1 + candidates.shape[1]].any(axis=1).sum()))
        key, step_key = jax.random.split(key)
        state, timestep = step(step_key, state, actions)
    print(f"{task}: matched_plan {np.median(times):.1f} ms median, {max(times):.1f} ms at most "
          f"(minute {int(np.argmax(times))}) over {len(times)} minutes; vehicles with an order "
          f"to claim: median {int(np.median(claimable))}, at most {max(claimable)}\n")


if __name__ == "__main__":
    main()
