"""Transformer building blocks shared by CMAT and the transformer baselines.

Arrays carry any number of leading batch axes; the token axis is the second to last. Blocks are
post-LayerNorm, as in the reference MAT implementation.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

HIDDEN_GAIN = float(np.sqrt(2.0))
"""Orthogonal gain of layers followed by an activation (the reference MAT's `activate=True`:
`calculate_gain('relu')`)."""
SMALL_GAIN = 0.01
"""Orthogonal gain of the reference MAT's other layers (its `init_` default, gain=0.01): the
query, key, value and output projections, the second feed-forward layer, the output heads.
Blocks take it as their `gain` (`NetworkConfig.init_gain`)."""


def dense(
    features: int, gain: float = HIDDEN_GAIN, name: str | None = None, use_bias: bool = True
) -> nn.Dense:
    """A dense layer with orthogonal weights of the given gain and zero bias (or none)."""
    return nn.Dense(
        features, kernel_init=nn.initializers.orthogonal(gain), bias_init=nn.initializers.zeros,
        name=name, use_bias=use_bias,
    )


KeyValues = tuple[jax.Array, jax.Array]
"""Keys and values of attended positions, each [..., heads, L, d/heads] (head-major)."""


def extend(cache: KeyValues, new: KeyValues, position: int | jax.Array) -> KeyValues:
    """The cache (`MultiHeadAttention.empty_cache`) with the one position of `new` written at
    `position`.

    One buffer per sequence, written in place, rather than a concatenation per position: the
    unrolled CMAT decoder's gradient compiles and runs faster at large m (docs/speed.md)."""
    return (
        jax.lax.dynamic_update_slice_in_dim(cache[0], new[0], position, axis=-2),
        jax.lax.dynamic_update_slice_in_dim(cache[1], new[1], position, axis=-2),
    )


SCAN_LENGTH = 16
"""Above this many sequential positions a decoder (CMAT's consensus iterations, MAT's and
Sable's agents) runs one position compiled once and scanned (`scan_positions`), so compile time
does not grow with the sequence; up to it the positions are unrolled."""


def scan_positions(
    module: nn.Module, step: Callable[..., tuple[Any, Any]], carry: Any, xs: Any, length: int,
    scan: bool | None = None,
) -> tuple[Any, Any]:
    """`step(module, carry, (k, x_k)) -> (carry, y_k)` for k = 0..length-1, x_k the k-th slice
    of every leaf of `xs` (None for none): a Python loop with a static k up to `SCAN_LENGTH`,
    else `nn.scan` with a traced k and the parameters shared. Returns the last carry and the
    y_k stacked on a leading axis. Both compute the same numbers up to float rounding (a traced
    k attends over whole caches with the unwritten positions masked:
    `MultiHeadAttention.attend_and_write`). `scan` forces one way or the other."""
    if (length > SCAN_LENGTH) if scan is None else scan:
        run = nn.scan(step, variable_broadcast="params", split_rngs={"params": False},
                      length=length)
        return run(module, carry, (jnp.arange(length), xs))
    outputs = []
    for k in range(length):
        carry, y = step(module, carry, (k, jax.tree.map(lambda leaf, k=k: leaf[k], xs)))
        outputs.append(y)
    return carry, jax.tree.map(lambda *leaves: jnp.stack(leaves), *outputs)


