"""Per-update diagnostics against numpy on a fixed batch, and end to end into metrics.csv and
`cmat plot --diagnostics`."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cmat.algorithms import build_algorithm
from cmat.algorithms.base import Batch
from cmat.algorithms.ppo import (
    PER_AGENT_DIAGNOSTICS,
    block_grad_norms,
    explained_variance,
    policy_diagnostics,
)
from cmat.cli import main
from cmat.config import NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.rundir import RunDir

pytestmark = pytest.mark.quick_compiles

SPEC = EnvSpec("test", 3, 5, 4, True, 10, False)
NETWORK = NetworkConfig(n_embd=16, n_head=2, init_gain=1.0)


def fixed_batch(algo: str) -> tuple[object, dict, Batch]:
    algorithm = build_algorithm(algo, NETWORK, SPEC)
    keys = jax.random.split(jax.random.PRNGKey(3), 6)
    obs = jax.random.normal(keys[0], (64, 3, 5))
    mask = jnp.ones((64, 3, 4), bool).at[:, 2, 3].set(False)
    params = jax.jit(algorithm.init)(keys[1], obs[0], mask[0])
    acted = jax.jit(jax.vmap(algorithm.act, in_axes=(None, 0, 0, 0)))(
        params, obs, mask, jax.random.split(keys[2], 64))
    batch = Batch(
        obs, mask, acted.actions, acted.log_probs + 0.2 * jax.random.normal(keys[3], (64, 3)),
        acted.value, jax.random.normal(keys[4], (64,)), jax.random.normal(keys[5], (64,)),
        acted.extras, alive=jnp.ones((64, 3), bool).at[:8, 1].set(False),
    )
    return algorithm, params, batch


@pytest.mark.parametrize("algo", ["cmat", "mappo"])
def test_ratio_diagnostics_and_entropy_per_agent_equal_numpy(algo: str) -> None:
    algorithm, params, batch = fixed_batch(algo)
    ppo = PPOConfig(clip_eps=0.1, active_masks=True)
    _, metrics = jax.jit(algorithm.loss, static_argnums=2)(params, batch, ppo)
    if algo == "cmat":
        _, _, distribution = jax.jit(algorithm.log_ratio)(params, batch)
    else:
        distribution = jax.jit(algorithm.distribution)(params, batch.obs, batch.action_mask)
    agent = np.asarray(distribution.log_prob(batch.actions) - batch.log_probs, np.float64)
    joint = agent.sum(axis=1)
    alive = np.asarray(batch.alive)

    def k3(log_ratio: np.ndarray) -> np.ndarray:
        return np.exp(log_ratio) - 1 - log_ratio

    expected = {
        "joint_approx_kl": k3(joint).mean(),
        "joint_clip_frac": (np.abs(np.exp(joint) - 1) > 0.1).mean(),
        "agent_approx_kl": k3(agent)[alive].mean(),
        "agent_clip_frac": (np.abs(np.exp(agent) - 1) > 0.1)[alive].mean(),
    }
    entropies = np.asarray(distribution.entropy())
    expected.update({f"entropy_agent_{i}": entropies[alive[:, i], i].mean() for i in range(3)})
    assert not alive[:, 1].all()
    assert 0.05 < expected["joint_clip_frac"] < 1 and expected["agent_clip_frac"] > 0
    for name, value in expected.items():
        assert float(metrics[name]) == pytest.approx(value, rel=1e-4, abs=1e-6), name


@pytest.mark.parametrize("n", [PER_AGENT_DIAGNOSTICS, PER_AGENT_DIAGNOSTICS + 1, 250])
def test_entropy_is_named_per_agent_up_to_the_limit_and_summarised_above(n: int) -> None:
    rng = np.random.default_rng(n)
    entropy = rng.uniform(0.0, 2.0, size=(48, n))
    alive = rng.random((48, n)) > 0.3
    alive[:, 0] = False
    log_ratio = rng.normal(scale=0.1, size=(48, n))
    got = policy_diagnostics(jnp.asarray(log_ratio), jnp.asarray(log_ratio.sum(axis=1)), 0.2,
                             jnp.asarray(entropy), jnp.asarray(alive))
    per_agent = (entropy * alive).sum(axis=0) / np.maximum(alive.sum(axis=0), 1)
    named = {key for key in got if key.startswith("entropy_agent_")}
    if n <= PER_AGENT_DIAGNOSTICS:
        assert named == {f"entropy_agent_{i}" for i in range(n)}
        for i in range(n):
            assert float(got[f"entropy_agent_{i}"]) == pytest.approx(per_agent[i], rel=1e-5)
    else:
        expected = {"min": per_agent.min(), "median": np.median(per_agent),
                    "max": per_agent.max()}
        assert named == {f"entropy_agent_{name}" for name in expected}
        for name, value in expected.items():
            assert float(got[f"entropy_agent_{name}"]) == pytest.approx(value, rel=1e-5), name
        assert per_agent.min() == 0.0  # the agent never alive counts as entropy 0


def test_block_gradient_norms_equal_numpy() -> None:
    algorithm, params, batch = fixed_batch("cmat")
    grads = jax.jit(jax.grad(lambda p: algorithm.loss(p, batch, PPOConfig())[0]))(params)
    norms = block_grad_norms(grads)
    assert set(norms) == {f"grad_norm_{name}" for name in (
        "encoder", "critic_compressor", "critic_mlp", "decoder", "actor_compressor", "actor_mlp")}
    for name, block in grads["params"].items():
        squares = sum(float(np.sum(np.square(np.asarray(leaf, np.float64))))
                      for leaf in jax.tree.leaves(block))
        assert float(norms[f"grad_norm_{name}"]) == pytest.approx(np.sqrt(squares), rel=1e-4)
    mappo, mappo_params, mappo_batch = fixed_batch("mappo")
    mappo_grads = jax.jit(jax.grad(lambda p: mappo.loss(p, mappo_batch, PPOConfig())[0]))(
        mappo_params)
    assert set(block_grad_norms(mappo_grads)) == {"grad_norm_actor", "grad_norm_critic"}


def test_explained_variance_equals_numpy() -> None:
    rng = np.random.default_rng(0)
    targets = rng.normal(size=200)
    predictions = targets + rng.normal(scale=0.5, size=200)
    expected = 1 - np.var(targets - predictions) / np.var(targets)
    got = explained_variance(jnp.asarray(predictions), jnp.asarray(targets))
    assert float(got) == pytest.approx(expected, rel=1e-4)
    assert np.isnan(float(explained_variance(jnp.ones(4), jnp.full(4, 2.0))))


def test_a_run_logs_its_diagnostics_and_plots_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    args = ["train", "--env", "matrix:fig1", "--steps", "200", "--set", "num_envs=4",
            "rollout_length=25", "log_interval=1", "ppo.epochs=2", "eval_episodes=2"]
    assert main([*args, "--out", str(out)]) == 0
    rows = [r for r in RunDir(out).read_metrics() if r["kind"] == "train"]
    assert len(rows) == 2
    for column in ("joint_clip_frac", "agent_clip_frac", "joint_approx_kl", "agent_approx_kl",
                   "explained_variance", "entropy_agent_0", "entropy_agent_1",
                   "grad_norm_encoder", "grad_norm_decoder", "grad_norm_actor_mlp"):
        assert all(r[column] not in ("", "nan") for r in rows), column
    image = tmp_path / "diagnostics.png"
    assert main(["plot", str(out), "--out", str(image), "--diagnostics"]) == 0
    assert image.stat().st_size > 10_000
