"""CMAT's named departures from the paper change only what they say, and `--preset paper` is
exactly the paper's setting."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cmat.algorithms import build_algorithm
from cmat.algorithms.base import Batch
from cmat.algorithms.cmat.options import CMATOptions
from cmat.algorithms.ppo import clipped_surrogate_loss, joint_clip_range
from cmat.config import NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.errors import CmatError
from cmat.resolve import load_config
from cmat.runners.learner import make_batch, optimise
from cmat.runners.trainer import build_setup, init_state

pytestmark = pytest.mark.quick_compiles

SPEC = EnvSpec("test", 4, 5, 3, True, 10, False)


def batch_for(algorithm, spread: float = 0.3) -> tuple[dict, Batch]:
    keys = jax.random.split(jax.random.PRNGKey(7), 5)
    obs = jax.random.normal(keys[0], (32, 4, 5))
    mask = jnp.ones((32, 4, 3), bool)
    params = jax.jit(algorithm.init)(keys[1], obs[0], mask[0])
    acted = jax.jit(jax.vmap(algorithm.act, in_axes=(None, 0, 0, 0)))(
        params, obs, mask, jax.random.split(keys[2], 32))
    return params, Batch(
        obs, mask, acted.actions,
        acted.log_probs + spread * jax.random.normal(keys[3], (32, 4)), acted.value,
        jax.random.normal(keys[4], (32,)), jnp.zeros(32), acted.extras,
        alive=jnp.ones((32, 4), bool).at[:10, 3].set(False),
    )


NETWORK = NetworkConfig(n_embd=16, init_gain=1.0)


@pytest.fixture(scope="module")
def cmat_batch():
    algorithm = build_algorithm("cmat", NETWORK, SPEC)
    return (algorithm, *batch_for(algorithm))


def with_options(**options: object):
    """CMAT on the fixture's network with loss options of its section changed (the same
    parameters: the loss options shape none)."""
    return build_algorithm("cmat", NETWORK, SPEC, options=CMATOptions(**options))


@pytest.mark.unit
def test_paper_options_give_the_papers_loss(cmat_batch) -> None:
    """Defaults: the clipped objective on the joint ratio with [1−ε, 1+ε] and the mean entropy."""
    algorithm, params, batch = cmat_batch
    ppo = PPOConfig()
    _, metrics = jax.jit(algorithm.loss, static_argnums=2)(params, batch, ppo)
    log_ratio, _, distribution = jax.jit(algorithm.log_ratio)(params, batch)
    ratio = np.exp(np.asarray(log_ratio, np.float64))
    adv = np.asarray(batch.advantages)
    objective = np.minimum(ratio * adv, np.clip(ratio, 0.95, 1.05) * adv)
    assert float(metrics["policy_loss"]) == pytest.approx(-objective.mean(), rel=1e-5)
    assert float(metrics["entropy"]) == pytest.approx(
        float(np.asarray(distribution.entropy()).mean()), rel=1e-6)


@pytest.mark.unit
def test_per_agent_joint_clip_widens_the_range_to_the_kth_power(cmat_batch) -> None:
    algorithm, params, batch = cmat_batch
    per_agent = with_options(joint_clip="per_agent")
    _, metrics = jax.jit(per_agent.loss, static_argnums=2)(params, batch, PPOConfig())
    log_ratio, _, _ = jax.jit(algorithm.log_ratio)(params, batch)
    ratio = np.exp(np.asarray(log_ratio, np.float64))
    k = np.asarray(batch.alive).sum(axis=1)
    adv = np.asarray(batch.advantages)
    objective = np.minimum(ratio * adv, np.clip(ratio, 0.95 ** k, 1.05 ** k) * adv)
    assert float(metrics["policy_loss"]) == pytest.approx(-objective.mean(), rel=1e-5)
    outside = (ratio < 0.95 ** k) | (ratio > 1.05 ** k)
    assert float(metrics["clip_frac"]) == pytest.approx(outside.mean())
    paper = np.abs(ratio - 1) > 0.05
    assert outside.mean() < paper.mean()
    entropy = jax.jit(algorithm.loss, static_argnums=2)(params, batch, PPOConfig())[1]["entropy"]
    assert float(metrics["entropy"]) == pytest.approx(float(entropy))


@pytest.mark.unit
def test_one_agent_per_agent_clip_is_the_papers_clip() -> None:
    log_ratio = jnp.linspace(-0.3, 0.3, 13)
    advantages = jnp.sign(jnp.sin(jnp.arange(13.0)))
    paper, _ = clipped_surrogate_loss(log_ratio, advantages, 0.1)
    scaled, _ = clipped_surrogate_loss(
        log_ratio, advantages, 0.1, clip_range=joint_clip_range(0.1, jnp.ones(13)))
    assert float(scaled) == pytest.approx(float(paper), rel=1e-6)


@pytest.mark.unit
def test_entropy_sum_is_the_joint_policys_entropy(cmat_batch) -> None:
    algorithm, params, batch = cmat_batch
    loss = jax.jit(algorithm.loss, static_argnums=2)
    mean = loss(params, batch, PPOConfig())[1]
    summed = jax.jit(with_options(entropy_reduction="sum").loss, static_argnums=2)(
        params, batch, PPOConfig())[1]
    assert float(summed["entropy"]) == pytest.approx(4 * float(mean["entropy"]), rel=1e-6)
    assert float(summed["policy_loss"]) == float(mean["policy_loss"])


def test_kl_early_stop_skips_the_epochs_after_the_target() -> None:
    """The early stop lives in the shared SGD loop; MAPPO's small MLPs compile fastest."""
    base = ["env=matrix:fig1", "algo=mappo", "num_envs=4", "rollout_length=5",
            "network.n_embd=8", "network.init_gain=1.0", "ppo.lr=0.01"]
    setup = build_setup(load_config(overrides=base))
    state = jax.jit(lambda key: init_state(setup, key))(jax.random.PRNGKey(0))
    learner = state.learner
    _, rollout = jax.jit(setup.collector.collect)(learner.params, state.envs, learner.rng)
    _, batch = jax.jit(lambda s, r: make_batch(setup.learner, s, r))(learner, rollout)

    def optimised(*overrides: str):
        variant = build_setup(load_config(overrides=[*base, *overrides])).learner
        params, _, metrics = jax.jit(lambda p, o, b, k: optimise(variant, p, o, b, k))(
            learner.params, learner.opt_state, batch, jax.random.PRNGKey(1))
        return params, metrics

    full, full_metrics = optimised("ppo.epochs=4")
    loose, loose_metrics = optimised("ppo.epochs=4", "ppo.target_kl=1e6")
    assert float(loose_metrics["epochs_run"]) == 4
    for a, b in zip(jax.tree.leaves(full), jax.tree.leaves(loose)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    # one minibatch: an epoch measures KL before its step, so epoch 1 sees 0 and epoch 2 stops
    two, _ = optimised("ppo.epochs=2")
    stopped, stopped_metrics = optimised("ppo.epochs=4", "ppo.target_kl=1e-12")
    assert float(stopped_metrics["epochs_run"]) == 2
    for a, b in zip(jax.tree.leaves(two), jax.tree.leaves(stopped)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    assert "epochs_run" not in full_metrics


PAPER = {
    "num_envs": 8, "rollout_length": 100,
    "ppo.lr": 5e-4, "ppo.adam_eps": 1e-5, "ppo.epochs": 15, "ppo.num_minibatches": 1,
    "ppo.clip_eps": 0.05, "ppo.ent_coef": 0.01, "ppo.value_coef": 1.0,
    "ppo.max_grad_norm": 10.0, "ppo.gamma": 0.99, "ppo.gae_lambda": 0.95,
    "ppo.value_norm": True, "ppo.huber_loss": True, "ppo.huber_delta": 10.0,
    "ppo.clipped_value_loss": True, "ppo.target_tau": 0.1, "options.joint_clip": "joint",
    "options.entropy_reduction": "mean", "ppo.target_kl": None, "ppo.active_masks": False,
    "network.n_embd": 64, "network.n_head": 1, "network.n_block": 1,
    "options.consensus_iterations": "n", "options.consensus_source": "mixture",
    "options.consensus_policy": "deterministic", "network.init_gain": 0.01,
    "network.log_std_init": 1.0,
}
"""The paper's setting, written from the paper (the MAT SMAC hyper-parameters with 8 rollout
threads) and the reference MAT implementation's SMAC train scripts."""


def value(config, dotted: str):
    for part in dotted.split("."):
        config = getattr(config, part)
    return config


@pytest.mark.unit
def test_the_paper_preset_resolves_to_the_papers_values() -> None:
    config = load_config(overrides=["preset=paper", "env=smax:6h_vs_8z"])
    assert config.preset == "paper"
    for name, expected in PAPER.items():
        assert value(config, name) == expected, name
    overridden = load_config(overrides=["preset=paper", "ppo.clip_eps=0.2"])
    assert overridden.ppo.clip_eps == 0.2 and overridden.num_envs == 8
    assert load_config(overrides=["preset=paper", "algo=mappo"]).ppo.clip_eps == 0.2
    with pytest.raises(CmatError, match="unknown preset 'fast'"):
        load_config(overrides=["preset=fast"])


@pytest.mark.unit
def test_the_paper_preset_takes_mats_column_of_the_suite() -> None:
    mujoco = load_config(overrides=["preset=paper", "env=mamujoco:HalfCheetah-6x1"])
    assert (mujoco.ppo.lr, mujoco.ppo.epochs, mujoco.ppo.num_minibatches) == (5e-5, 10, 40)
    assert (mujoco.ppo.ent_coef, mujoco.ppo.max_grad_norm) == (0.001, 0.5)
    assert (mujoco.num_envs, mujoco.ppo.target_tau, mujoco.ppo.clip_eps) == (8, 0.1, 0.05)
    football = load_config(overrides=["preset=paper", "env=grf:academy_3_vs_1_with_keeper"])
    assert (football.rollout_length, football.ppo.epochs, football.num_envs) == (200, 10, 8)


@pytest.mark.unit
def test_cmats_default_is_the_tuned_setting_and_differs_from_the_papers_clip_and_tau() -> None:
    default, tuned = load_config(), load_config(overrides=["preset=tuned"])
    assert (default.options.joint_clip, default.ppo.target_tau) == ("per_agent", 1.0)
    assert dataclasses.replace(tuned, preset=None) == default
    paper_clip_and_tau = load_config(overrides=["cmat.joint_clip=joint", "ppo.target_tau=0.1"])
    assert dataclasses.replace(
        default, ppo=dataclasses.replace(default.ppo, target_tau=0.1),
        options=dataclasses.replace(default.options, joint_clip="joint")) == paper_clip_and_tau
    triple_bert = load_config(overrides=["algo=triple_bert"])
    assert (triple_bert.options.joint_clip, triple_bert.ppo.target_tau) == ("joint", 0.1)
    tuned_triple_bert = load_config(overrides=["algo=triple_bert", "preset=tuned"])
    assert (tuned_triple_bert.options.joint_clip, tuned_triple_bert.ppo.target_tau) == (
        "per_agent", 1.0)
    with pytest.raises(CmatError, match="unknown preset 'tuned' for mat; available: paper"):
        load_config(overrides=["preset=tuned", "algo=mat"])


@pytest.mark.unit
@pytest.mark.parametrize("override", ["cmat.joint_clip=geometric", "cmat.entropy_reduction=max",
                                      "ppo.target_kl=0", "ppo.target_kl=-1"])
def test_bad_option_values_are_rejected(override: str) -> None:
    with pytest.raises(CmatError, match=override.split("=")[0]):
        load_config(overrides=[override])


@pytest.mark.unit
@pytest.mark.parametrize("algo", ["mat", "mappo"])
def test_joint_options_are_for_joint_ratio_algorithms(algo: str) -> None:
    with pytest.raises(CmatError, match=f"unknown key {algo}.joint_clip"):
        load_config(overrides=[f"algo={algo}", f"{algo}.joint_clip=per_agent"])
