"""Several devices compute what one does: seeds or environments sharded across two host
devices (`--xla_force_host_platform_device_count=2`, set before JAX starts, so in a subprocess)
against the same runs on one device."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

pytestmark = pytest.mark.quick_compiles

PROGRAM = r"""
import json, sys
import jax, numpy as np
from cmat.resolve import load_config
from cmat.runners.trainer import JaxTrainer

results = {"devices": len(jax.local_devices())}
for name, extra in (("seeds", ["seeds=2", "num_envs=4"]), ("envs", ["seeds=1", "num_envs=4"])):
    config = load_config(overrides=["env=matrix:fig1", "algo=mappo", "rollout_length=8",
                                    "total_steps=64", "log_interval=2", "ppo.epochs=2",
                                    "network.n_embd=16", "eval_episodes=4", *extra])
    trainer = JaxTrainer(config)
    state = trainer.init()
    state, metrics = trainer.train_chunk(state)
    evaluation = trainer.evaluate(state, 4)
    sharding = jax.tree.leaves(state.envs.timestep.obs)[0].sharding
    results[name] = {
        "axis": trainer.sharded_axis,
        "shards": len(sharding.device_set),
        "params": [np.asarray(x).tolist() for x in jax.tree.leaves(state.learner.params)],
        "loss": np.asarray(metrics["loss"]).tolist(),
        "return": np.asarray(evaluation["episode_return"]).tolist(),
    }
print(json.dumps(results))
"""


def run(devices: int) -> dict:
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}"
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    done = subprocess.run([sys.executable, "-c", PROGRAM], capture_output=True, text=True,
                          env=env, timeout=900, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    result: dict = json.loads(done.stdout.strip().splitlines()[-1])
    return result


@pytest.fixture(scope="module")
def runs() -> tuple[dict, dict]:
    return run(1), run(2)


def test_two_devices_shard_seeds_else_environments(runs: tuple[dict, dict]) -> None:
    one, two = runs
    assert (one["devices"], two["devices"]) == (1, 2)
    assert (one["seeds"]["axis"], one["envs"]["axis"]) == (None, None)
    assert (two["seeds"]["axis"], two["envs"]["axis"]) == ("seeds", "envs")
    assert two["seeds"]["shards"] == two["envs"]["shards"] == 2


@pytest.mark.parametrize("case", ["seeds", "envs"])
def test_two_devices_train_what_one_trains(runs: tuple[dict, dict], case: str) -> None:
    """Equal up to floating-point order: parameters after two updates within 1e-4."""
    one, two = runs[0][case], runs[1][case]
    for a, b in zip(one["params"], two["params"], strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(one["loss"], two["loss"], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(one["return"], two["return"], rtol=1e-4, atol=1e-4)
