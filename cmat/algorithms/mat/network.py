"""The Multi-Agent Transformer network (Wen et al. 2022) as in the official PKU-MARL code.

O --Encoder--> Ô --per-agent head--> V(ô_i);  V(O) = mean_i V(ô_i)  (paper text after eq. mat)
Each V(ô_i) is regressed on the team's value target (the reference implementation's loss); the
team value V(O) is what GAE and the target critic use.
a^σ(k-1) --embed--> causal self-attention --> ô^σ(k) queries it --> π^σ(k)(· | O, a^σ(<k))

The decoder runs along a decision order σ, a permutation of the agents (the identity for MAT, a
sampled one for PMAT): position k acts for agent σ(k), and as in the reference decode block its
query and residual are that agent's ô^σ(k), attending causally to the features of the action
tokens a^σ(1..k-1) (a start token first). Acting iterates the positions with a key/value cache;
training is one causal pass over the shifted actions, the same computation.

All methods are per team (agents on the leading axis); batch them with `jax.vmap`.
"""

from __future__ import annotations

from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from cmat.config import NetworkConfig
from cmat.networks.heads import (
    ActionHead,
    decode_in_order,
    mask_unavailable,
    previous_action_features,
    start_action,
)
from cmat.networks.layers import (
    SMALL_GAIN,
    FeedForward,
    KeyValues,
    MultiHeadAttention,
    ObservationEncoder,
    dense,
)


class BlockCache(NamedTuple):
    """Keys/values of the positions decoded so far, for both attentions of a decode block."""

    tokens: KeyValues
    features: KeyValues


class MATOutput(NamedTuple):
    """Teacher-forced outputs of one team, agents in index order."""

    action_params: jax.Array
    """[n, A]: masked logits (discrete) or Gaussian means (continuous)."""
    log_std: jax.Array
    """[A] learned state-independent log-std (continuous); empty for discrete heads."""
    agent_values: jax.Array
    """[n] per-agent values V(ô_i); the team value V(O) is their mean."""
    encoded: jax.Array
    """[n, d] the encoder output Ô."""


class MATDecodeBlock(nn.Module):
    """The reference decode block, post-LayerNorm:

    x = LN(t + CausalAttn(t, t)),  y = LN(ô + CausalAttn(query=ô, keys/values=x)),
    output LN(y + MLP(y)), where t are the action tokens and ô the agents' encodings.
    """

    n_embd: int
    n_head: int
    gain: float = SMALL_GAIN

    def setup(self) -> None:
        self.token_attention = MultiHeadAttention(self.n_embd, self.n_head, self.gain)
        self.agent_attention = MultiHeadAttention(self.n_embd, self.n_head, self.gain)
        self.feed_forward = FeedForward(self.n_embd, self.gain)
        self.norms = [nn.LayerNorm() for _ in range(3)]

    def step(
        self, token: jax.Array, agent: jax.Array, cache: BlockCache, position: int | jax.Array
    ) -> tuple[jax.Array, BlockCache]:
        """One position: token and agent [1, d], given the cache (`empty_cache`) with the
        positions before it written; `position` static, or traced under `scan_positions`."""
        attended, token_kv = self.token_attention.attend_and_write(token, token, cache.tokens,
                                                                   position)
        x = self.norms[0](token + attended)
        attended, feature_kv = self.agent_attention.attend_and_write(agent, x, cache.features,
                                                                     position)
        y = self.norms[1](agent + attended)
        return self.norms[2](y + self.feed_forward(y)), BlockCache(token_kv, feature_kv)

    def empty_cache(self, token: jax.Array, length: int) -> BlockCache:
        """Both attentions' caches of `length` positions for one token like `token` [d]."""
        return BlockCache(self.token_attention.empty_cache(token, length),
                          self.agent_attention.empty_cache(token, length))

    def __call__(self, tokens: jax.Array, agents: jax.Array) -> jax.Array:
        """All positions at once (causal masks); equals iterating `step`."""
        x = self.norms[0](tokens + self.token_attention(tokens, tokens, causal=True))
        y = self.norms[1](agents + self.agent_attention(agents, x, causal=True))
        out: jax.Array = self.norms[2](y + self.feed_forward(y))
        return out


class AgentValueHead(nn.Module):
    """V(ô_i) for every agent: the reference encoder head (Linear, GELU, LayerNorm, Linear)."""

    n_embd: int
    init_gain: float

    @nn.compact
    def __call__(self, encoded: jax.Array) -> jax.Array:
        hidden = nn.LayerNorm()(nn.gelu(dense(self.n_embd)(encoded)))
        return dense(1, self.init_gain)(hidden)[..., 0]


