"""PPO pieces shared by every algorithm: GAE, the clipped objective, value losses, ValueNorm.

Each is a plain function of arrays, unit-tested against a plain reference.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from cmat.config import PPOConfig


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

    def backward(
        carry: jax.Array, step: tuple[jax.Array, jax.Array]
    ) -> tuple[jax.Array, jax.Array]:
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
    log_ratio: jax.Array,
    advantages: jax.Array,
    clip_eps: float,
    mask: jax.Array | None = None,
    clip_range: tuple[jax.Array, jax.Array] | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """−E[min(R·A, clip(R, 1−ε, 1+ε)·A)] (paper eq. cmat), with PPO diagnostics.

    The mean runs over the entries where `mask` holds (active masks; every entry without one).
    log R is clamped to ±`LOG_RATIO_BOUND` before `exp`. `clip_range` (lower, upper), arrays
    broadcast to R, replaces [1−ε, 1+ε] (`joint_clip_range`)."""
    log_ratio = jnp.clip(log_ratio, -LOG_RATIO_BOUND, LOG_RATIO_BOUND)
    ratio = jnp.exp(log_ratio)
    unclipped = ratio * advantages
    if clip_range is None:
        clipped = jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * advantages
        outside = jnp.abs(ratio - 1.0) > clip_eps
    else:
        lower, upper = clip_range
        clipped = jnp.clip(ratio, lower, upper) * advantages
        outside = (ratio < lower) | (ratio > upper)
    loss = -masked_mean(jnp.minimum(unclipped, clipped), mask)
    diagnostics = {
        "approx_kl": masked_mean((ratio - 1.0) - log_ratio, mask),
        "clip_frac": masked_mean(outside.astype(jnp.float32), mask),
    }
    return loss, diagnostics


def joint_clip_range(clip_eps: float, active_agents: jax.Array) -> tuple[jax.Array, jax.Array]:
    """[(1−ε)^k, (1+ε)^k] for k active agents per sample [B]: the joint ratio's range when each
    agent's share of it, the geometric mean R^(1/k), is held to [1−ε, 1+ε]
    (`JointRatioOptions.joint_clip` per_agent). With k = 1 it is the paper's [1−ε, 1+ε]."""
    k = active_agents.astype(jnp.float32)
    return (1.0 - clip_eps) ** k, (1.0 + clip_eps) ** k


PER_AGENT_DIAGNOSTICS = 32
"""The largest team whose diagnostics name every agent (`entropy_agent_i`): every SMAX team (up
to 27 units) does; a fleet of hundreds of vehicles logs the spread over agents instead, so its
metrics.csv keeps a few dozen columns rather than one per vehicle."""


def policy_diagnostics(
    agent_log_ratio: jax.Array,
    joint_log_ratio: jax.Array,
    clip_eps: float,
    entropy: jax.Array,
    mask: jax.Array | None = None,
) -> dict[str, jax.Array]:
    """Trust-region diagnostics of one minibatch, for every algorithm alike.

    agent_log_ratio [B, n]: log π_i − log π_i,old; joint_log_ratio [B]: log of the ratio CMAT
    clips (Σ_i of the above, plus a sampled consensus's term); entropy [B, n]. Returns the
    approximate KL ((r − 1) − log r, Schulman's k3 estimator) and the clip fraction
    (|r − 1| > ε) of the joint ratio over samples and of the per-agent ratios over the active
    entries, and each agent's mean entropy over the samples where it is active
    (`entropy_agent_i`; a dead agent's forced action has entropy 0). Above
    `PER_AGENT_DIAGNOSTICS` agents (a fleet), the spread of those per-agent means replaces them:
    `entropy_agent_min`, `entropy_agent_median`, `entropy_agent_max`. `mask` [B, n] is the
    batch's `alive` whatever `ppo.active_masks` says: the diagnostics describe active agents."""
    joint = jnp.exp(jnp.clip(joint_log_ratio, -LOG_RATIO_BOUND, LOG_RATIO_BOUND))
    agent = jnp.exp(jnp.clip(agent_log_ratio, -LOG_RATIO_BOUND, LOG_RATIO_BOUND))
    diagnostics = {
        "joint_approx_kl": jnp.mean((joint - 1.0) - jnp.log(joint)),
        "joint_clip_frac": jnp.mean((jnp.abs(joint - 1.0) > clip_eps).astype(jnp.float32)),
        "agent_approx_kl": masked_mean((agent - 1.0) - jnp.log(agent), mask),
        "agent_clip_frac": masked_mean(
            (jnp.abs(agent - 1.0) > clip_eps).astype(jnp.float32), mask
        ),
    }
    if mask is None:
        per_agent = jnp.mean(entropy, axis=0)
    else:
        weights = jnp.broadcast_to(mask, entropy.shape).astype(entropy.dtype)
        per_agent = jnp.sum(entropy * weights, axis=0) / jnp.maximum(jnp.sum(weights, axis=0), 1.0)
    if per_agent.shape[0] > PER_AGENT_DIAGNOSTICS:
        diagnostics["entropy_agent_min"] = jnp.min(per_agent)
        diagnostics["entropy_agent_median"] = jnp.median(per_agent)
        diagnostics["entropy_agent_max"] = jnp.max(per_agent)
        return diagnostics
    for index in range(per_agent.shape[0]):
        diagnostics[f"entropy_agent_{index}"] = per_agent[index]
    return diagnostics


