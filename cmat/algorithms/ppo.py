"""PPO pieces shared by every algorithm: GAE, the clipped objective, value losses, ValueNorm.

Each is a plain function of arrays, unit-tested against a plain reference.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax


def generalized_advantages(
    rewards: jax.Array,
    values: jax.Array,
    dones: jax.Array,
    last_value: jax.Array,
    gamma: float,
    gae_lambda: float,
) -> tuple[jax.Array, jax.Array]:
    """GAE over time-major arrays [T, ...] (Schulman et al. 2016).

    values[t] = V(s_t); dones[t] says the transition from s_t ended the episode (no bootstrap);
    last_value = V(s_T). Returns (advantages, returns = advantages + values).
    """
    next_values = jnp.concatenate([values[1:], last_value[None]], axis=0)
    not_done = 1.0 - dones.astype(values.dtype)
    deltas = rewards + gamma * next_values * not_done - values

    def backward(carry: jax.Array, step: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
        delta, keep = step
        advantage = delta + gamma * gae_lambda * keep * carry
        return advantage, advantage

    _, advantages = jax.lax.scan(
        backward, jnp.zeros_like(last_value), (deltas, not_done), reverse=True
    )
    return advantages, advantages + values


def joint_log_ratio(log_probs: jax.Array, old_log_probs: jax.Array) -> jax.Array:
    """log R = Σ_i (log π_i − log π_i,old) over the agent axis (last), paper eq. ratio.

    Summed in log space, so the joint ratio is the product of per-agent ratios without overflow.
    An agent whose only available action is forced contributes exactly 0.
    """
    return jnp.sum(log_probs - old_log_probs, axis=-1)


LOG_RATIO_BOUND = 20.0
"""|log R| is clamped to this before `exp`. A joint log-ratio sums n per-agent terms, so with
many agents it can pass float32's exp limit (about 88.7: exp(89) = inf, and inf·A or its
gradient turns every parameter into NaN after global-norm clipping). Inside e^±20 (about 2e-9
to 5e8) the loss and its gradient are unchanged; the clip range 1 ± ε sits far inside it. A
sample beyond it contributes a constant: its ratio is no longer a meaningful trust-region
quantity."""


def masked_mean(x: jax.Array, mask: jax.Array | None = None) -> jax.Array:
    """Mean of `x` over the entries where `mask` (broadcast to x) holds; plain mean without a
    mask. An all-False mask gives 0 (the reference's sum / count with no active entry)."""
    if mask is None:
        return jnp.mean(x)
    weights = jnp.broadcast_to(mask, x.shape).astype(x.dtype)
    return jnp.sum(x * weights) / jnp.maximum(jnp.sum(weights), 1.0)


def clipped_surrogate_loss(
    log_ratio: jax.Array, advantages: jax.Array, clip_eps: float, mask: jax.Array | None = None
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """−E[min(R·A, clip(R, 1−ε, 1+ε)·A)] (paper eq. cmat), with PPO diagnostics.

    The mean runs over the entries where `mask` holds (active masks; every entry without one).
    log R is clamped to ±`LOG_RATIO_BOUND` before `exp`."""
    log_ratio = jnp.clip(log_ratio, -LOG_RATIO_BOUND, LOG_RATIO_BOUND)
    ratio = jnp.exp(log_ratio)
    unclipped = ratio * advantages
    clipped = jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * advantages
    loss = -masked_mean(jnp.minimum(unclipped, clipped), mask)
    diagnostics = {
        "approx_kl": masked_mean((ratio - 1.0) - log_ratio, mask),
        "clip_frac": masked_mean((jnp.abs(ratio - 1.0) > clip_eps).astype(jnp.float32), mask),
    }
    return loss, diagnostics


def value_loss(
    values: jax.Array,
    old_values: jax.Array,
    targets: jax.Array,
    clip_eps: float,
    huber: bool,
    huber_delta: float,
    clipped: bool,
    mask: jax.Array | None = None,
) -> jax.Array:
    """Critic loss: squared or Huber error to the targets, optionally the clipped PPO form,
    averaged over the entries where `mask` holds (every entry without one)."""

    def error(prediction: jax.Array) -> jax.Array:
        residual = targets - prediction
        if huber:
            return optax.huber_loss(residual, delta=huber_delta)
        return 0.5 * jnp.square(residual)

    loss = error(values)
    if clipped:
        clipped_values = old_values + jnp.clip(values - old_values, -clip_eps, clip_eps)
        loss = jnp.maximum(loss, error(clipped_values))
    return masked_mean(loss, mask)


def normalize(x: jax.Array, mask: jax.Array | None = None, eps: float = 1e-8) -> jax.Array:
    """(x − mean) / (std + eps), with mean and std over the entries where `mask` (broadcast to
    x) holds, as the reference MAT and MAPPO normalise advantages over active agents only."""
    mean = masked_mean(x, mask)
    std = jnp.sqrt(masked_mean(jnp.square(x - mean), mask))
    return (x - mean) / (std + eps)


class ValueNormState(NamedTuple):
    """Debiased running mean and mean square of value targets (MAT's ValueNorm)."""

    mean: jax.Array
    mean_square: jax.Array
    debias: jax.Array


VALUE_NORM_BETA = 0.99999
VALUE_NORM_EPS = 1e-5


def value_norm_init() -> ValueNormState:
    zero = jnp.zeros((), jnp.float32)
    return ValueNormState(zero, zero, zero)


def value_norm_update(state: ValueNormState, targets: jax.Array) -> ValueNormState:
    beta = VALUE_NORM_BETA
    return ValueNormState(
        mean=beta * state.mean + (1 - beta) * jnp.mean(targets),
        mean_square=beta * state.mean_square + (1 - beta) * jnp.mean(jnp.square(targets)),
        debias=beta * state.debias + (1 - beta),
    )


def _moments(state: ValueNormState) -> tuple[jax.Array, jax.Array]:
    debias = jnp.maximum(state.debias, VALUE_NORM_EPS)
    mean = state.mean / debias
    variance = jnp.maximum(state.mean_square / debias - jnp.square(mean), 1e-2)
    return mean, jnp.sqrt(variance)


def value_norm_normalize(state: ValueNormState, x: jax.Array) -> jax.Array:
    mean, std = _moments(state)
    return (x - mean) / std


def value_norm_denormalize(state: ValueNormState, x: jax.Array) -> jax.Array:
    mean, std = _moments(state)
    return x * std + mean
