"""The joint ratio's PPO objective, shared by CMAT and Triple-BERT: the team as one multi-action
agent trained with single-agent PPO on R = Π_i π_i / π_i,old (paper eq. cmat, eq. ratio), with
one team value. Each algorithm computes its own log R (CMAT adds its consensus's term) and
hands it here with its action distribution, its value and its section's `JointRatioOptions`.
"""

from __future__ import annotations

import distrax
import jax
import jax.numpy as jnp

from cmat.algorithms.base import Batch, active_mask
from cmat.algorithms.options import JointRatioOptions
from cmat.algorithms.ppo import (
    clipped_surrogate_loss,
    joint_clip_range,
    masked_mean,
    policy_diagnostics,
    total_loss,
    value_loss,
)
from cmat.config import PPOConfig


def joint_ratio_loss(
    log_ratio: jax.Array, distribution: distrax.Distribution, value: jax.Array, batch: Batch,
    ppo: PPOConfig, options: JointRatioOptions,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Clipped surrogate on the joint ratio, per-agent entropy, team value loss: the total loss
    and its metrics.

    `log_ratio` [B] is log R; `distribution` the per-agent action distribution [B, n];
    `value` [B] the team value V(O). The entropy is averaged over agents (over active agents
    with `ppo.active_masks`). Named departures from the paper (`JointRatioOptions`):
    `joint_clip=per_agent` clips R to [(1−ε)^k, (1+ε)^k] for k active agents instead of
    [1−ε, 1+ε] (eq. cmat); `entropy_reduction=sum` weights the entropy of the joint policy
    Σ_i H(π_i) instead of its mean over agents (n times the mean without active masks)."""
    clip_range = None
    if options.joint_clip == "per_agent":
        alive = batch.alive if batch.alive is not None else jnp.ones(batch.log_probs.shape)
        clip_range = joint_clip_range(ppo.clip_eps, jnp.sum(alive, axis=-1))
    policy_loss, diagnostics = clipped_surrogate_loss(
        log_ratio, batch.advantages, ppo.clip_eps, clip_range=clip_range
    )
    entropies = distribution.entropy()
    entropy = masked_mean(entropies, active_mask(batch, ppo))
    if options.entropy_reduction == "sum":
        entropy = entropy * entropies.shape[-1]
    critic_loss = value_loss(value, batch.values, batch.targets, ppo)
    total, terms = total_loss(policy_loss, entropy, critic_loss, ppo)
    return total, {
        **terms,
        **diagnostics,
        **policy_diagnostics(
            distribution.log_prob(batch.actions) - batch.log_probs, log_ratio, ppo.clip_eps,
            entropies, batch.alive,
        ),
    }
