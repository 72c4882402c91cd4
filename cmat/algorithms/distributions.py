"""Per-agent action distributions over a team (batch shape [..., n_agents])."""

from __future__ import annotations

import distrax
import jax
import jax.numpy as jnp


def action_distribution(
    action_params: jax.Array, log_std: jax.Array, discrete: bool
) -> distrax.Distribution:
    """Categorical over masked logits, or a diagonal Gaussian with the reference MAT's
    std = sigmoid(log_std) * 0.5 (a learned, state-independent log-std)."""
    if discrete:
        return distrax.Categorical(logits=action_params)
    std = jax.nn.sigmoid(log_std) * 0.5
    return distrax.Independent(distrax.Normal(action_params, std), 1)


def greedy_action(action_params: jax.Array, discrete: bool) -> jax.Array:
    """The most likely action: argmax of masked logits, or the Gaussian mean."""
    if discrete:
        return jnp.argmax(action_params, axis=-1)
    return action_params