class MultiHeadAttention(nn.Module):
    """Scaled dot-product attention with separate query, key and value projections.

    Heads are kept on the axis before positions, so both products are batched matmuls whose
    batch axes lead and whose contraction axes are minor: with one head (the reference
    setting) no transpose is left. On CPU this halved the time of SMAX 3m's per-team
    attention (64 envs x 3 agents) against a positions-then-heads layout (docs/speed.md).
    """

    n_embd: int
    n_head: int
    gain: float = SMALL_GAIN
    """Orthogonal gain of the four projections."""

    def setup(self) -> None:
        self.query = dense(self.n_embd, self.gain)
        self.key = dense(self.n_embd, self.gain)
        self.value = dense(self.n_embd, self.gain)
        self.out = dense(self.n_embd, self.gain)

    def split_heads(self, x: jax.Array) -> jax.Array:
        """[..., L, d] -> [..., heads, L, d/heads]."""
        heads = x.reshape(*x.shape[:-1], self.n_head, self.n_embd // self.n_head)
        return jnp.moveaxis(heads, -2, -3)

    def project_memory(self, memory: jax.Array) -> KeyValues:
        """Keys and values of `memory` [..., L, d]."""
        return self.split_heads(self.key(memory)), self.split_heads(self.value(memory))

    def scaled_queries(self, x: jax.Array) -> jax.Array:
        """Queries of x [..., L, d], split into heads and scaled by 1/sqrt(d/heads)."""
        queries: jax.Array = self.split_heads(self.query(x)) / np.sqrt(self.n_embd // self.n_head)
        return queries

    def merge_heads(self, heads: jax.Array, x: jax.Array) -> jax.Array:
        """The output projection of heads [..., heads, L, d/heads] for queries like x."""
        return self.out(jnp.moveaxis(heads, -3, -2).reshape(*x.shape[:-1], self.n_embd))

    def attend(
        self, x: jax.Array, keys: jax.Array, values: jax.Array, causal: bool = False,
        visible: jax.Array | None = None, query_block: int = 0,
    ) -> jax.Array:
        """Query positions of `x` attend to the given keys: all of them, with `causal`
        position k to keys 0..k only, with `visible` [keys] (bool) the visible keys only.
        With `query_block` > 0 (not with `causal`) and more queries than that, the queries go
        in blocks of that many (`blockwise_attention`): the same result, in memory linear in
        the number of queries at a fixed number of keys."""
        queries = self.scaled_queries(x)
        if 0 < query_block < x.shape[-2] and not causal:
            heads = blockwise_attention(queries, keys, values, query_block, visible)
        else:
            logits = jnp.einsum("...qd,...kd->...qk", queries, keys)
            if visible is not None:
                logits = jnp.where(visible, logits, jnp.finfo(logits.dtype).min)
            if causal:
                mask = jnp.tril(jnp.ones((x.shape[-2], keys.shape[-2]), dtype=bool))
                logits = jnp.where(mask, logits, jnp.finfo(logits.dtype).min)
            heads = jnp.einsum("...qk,...kd->...qd", jax.nn.softmax(logits, axis=-1), values)
        return self.merge_heads(heads, x)

    def empty_cache(self, token: jax.Array, length: int) -> KeyValues:
        """Zero keys and values of `length` positions for tokens like `token` [..., d]."""
        shape = (*token.shape[:-1], self.n_head, length, self.n_embd // self.n_head)
        return jnp.zeros(shape, token.dtype), jnp.zeros(shape, token.dtype)

    def attend_and_write(
        self, x: jax.Array, memory: jax.Array, cache: KeyValues, position: int | jax.Array
    ) -> tuple[jax.Array, KeyValues]:
        """x [..., 1, d] attends to positions 0..position-1 of a cache (`empty_cache`) and to
        `memory` [..., 1, d] at `position`; returns the output and the cache with `memory`'s
        keys and values written there (`extend`).

        A static position reads the written prefix. A traced one (`scan_positions`) reads the
        whole cache before writing to it, the positions from `position` on masked, and joins
        the new position's score in the softmax: the same numbers up to rounding, and no read
        follows the write, so XLA's CPU backend makes half the copies of the carried cache at
        each position (docs/speed.md)."""
        new = self.project_memory(memory)
        if isinstance(position, int):
            cache = extend(cache, new, position)
            return self.attend(x, cache[0][..., : position + 1, :],
                               cache[1][..., : position + 1, :]), cache
        queries = self.scaled_queries(x)
        earlier = jnp.einsum("...qd,...kd->...qk", queries, cache[0])
        earlier = jnp.where(jnp.arange(cache[0].shape[-2]) < position, earlier,
                            jnp.finfo(earlier.dtype).min)
        own = jnp.einsum("...qd,...kd->...qk", queries, new[0])
        top = jnp.maximum(earlier.max(axis=-1, keepdims=True), own)
        earlier, own = jnp.exp(earlier - top), jnp.exp(own - top)
        heads = (jnp.einsum("...qk,...kd->...qd", earlier, cache[1]) + own * new[1]) / (
            earlier.sum(axis=-1, keepdims=True) + own)
        return self.merge_heads(heads, x), extend(cache, new, position)

    def __call__(
        self, x: jax.Array, memory: jax.Array, causal: bool = False, query_block: int = 0
    ) -> jax.Array:
        return self.attend(x, *self.project_memory(memory), causal=causal,
                           query_block=query_block)


def blockwise_attention(
    queries: jax.Array, keys: jax.Array, values: jax.Array, block: int,
    visible: jax.Array | None = None,
) -> jax.Array:
    """softmax(q kᵀ) v for queries [..., Lq, d] in blocks of `block` queries, one block at a
    time (`lax.map`), each block's scores recomputed in the backward pass (`jax.checkpoint`):
    the scores held at once are [..., block, Lk] instead of [..., Lq, Lk], in the forward and
    the backward pass. Each query's softmax is over all keys, as in full attention, so the
    result is the same up to floating-point order (and stays equivariant in the queries);
    `visible` [Lk] masks keys. Queries are padded to whole blocks and the padding dropped."""
    length = queries.shape[-2]
    blocks = -(-length // block)
    padded = jnp.pad(queries, [(0, 0)] * (queries.ndim - 2) + [(0, blocks * block - length),
                                                                (0, 0)])
    stacked = jnp.moveaxis(padded.reshape(*padded.shape[:-2], blocks, block,
                                          padded.shape[-1]), -3, 0)

    @jax.checkpoint
    def one(query_block: jax.Array) -> jax.Array:
        logits = jnp.einsum("...qd,...kd->...qk", query_block, keys)
        if visible is not None:
            logits = jnp.where(visible, logits, jnp.finfo(logits.dtype).min)
        return jnp.einsum("...qk,...kd->...qd", jax.nn.softmax(logits, axis=-1), values)

    out = jnp.moveaxis(jax.lax.map(one, stacked), 0, -3)
    return out.reshape(*out.shape[:-3], blocks * block, out.shape[-1])[..., :length, :]


class FeedForward(nn.Module):
    """Dense (ReLU gain) → GELU → Dense (`gain`), the reference block MLP."""

    n_embd: int
    gain: float = SMALL_GAIN

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        return dense(self.n_embd, self.gain)(nn.gelu(dense(self.n_embd)(x)))


class EncoderBlock(nn.Module):
    """Bidirectional self-attention over agents; no positional information, so equivariant.

    With `inducing_points` k > 0 the agents attend through k learned vectors instead of to each
    other: the induced set attention block of the Set Transformer (Lee et al., 2019, ISAB),
    H = MAB(I, X) = LN(A + FF(A)), A = LN(I + Attention(I, X)), then each agent attends to H.
    H is invariant to the agents' order and each agent's output depends on its own input and H,
    so the block stays equivariant, in time and memory linear in the number of agents n
    (k·n scores per head and sample instead of n²)."""

    n_embd: int
    n_head: int
    gain: float = SMALL_GAIN
    query_block: int = 0
    """`EncoderOptions.attention_block`: agents per block of the self-attention (0: all)."""
    inducing_points: int = 0
    """`EncoderOptions.inducing_points`: k learned vectors the agents attend through (0: the
    agents attend to each other)."""

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        attention = MultiHeadAttention(self.n_embd, self.n_head, self.gain)
        if self.inducing_points:
            inducing = self.param("inducing", nn.initializers.xavier_uniform(),
                                  (self.inducing_points, self.n_embd))
            queries = jnp.broadcast_to(inducing, (*x.shape[:-2], *inducing.shape))
            pooled = MultiHeadAttention(self.n_embd, self.n_head, self.gain)(queries, x)
            pooled = nn.LayerNorm()(queries + pooled)
            memory = nn.LayerNorm()(pooled + FeedForward(self.n_embd, self.gain)(pooled))
        else:
            memory = x
        x = nn.LayerNorm()(x + attention(x, memory, query_block=self.query_block))
        out: jax.Array = nn.LayerNorm()(x + FeedForward(self.n_embd, self.gain)(x))
        return out


class ObservationEncoder(nn.Module):
    """Encoder(O) -> Ô in R^{n x d} (paper eq. encoder), with no positional embedding."""

    n_embd: int
    n_head: int
    n_block: int
    gain: float = SMALL_GAIN
    query_block: int = 0
    """`EncoderOptions.attention_block`: agents per block of each self-attention (0: all)."""
    inducing_points: int = 0
    """`EncoderOptions.inducing_points`: each block's agents attend through this many learned
    vectors (`EncoderBlock`; 0: to each other, the paper's encoder)."""

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        x = nn.gelu(dense(self.n_embd)(nn.LayerNorm()(obs)))
        x = nn.LayerNorm()(x)
        for _ in range(self.n_block):
            x = EncoderBlock(self.n_embd, self.n_head, self.gain, self.query_block,
                             self.inducing_points)(x)
        return x


class Compressor(nn.Module):
    """Soft-mixture pooling of a set (paper eq. critic_compressor).

    M = softmax over the N inputs of MLP(x) in R^{N x h}; z = Mᵀx in R^{h x d};
    y = MLP(flatten z). Permutation invariant over the N inputs. Mᵀ is formed directly
    (softmax along its rows), so z = Mᵀx is a plain batched matmul with no transposed operand.
    The paper's code is built on the reference MAT's, so its convention applies: the layers
    not followed by an activation (the mixture scores and the output) start with `gain`, so the
    initial mixture is close to a uniform mean over the inputs.
    """

    n_embd: int
    heads: int
    out_features: int
    gain: float = SMALL_GAIN

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        scores = dense(self.heads, self.gain)(nn.gelu(dense(self.n_embd)(x)))
        mixture_transposed = jax.nn.softmax(jnp.swapaxes(scores, -1, -2), axis=-1)
        pooled = mixture_transposed @ x
        flat = pooled.reshape(*pooled.shape[:-2], self.heads * x.shape[-1])
        return dense(self.out_features, self.gain)(nn.gelu(dense(self.n_embd)(flat)))


class DecoderBlock(nn.Module):
    """Causal self-attention over earlier tokens, cross-attention to the encoder output, MLP.

    `step` processes one new token given the keys/values of the tokens before it, so iterating
    it is exactly a causal Transformer over the whole token sequence (a key/value cache).
    """

    n_embd: int
    n_head: int
    gain: float = SMALL_GAIN

    def setup(self) -> None:
        self.self_attention = MultiHeadAttention(self.n_embd, self.n_head, self.gain)
        self.cross_attention = MultiHeadAttention(self.n_embd, self.n_head, self.gain)
        self.feed_forward = FeedForward(self.n_embd, self.gain)
        self.norms = [nn.LayerNorm() for _ in range(3)]

    def step(
        self, token: jax.Array, cache: KeyValues, encoded: KeyValues, position: int | jax.Array
    ) -> tuple[jax.Array, KeyValues]:
        """token [..., 1, d] at `position` (static, or traced under `scan_positions`); cache:
        keys/values of the sequence (`empty_cache`) with the earlier tokens written."""
        attended, cache = self.self_attention.attend_and_write(token, token, cache, position)
        x = self.norms[0](token + attended)
        x = self.norms[1](x + self.cross_attention.attend(x, *encoded))
        x = self.norms[2](x + self.feed_forward(x))
        return x, cache

    def empty_cache(self, token: jax.Array, length: int) -> KeyValues:
        """The self-attention's cache of `length` positions for tokens like `token` [..., d]."""
        return self.self_attention.empty_cache(token, length)

    def encode_memory(self, memory: jax.Array) -> KeyValues:
        """Cross-attention keys/values of the encoder output, computed once for all steps."""
        return self.cross_attention.project_memory(memory)

    def __call__(self, tokens: jax.Array, memory: jax.Array) -> jax.Array:
        """Full causal pass over tokens [..., L, d]; equals iterating `step` (used in tests)."""
        x = self.norms[0](tokens + self.self_attention(tokens, tokens, causal=True))
        x = self.norms[1](x + self.cross_attention(x, memory))
        out: jax.Array = self.norms[2](x + self.feed_forward(x))
        return out