class OrderScorer(nn.Module):
    """PMAT's scoring block (Hu et al. 2025; reference `ScoringBlock`, NUDT-BI-MARL/PMAT
    `mat/algorithms/mat/algorithm/pma_transformer.py`, 8894f9e): LayerNorm, then `layers` ×
    (Dense(`hidden`, gain √2), GELU, LayerNorm), then Dense(1, `init_gain`) squashed to a weight
    w = 9·sigmoid + 1 in (1, 10); the order's probability is Π_k w_σ(k) / Σ_{j≥k} w_σ(j).

    encoded [..., n, d] -> log w [..., n], each agent's Plackett-Luce log-weight in (0, log 10).
    """

    init_gain: float
    hidden: int = 64
    """The reference's `hid_dim`, whatever the transformer's width."""
    layers: int = 2
    """The reference SMAC script's `--rank_layer_N`."""

    @nn.compact
    def __call__(self, encoded: jax.Array) -> jax.Array:
        x = nn.LayerNorm()(encoded)
        for _ in range(self.layers):
            x = nn.LayerNorm()(nn.gelu(dense(self.hidden)(x)))
        weight = 9.0 * nn.sigmoid(dense(1, self.init_gain)(x)[..., 0]) + 1.0
        return jnp.log(weight)


class MATNetwork(nn.Module):
    """MAT actor-critic over one team; the decoder follows a given decision order. The
    previous action's embedding has no bias for discrete actions, as the reference's
    `action_encoder` (`nn.Linear(action_dim + 1, n_embd, bias=False)`, ma_transformer.py)."""

    config: NetworkConfig
    num_agents: int
    action_dim: int
    discrete: bool
    attention_block: int = 0
    """`EncoderOptions.attention_block`: agents per block of the encoder's attention."""
    inducing_points: int = 0
    """`EncoderOptions.inducing_points`: learned vectors the encoder's agents attend through."""

    def setup(self) -> None:
        cfg = self.config
        gain = cfg.init_gain
        self.encoder = ObservationEncoder(cfg.n_embd, cfg.n_head, cfg.n_block, gain,
                                          self.attention_block, self.inducing_points)
        self.value_head = AgentValueHead(cfg.n_embd, gain)
        self.action_embedding = dense(cfg.n_embd, use_bias=not self.discrete)
        self.token_norm = nn.LayerNorm()
        self.blocks = [MATDecodeBlock(cfg.n_embd, cfg.n_head, gain) for _ in range(cfg.n_block)]
        self.head = ActionHead(cfg.n_embd, self.action_dim, self.discrete, gain, cfg.log_std_init)

    def encode(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Ô [n, d] and the per-agent values V(ô_i) [n]."""
        encoded = self.encoder(obs)
        return encoded, self.value_head(encoded)

    def value(self, obs: jax.Array) -> jax.Array:
        """The team value V(O) = mean_i V(ô_i)."""
        return jnp.mean(self.encode(obs)[1], axis=-1)

    def start_action(self) -> jax.Array:
        return start_action(self.action_dim, self.discrete)

    def embed(self, actions: jax.Array) -> jax.Array:
        """Decoder tokens of previous actions (`previous_action_features`)."""
        features = previous_action_features(actions, self.action_dim, self.discrete)
        tokens: jax.Array = self.token_norm(nn.gelu(self.action_embedding(features)))
        return tokens

    def policy_params(
        self, features: jax.Array, action_mask: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        params, log_std = self.head(features)
        return mask_unavailable(params, action_mask, self.discrete), log_std

    def decode(
        self, encoded: jax.Array, action_mask: jax.Array, order: jax.Array, key: jax.Array | None
    ) -> tuple[jax.Array, jax.Array]:
        """Acts agent by agent along `order`, feeding each action back (sampled, or the most
        likely one when `key` is None). Returns actions and their log-probs in agent order."""
        token = jnp.zeros((self.config.n_embd,), encoded.dtype)
        caches = [block.empty_cache(token, self.num_agents) for block in self.blocks]
        actions, log_probs, _ = decode_in_order(self, encoded[order], caches, action_mask, order,
                                                key, self.start_action(), self.discrete)
        return actions, log_probs

    def decode_step(
        self, agents: jax.Array, k: int | jax.Array, previous: jax.Array,
        caches: list[BlockCache],
    ) -> tuple[jax.Array, list[BlockCache]]:
        """The decoder features [d] of position k, whose agent's encoding is agents[k] (agents
        [n, d] in decision order), given the previous position's action."""
        x = self.embed(previous[None])
        agent = jax.lax.dynamic_slice_in_dim(agents, k, 1)
        written = []
        for block, cache in zip(self.blocks, caches, strict=True):
            x, cache = block.step(x, agent, cache, k)
            written.append(cache)
        return x[0], written

    def __call__(
        self, obs: jax.Array, action_mask: jax.Array, actions: jax.Array, order: jax.Array
    ) -> MATOutput:
        """Teacher forcing: every agent's distribution given the actions of those before it
        in `order`, in one causal pass over the shifted action sequence."""
        encoded, agent_values = self.encode(obs)
        ordered = actions[order]
        shifted = jnp.concatenate([self.start_action()[None], ordered[:-1]], axis=0)
        x = self.embed(shifted)
        for block in self.blocks:
            x = block(x, encoded[order])
        inverse = jnp.argsort(order)
        params, log_std = self.policy_params(x[inverse], action_mask)
        return MATOutput(params, log_std, agent_values, encoded)
