"""The Consensus Multi-Agent Transformer network (paper Sec. Network Architecture, Fig. 2).

O --Encoder--> Ô --Critic-Compressor--> e0 --Critic-MLP--> V(O)
e0 --Decoder, m iterations--> e1..em;  E = {e0..em} --Actor-Compressor--> c
Actor-MLP([ô_i; c]) --> per-agent action distribution, weights shared across agents.

Order independence holds by construction: the encoder has no positional embedding (equivariant),
both compressors pool sets (invariant), so V and c are invariant and agent i's distribution
depends only on ô_i and c. The decoder keeps a learned positional embedding over iterations
(the paper keeps it "to be aware of the convergence process").
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import flax.linen as nn

from cmat.config import NetworkConfig, resolve_iterations
from cmat.networks.layers import Compressor, DecoderBlock, ObservationEncoder, dense


class PolicyOutput(NamedTuple):
    """Per-agent action-distribution parameters and the team value."""

    action_params: jax.Array
    """[..., n, A]: masked logits (discrete) or Gaussian means (continuous)."""
    log_std: jax.Array
    """[A] learned state-independent log-std (continuous); zeros for discrete heads."""
    value: jax.Array
    """[...] team value V(O), in the value normaliser's space."""
    consensus: jax.Array
    """[..., d] the final consensus c."""


class ActionHead(nn.Module):
    """Actor-MLP([ô_i; c]) (paper eq. actor_MLP), shared across agents."""

    n_embd: int
    action_dim: int
    discrete: bool
    init_gain: float

    @nn.compact
    def __call__(self, features: jax.Array) -> tuple[jax.Array, jax.Array]:
        hidden = nn.LayerNorm()(nn.gelu(dense(self.n_embd)(features)))
        params = dense(self.action_dim, self.init_gain)(hidden)
        log_std = self.param(
            "log_std", nn.initializers.zeros, (0 if self.discrete else self.action_dim,)
        )
        return params, log_std


class ValueHead(nn.Module):
    """Critic-MLP(e0) -> V(O) (paper eq. critic)."""

    n_embd: int

    @nn.compact
    def __call__(self, e0: jax.Array) -> jax.Array:
        return dense(1, 1.0)(nn.gelu(dense(self.n_embd)(e0)))[..., 0]


class ConsensusDecoder(nn.Module):
    """Iterates the consensus: e_k = Decoder([e0..e(k-1)] + pos, Ô) at the last position.

    Causal attention makes earlier positions independent of later ones, so a key/value cache is
    exact; the m iterations are unrolled (m is static and small), and gradients flow through all
    of them (the consensus is deterministic, paper eq. ratio).
    """

    n_embd: int
    n_head: int
    n_block: int
    iterations: int

    @nn.compact
    def __call__(self, e0: jax.Array, encoded: jax.Array) -> jax.Array:
        """e0 [..., d], encoded [..., n, d] -> E = [e0..em] as [..., m+1, d]."""
        if self.iterations == 0:
            return e0[..., None, :]
        blocks = [DecoderBlock(self.n_embd, self.n_head) for _ in range(self.n_block)]
        positions = self.param(
            "positions", nn.initializers.normal(0.02), (self.iterations, self.n_embd)
        )
        memories = [block.encode_memory(encoded) for block in blocks]
        caches: list[tuple[jax.Array, jax.Array] | None] = [None] * self.n_block
        sequence = [e0]
        for k in range(self.iterations):
            x = (sequence[-1] + positions[k])[..., None, :]
            for layer, block in enumerate(blocks):
                x, caches[layer] = block.step(x, caches[layer], memories[layer])
            sequence.append(x[..., 0, :])
        return jnp.stack(sequence, axis=-2)


class CMATNetwork(nn.Module):
    """CMAT actor-critic over one team: obs [..., n, obs_dim] -> PolicyOutput."""

    config: NetworkConfig
    num_agents: int
    action_dim: int
    discrete: bool

    @property
    def iterations(self) -> int:
        """m (paper eq. decoder); defaults to the number of agents ('n', 'n/2', '2n' allowed)."""
        return resolve_iterations(self.config.consensus_iterations, self.num_agents)

    def setup(self) -> None:
        cfg = self.config
        self.encoder = ObservationEncoder(cfg.n_embd, cfg.n_head, cfg.n_block)
        self.critic_compressor = Compressor(cfg.n_embd, cfg.compressor_heads, cfg.n_embd)
        self.critic_mlp = ValueHead(cfg.n_embd)
        self.decoder = ConsensusDecoder(cfg.n_embd, cfg.n_head, cfg.n_block, self.iterations)
        self.actor_compressor = Compressor(cfg.n_embd, cfg.compressor_heads, cfg.n_embd)
        self.actor_mlp = ActionHead(cfg.n_embd, self.action_dim, self.discrete, cfg.init_gain)

    def value(self, obs: jax.Array) -> jax.Array:
        """V(O) alone (encoder, Critic-Compressor, Critic-MLP): what the target critic needs."""
        return self.critic_mlp(self.critic_compressor(self.encoder(obs)))

    def __call__(self, obs: jax.Array, action_mask: jax.Array) -> PolicyOutput:
        encoded = self.encoder(obs)
        e0 = self.critic_compressor(encoded)
        consensus_vectors = self.decoder(e0, encoded)
        if self.config.consensus_source == "last":
            consensus = consensus_vectors[..., -1, :]
        else:
            consensus = self.actor_compressor(consensus_vectors)
        shared = jnp.broadcast_to(consensus[..., None, :], encoded.shape)
        action_params, log_std = self.actor_mlp(jnp.concatenate([encoded, shared], axis=-1))
        if self.discrete:
            action_params = jnp.where(action_mask, action_params, MASKED_LOGIT)
        return PolicyOutput(action_params, log_std, self.critic_mlp(e0), consensus)


MASKED_LOGIT = -1e9
"""Logit of an unavailable action: exp underflows to exactly 0 probability in float32."""
