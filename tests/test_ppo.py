"""PPO pieces against plain references: GAE, the joint ratio, the clipped loss, ValueNorm."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from cmat.algorithms import ppo
from cmat.config import PPOConfig

pytestmark = pytest.mark.unit


def plain_gae(rewards, values, dones, last_value, gamma, lam):
    advantages = np.zeros_like(rewards)
    next_advantage = np.zeros_like(last_value)
    for t in reversed(range(len(rewards))):
        next_value = last_value if t == len(rewards) - 1 else values[t + 1]
        keep = 1.0 - dones[t]
        delta = rewards[t] + gamma * next_value * keep - values[t]
        next_advantage = delta + gamma * lam * keep * next_advantage
        advantages[t] = next_advantage
    return advantages, advantages + values


def test_gae_matches_a_plain_loop() -> None:
    rng = np.random.default_rng(0)
    rewards = rng.normal(size=(37, 4)).astype(np.float32)
    values = rng.normal(size=(37, 4)).astype(np.float32)
    dones = rng.random((37, 4)) < 0.15
    last = rng.normal(size=4).astype(np.float32)
    advantages, returns = ppo.generalized_advantages(
        jnp.asarray(rewards), jnp.asarray(values), jnp.asarray(dones), jnp.asarray(last), 0.97, 0.9
    )
    expected_adv, expected_ret = plain_gae(
        rewards, values, dones.astype(np.float32), last, 0.97, 0.9
    )
    np.testing.assert_allclose(advantages, expected_adv, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(returns, expected_ret, rtol=1e-5, atol=1e-5)


def test_joint_ratio_is_the_product_of_per_agent_ratios() -> None:
    rng = np.random.default_rng(1)
    old = np.log(rng.uniform(0.05, 1.0, size=(64, 6)))
    new = np.log(rng.uniform(0.05, 1.0, size=(64, 6)))
    joint = np.exp(ppo.joint_log_ratio(jnp.asarray(new), jnp.asarray(old)))
    np.testing.assert_allclose(joint, np.prod(np.exp(new) / np.exp(old), axis=-1), rtol=1e-4)


def test_joint_ratio_of_forced_agents_is_one() -> None:
    logp = jnp.zeros((3, 4))
    assert np.allclose(np.exp(ppo.joint_log_ratio(logp, logp)), 1.0)


def test_clipped_surrogate_matches_numpy_reference() -> None:
    rng = np.random.default_rng(2)
    log_ratio = rng.normal(scale=0.2, size=256)
    advantages = rng.normal(size=256)
    eps = 0.05
    loss, diagnostics = ppo.clipped_surrogate_loss(
        jnp.asarray(log_ratio), jnp.asarray(advantages), eps
    )
    ratio = np.exp(log_ratio)
    expected = -np.mean(
        np.minimum(ratio * advantages, np.clip(ratio, 1 - eps, 1 + eps) * advantages)
    )
    assert float(loss) == pytest.approx(expected, rel=1e-5)
    assert float(diagnostics["clip_frac"]) == pytest.approx(np.mean(np.abs(ratio - 1) > eps))


@pytest.mark.parametrize("huber", [True, False])
@pytest.mark.parametrize("clipped", [True, False])
def test_value_loss_matches_numpy_reference(huber: bool, clipped: bool) -> None:
    rng = np.random.default_rng(3)
    values, old, targets = (rng.normal(scale=8.0, size=128) for _ in range(3))
    eps, delta = 0.2, 10.0

    def error(prediction):
        residual = targets - prediction
        if huber:
            small = np.abs(residual) <= delta
            return np.where(small, 0.5 * residual**2, delta * (np.abs(residual) - 0.5 * delta))
        return 0.5 * residual**2

    expected = error(values)
    if clipped:
        expected = np.maximum(expected, error(old + np.clip(values - old, -eps, eps)))
    config = PPOConfig(
        clip_eps=eps, huber_loss=huber, huber_delta=delta, clipped_value_loss=clipped
    )
    loss = ppo.value_loss(jnp.asarray(values), jnp.asarray(old), jnp.asarray(targets), config)
    assert float(loss) == pytest.approx(float(np.mean(expected)), rel=1e-5)


def test_value_norm_round_trip_and_statistics() -> None:
    state = ppo.value_norm_init()
    rng = np.random.default_rng(4)
    for _ in range(50):
        state = ppo.value_norm_update(state, jnp.asarray(rng.normal(5.0, 3.0, size=512)))
    x = jnp.asarray(rng.normal(5.0, 3.0, size=1000))
    normalized = ppo.value_norm_normalize(state, x)
    assert abs(float(jnp.mean(normalized))) < 0.2
    assert abs(float(jnp.std(normalized)) - 1.0) < 0.1
    np.testing.assert_allclose(
        ppo.value_norm_denormalize(state, normalized), x, rtol=1e-4, atol=1e-4
    )