def explained_variance(predictions: jax.Array, targets: jax.Array) -> jax.Array:
    """1 − Var(targets − predictions) / Var(targets) over all entries; NaN where the targets
    do not vary."""
    variance = jnp.var(targets)
    return jnp.where(variance > 0, 1.0 - jnp.var(targets - predictions) / variance, jnp.nan)


def block_grad_norms(grads: Any) -> dict[str, jax.Array]:
    """The global norm of the gradient of each top-level parameter block (`grad_norm_NAME`):
    Flax's `params` collection levels are skipped, so CMAT's blocks are encoder,
    critic_compressor, critic_mlp, decoder, actor_compressor, actor_mlp; MAPPO's actor and
    critic."""
    while isinstance(grads, dict) and set(grads) == {"params"}:
        grads = grads["params"]
    if not isinstance(grads, dict):
        return {}
    return {f"grad_norm_{name}": optax.tree.norm(block) for name, block in grads.items()}


def value_loss(
    values: jax.Array,
    old_values: jax.Array,
    targets: jax.Array,
    ppo: PPOConfig,
    mask: jax.Array | None = None,
) -> jax.Array:
    """Critic loss: squared error to the targets, or the Huber loss with `ppo.huber_delta`
    (`ppo.huber_loss`), in the clipped PPO form with `ppo.clip_eps` around `old_values`
    (`ppo.clipped_value_loss`), averaged over the entries where `mask` holds (every entry
    without one). Shapes: any, all alike (mask broadcast to them)."""

    def error(prediction: jax.Array) -> jax.Array:
        residual = targets - prediction
        if ppo.huber_loss:
            huber: jax.Array = optax.huber_loss(residual, delta=ppo.huber_delta)
            return huber
        return 0.5 * jnp.square(residual)

    loss = error(values)
    if ppo.clipped_value_loss:
        clipped_values = old_values + jnp.clip(values - old_values, -ppo.clip_eps, ppo.clip_eps)
        loss = jnp.maximum(loss, error(clipped_values))
    return masked_mean(loss, mask)


def total_loss(
    policy_loss: jax.Array, entropy: jax.Array, critic_loss: jax.Array, ppo: PPOConfig
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """PPO's minimised objective L = L_policy − c_ent·H + c_v·L_value (paper Algorithm 1; the
    reference MAT's `policy_loss - dist_entropy * entropy_coef + value_loss * value_loss_coef`)
    and its three terms as metrics (`policy_loss`, `value_loss`, `entropy`)."""
    total = policy_loss - ppo.ent_coef * entropy + ppo.value_coef * critic_loss
    return total, {"policy_loss": policy_loss, "value_loss": critic_loss, "entropy": entropy}


def normalize(x: jax.Array, mask: jax.Array | None = None, eps: float = 1e-8) -> jax.Array:
    """(x − mean) / (std + eps), with mean and std over the entries where `mask` (broadcast to
    x) holds, as the reference MAT and MAPPO normalise advantages over active agents only."""
    mean = masked_mean(x, mask)
    std = jnp.sqrt(masked_mean(jnp.square(x - mean), mask))
    return (x - mean) / (std + eps)


class ValueNormState(NamedTuple):
    """Debiased running mean and mean square of value targets (MAT's ValueNorm,
    mat/utils/valuenorm.py: β = 0.99999, ε = 1e-5, variance floored at 1e-2), all []."""

    mean: jax.Array
    mean_square: jax.Array
    debias: jax.Array


VALUE_NORM_BETA = 0.99999
VALUE_NORM_EPS = 1e-5


def value_norm_init() -> ValueNormState:
    """No targets seen: every statistic 0."""
    zero = jnp.zeros((), jnp.float32)
    return ValueNormState(zero, zero, zero)


def value_norm_update(state: ValueNormState, targets: jax.Array) -> ValueNormState:
    """The statistics after one batch of (unnormalised) targets of any shape."""
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
    """x (returns) in the normalised space the critics predict in."""
    mean, std = _moments(state)
    return (x - mean) / std


def value_norm_denormalize(state: ValueNormState, x: jax.Array) -> jax.Array:
    """x (critic outputs) back in return units, for GAE."""
    mean, std = _moments(state)
    return x * std + mean
