"""Host-environment throughput: env-only, collection and training steps/s, in-process vs workers.

    python benchmarks/host_throughput.py                     # HalfCheetah 6x1 and GRF 3 vs 1
    python benchmarks/host_throughput.py --env-ids mamujoco:Ant-8x1 --workers 0 2 4

For each environment and worker count (0 = in this process), in one run:
- env-only: the pool steps `--envs` environments with random legal actions (no policy);
- collection: `HostTrainer.collect` (the jitted policy's call per step plus the pool's step);
- training: whole `train_chunk`s of `--updates` updates (collection + the jitted PPO update),
  with the reference MAT settings for the suite (docs/suites.md) unless overridden.
Steps/s count environment transitions after compilation, which is reported separately. GRF is
skipped with a message when gfootball is not installed.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import time
from typing import Any

import jax
import numpy as np
from machine import describe

from cmat.envs.host import make_host_env
from cmat.envs.host.pool import make_pool
from cmat.envs.protocol import EnvSpec
from cmat.resolve import load_config
from cmat.runners.host import HostTrainer

DEFAULT_ENVS = ["mamujoco:HalfCheetah-6x1", "grf:academy_3_vs_1_with_keeper"]

SUITE_SETTINGS = {
    "mamujoco": ["ppo.lr=5e-5", "ppo.epochs=10", "ppo.num_minibatches=40", "ppo.ent_coef=0.001",
                 "ppo.max_grad_norm=0.5", "env_kwargs.agent_id=true"],
    "grf": ["ppo.epochs=10", "ppo.max_grad_norm=0.5"],
}
"""The reference MAT hyper-parameters of each suite (the reference MAT implementation's train
scripts, as in cmat/envs/suites.py); rollout
length and number of environments come from the command line."""


def installed(env_id: str) -> bool:
    module = {"mamujoco": "gymnasium_robotics", "grf": "gfootball"}.get(env_id.partition(":")[0])
    return module is None or importlib.util.find_spec(module) is not None


def random_actions(rng: np.random.Generator, mask: np.ndarray, spec: EnvSpec) -> np.ndarray:
    """Uniform legal actions [envs, agents] (discrete) or uniform in the Box (continuous)."""
    if not spec.discrete:
        return rng.uniform(spec.action_low, spec.action_high, mask.shape).astype(np.float32)
    return np.where(mask, rng.random(mask.shape), -1.0).argmax(-1)


def env_only(env_id: str, kwargs: dict[str, Any], envs: int, steps: int, workers: int) -> float:
    """Environment steps per second of a pool stepped with random legal actions."""
    probe = make_host_env(env_id, **kwargs)
    spec = probe.spec
    pool = make_pool(env_id, kwargs, list(range(envs)), workers, [probe])
    try:
        timestep = pool.reset()
        rng = np.random.default_rng(0)
        for _ in range(5):  # warm up (first steps allocate)
            timestep = pool.step(random_actions(rng, timestep.action_mask, spec))
        start = time.perf_counter()
        for _ in range(steps):
            timestep = pool.step(random_actions(rng, timestep.action_mask, spec))
        return envs * steps / (time.perf_counter() - start)
    finally:
        pool.close()


def training(env_id: str, envs: int, rollout: int, updates: int, workers: int,
             overrides: list[str]) -> dict[str, float]:
    suite = SUITE_SETTINGS.get(env_id.partition(":")[0], [])
    config = load_config(overrides=[
        f"env={env_id}", f"num_envs={envs}", f"rollout_length={rollout}", f"host_workers={workers}",
        f"log_interval={updates}", *suite, *overrides,
    ])
    trainer = HostTrainer(config)
    try:
        start = time.perf_counter()
        state = trainer.init()
        state, _ = trainer.train_chunk(state)  # compiles the policy step and the update
        jax.block_until_ready(state.learner.params)
        compile_s = time.perf_counter() - start
        start = time.perf_counter()
        learner, rollout = trainer.collect(state.learner)
        jax.block_until_ready(rollout.steps.obs)
        collect_s = time.perf_counter() - start
        start = time.perf_counter()
        state, _ = trainer.train_chunk(dataclasses.replace(state, learner=learner))
        jax.block_until_ready(state.learner.params)
        train_s = time.perf_counter() - start
    finally:
        trainer.close()
    steps = envs * rollout
    return {
        "first_chunk_s": compile_s,
        "collect_per_s": steps / collect_s,
        "train_per_s": updates * steps / train_s,
        "update_s": train_s / updates - collect_s,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env-ids", nargs="+", default=DEFAULT_ENVS)
    parser.add_argument("--envs", type=int, default=16, help="environments per run")
    parser.add_argument("--rollout", type=int, default=100, help="rollout_length of training")
    parser.add_argument("--steps", type=int, default=200, help="pool steps of the env-only run")
    parser.add_argument("--updates", type=int, default=2, help="updates per timed chunk")
    parser.add_argument("--workers", type=int, nargs="+", default=[0, 2])
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="config overrides for the training runs")
    args = parser.parse_args()
    print(f"# {describe()}")
    print(f"# envs={args.envs}, "
          f"rollout={args.rollout}, updates={args.updates}")
    header = (f"{'env':36} {'workers':>7} {'env-only/s':>11} {'collect/s':>10} {'train/s':>9} "
              f"{'update s':>9} {'1st chunk s':>11}")
    print(header)
    print("-" * len(header))
    for env_id in args.env_ids:
        if not installed(env_id):
            print(f"{env_id:36} skipped: not installed (GRF: scripts/install_grf.sh; "
                  f"MaMuJoCo: pip install -e '.[mujoco]')")
            continue
        for workers in args.workers:
            kwargs = {"agent_id": True} if env_id.startswith("mamujoco") else {}
            env_rate = env_only(env_id, kwargs, args.envs, args.steps, workers)
            result = training(env_id, args.envs, args.rollout, args.updates, workers, args.set)
            print(f"{env_id:36} {workers:>7} {env_rate:>11.0f} {result['collect_per_s']:>10.0f} "
                  f"{result['train_per_s']:>9.0f} {result['update_s']:>9.2f} "
                  f"{result['first_chunk_s']:>11.1f}", flush=True)


if __name__ == "__main__":
    main()
