"""What every network in cmat ends with: action heads, value heads, masking and distributions.

An actor is a torso (CMAT's encoder and consensus, MAT's decoder, an MLP) followed by
`ActionHead`, whose discrete logits go through `mask_unavailable`; `action_distribution` turns
head outputs into per-agent distributions (batch shape [..., n_agents]) and `greedy_action`
into the most likely action. A critic ends with `ValueHead`.
"""

from __future__ import annotations

from typing import Any

import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp

from cmat.networks.layers import HIDDEN_GAIN, SMALL_GAIN, dense, scan_positions

MASKED_LOGIT = -1e9
"""Logit of an unavailable action: exp underflows to exactly 0 probability in float32."""


def mask_unavailable(action_params: jax.Array, action_mask: jax.Array, discrete: bool) -> jax.Array:
    """Discrete logits [..., A] with the actions `action_mask` [..., A] rules out set to
    `MASKED_LOGIT`; continuous parameters unchanged."""
    if discrete:
        return jnp.where(action_mask, action_params, MASKED_LOGIT)
    return action_params


class SharedInputDense(nn.Module):
    """Dense([x_i; s]) for every token x_i and one vector s shared by all of them.

    W[x_i; s] + b = W_x x_i + (W_s s + b): the shared half is multiplied once per team instead
    of once per agent. Parameters are those of `dense` on the concatenation, so the two forms
    are interchangeable.
    """

    features: int

    @nn.compact
    def __call__(self, tokens: jax.Array, shared: jax.Array | None = None) -> jax.Array:
        """tokens [..., n, a], shared [..., s] or None -> [..., n, features]."""
        token_features = tokens.shape[-1]
        shared_features = 0 if shared is None else shared.shape[-1]
        kernel = self.param(
            "kernel", nn.initializers.orthogonal(HIDDEN_GAIN),
            (token_features + shared_features, self.features),
        )
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        if shared is None:
            return tokens @ kernel + bias
        return tokens @ kernel[:token_features] + (shared @ kernel[token_features:] + bias)[
            ..., None, :
        ]


class ActionHead(nn.Module):
    """Actor-MLP([ô_i; c]) (paper eq. actor_MLP), shared across agents.

    `shared` is the team-wide half of every agent's input (CMAT's consensus c); heads whose
    input is per-agent only (MAT, Triple-BERT) pass None.
    """

    n_embd: int
    action_dim: int
    discrete: bool
    init_gain: float
    log_std_init: float = 1.0
    """Initial log-std of continuous heads (std = sigmoid(log_std) · 0.5, reference MAT)."""

    @nn.compact
    def __call__(
        self, features: jax.Array, shared: jax.Array | None = None
    ) -> tuple[jax.Array, jax.Array]:
        first = SharedInputDense(self.n_embd, name="Dense_0")(features, shared)
        hidden = nn.LayerNorm()(nn.gelu(first))
        params = dense(self.action_dim, self.init_gain, name="Dense_1")(hidden)
        log_std = self.param(
            "log_std", nn.initializers.constant(self.log_std_init),
            (0 if self.discrete else self.action_dim,),
        )
        return params, log_std


class ValueHead(nn.Module):
    """Critic-MLP(e0) -> V(O) (paper eq. critic); the output layer starts with `gain` (the
    reference MAT's value head: gain 0.01)."""

    n_embd: int
    gain: float = SMALL_GAIN

    @nn.compact
    def __call__(self, e0: jax.Array) -> jax.Array:
        return dense(1, self.gain)(nn.gelu(dense(self.n_embd)(e0)))[..., 0]


def action_distribution(
    action_params: jax.Array, log_std: jax.Array, discrete: bool
) -> distrax.Distribution:
    """Categorical over masked logits, or a diagonal Gaussian with the reference MAT's
    std = sigmoid(log_std) * 0.5 (a learned, state-independent log-std)."""
    if discrete:
        return distrax.Categorical(logits=action_params)
    std = jax.nn.sigmoid(log_std) * 0.5
    return distrax.Independent(distrax.Normal(action_params, std), 1)


def start_action(action_dim: int, discrete: bool) -> jax.Array:
    """An autoregressive decoder's 'no previous agent' action: index -1 (one-hot slot 0) or a
    zero vector."""
    if discrete:
        return jnp.array(-1, jnp.int32)
    return jnp.zeros(action_dim)


def previous_action_features(actions: jax.Array, action_dim: int, discrete: bool) -> jax.Array:
    """A decoder's inputs for previous actions: one-hot over A+1 slots (slot 0: the start
    action), or the raw continuous vector."""
    return jax.nn.one_hot(actions + 1, action_dim + 1) if discrete else actions


def greedy_action(action_params: jax.Array, discrete: bool) -> jax.Array:
    """The most likely action: argmax of masked logits, or the Gaussian mean."""
    if discrete:
        return jnp.argmax(action_params, axis=-1)
    return action_params


def decode_in_order(
    module: nn.Module,
    context: Any,
    state: Any,
    action_mask: jax.Array,
    order: jax.Array,
    key: jax.Array | None,
    start: jax.Array,
    discrete: bool,
) -> tuple[jax.Array, jax.Array, Any]:
    """Agents act one after another along `order` [n] (MAT's autoregressive decoding, eq. mat).

    The k-th agent's decoder features and the decoder's next `state` come from
    `module.decode_step(context, k, previous action, state)` (the start action for the first),
    its action parameters from `module.policy_params(features, its mask)`, and its action is
    sampled (greedy where `key` is None) and fed to the next. Up to `SCAN_LENGTH` agents k is
    static and the positions unrolled; above, one position is compiled once and scanned
    (`scan_positions`), so compile time does not grow with the team. `action_mask` [n, A] is in
    agent order. Returns actions [n] (or [n, A]) and log-probs [n] in agent order, and the
    decoder's state after the last agent."""
    n = order.shape[0]
    keys = None if key is None else jax.random.split(key, n)

    def position(
        module: nn.Module, carry: tuple[jax.Array, Any], inputs: tuple[Any, Any]
    ) -> tuple[tuple[jax.Array, Any], tuple[jax.Array, jax.Array]]:
        previous, state = carry
        k, (mask, step_key) = inputs
        features, state = module.decode_step(context, k, previous, state)
        params, log_std = module.policy_params(features, mask)
        distribution = action_distribution(params, log_std, discrete)
        if step_key is None:
            action = greedy_action(params, discrete)
            log_prob = distribution.log_prob(action)
        else:
            action, log_prob = distribution.sample_and_log_prob(seed=step_key)
        return (action, state), (action, log_prob)

    (_, state), (actions, log_probs) = scan_positions(
        module, position, (start, state), (action_mask[order], keys), n
    )
    inverse = jnp.argsort(order)
    return actions[inverse], log_probs[inverse], state
