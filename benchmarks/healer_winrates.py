"""Win rates of random legal play and the scripted focus-fire team on the healer scenarios.

    python benchmarks/healer_winrates.py                         # MMM and MMM2, 256 episodes each
    python benchmarks/healer_winrates.py --scenarios MMM2 --episodes 1024

Each of `--episodes` parallel envs plays one whole episode against JaxMARL's heuristic enemy
(extended for healers); the win rate is the fraction won, with its binomial standard error.
"""

from __future__ import annotations

import argparse
import math
import time

import jax

from cmat.envs.jaxmarl_envs import SmaxEnv
from cmat.envs.random_policy import random_legal_actions
from cmat.envs.smax_healer import (
    SCENARIOS,
    first_episode_wins,
    focus_fire_policy,
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=SCENARIOS)
    parser.add_argument("--episodes", type=int, default=256, help="episodes per policy")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    print(f"{'scenario':<9} {'policy':<11} {'episodes':>8} {'win rate':>9} {'± s.e.':>7} {'s':>6}")
    for scenario in args.scenarios:
        env = SmaxEnv(scenario)
        policies = {"random": random_legal_actions, "focus-fire": focus_fire_policy(env.env)}
        for name, policy in policies.items():
            start = time.perf_counter()
            won = jax.jit(first_episode_wins(env, policy, args.episodes))(
                jax.random.key(args.seed)
            )
            rate = float(won.mean())
            stderr = math.sqrt(rate * (1 - rate) / args.episodes)
            print(f"{scenario:<9} {name:<11} {args.episodes:>8} {rate:>9.3f} {stderr:>7.3f} "
                  f"{time.perf_counter() - start:>6.1f}")


if __name__ == "__main__":
    main()
