"""The Consensus Multi-Agent Transformer network (paper Sec. Network Architecture, Fig. 2).

O --Encoder--> Ô --Critic-Compressor--> e0 --Critic-MLP--> V(O)
e0 --Decoder, m iterations--> e1..em;  E = {e0..em} --Actor-Compressor--> c
Actor-MLP([ô_i; c]) --> per-agent action distribution, weights shared across agents.

Order independence holds by construction: the encoder has no positional embedding (equivariant),
both compressors pool sets (invariant), so V and c are invariant and agent i's distribution
depends only on ô_i and c. The decoder keeps a learned positional embedding over iterations
(the paper keeps it "to be aware of the convergence process").

With a stochastic consensus policy (`NetworkConfig.consensus_policy`, the paper's future-work
variant, Appendix "A More General Framework"), a latent drawn from π_c(· | O) around μ(O)
conditions the Actor-MLP in place of c, so the joint policy is a mixture of products
(eq. joint-stochastic). π_c reads only the invariant c, so order independence still holds.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp

from cmat.algorithms.cmat.options import CMATOptions
from cmat.config import NetworkConfig
from cmat.networks.heads import ActionHead, ValueHead, mask_unavailable
from cmat.networks.layers import (
    SMALL_GAIN,
    Compressor,
    DecoderBlock,
    KeyValues,
    ObservationEncoder,
    dense,
    scan_positions,
)


class PolicyOutput(NamedTuple):
    """Per-agent action-distribution parameters and the team value."""

    action_params: jax.Array
    """[..., n, A]: masked logits (discrete) or Gaussian means (continuous)."""
    log_std: jax.Array
    """[A] learned state-independent log-std (continuous); zeros for discrete heads."""
    value: jax.Array
    """[...] team value V(O), in the value normaliser's space."""
    consensus: jax.Array
    """[..., d] the deterministic consensus μ(O)."""
    latent: Any = None
    """[...] code (categorical) or [..., d] vector (gaussian) the actors were conditioned on;
    None for the deterministic consensus."""
    latent_log_prob: Any = None
    """[...] log π_c(latent | O); None for the deterministic consensus."""
    latent_entropy: Any = None
    """[...] entropy of π_c(· | O); None for the deterministic consensus."""


class LatentConsensus(nn.Module):
    """π_c(z | O) around the deterministic consensus μ(O) (paper eq. joint-stochastic).

    categorical: logits over K codes from a linear layer on μ(O); the actors see
    μ(O) + embedding(z), whose table is initialised N(0, 1) so that codes start out as distinct
    products. gaussian: z ~ N(μ(O), diag σ²) with a learned state-independent log σ (initial
    σ = 1), sampled as μ + σ·ε; the actors see z. The mode (most likely code, or μ) is the greedy
    choice.
    """

    policy: str
    codes: int
    n_embd: int
    init_gain: float

    def setup(self) -> None:
        if self.policy == "categorical":
            self.code_logits = dense(self.codes, self.init_gain)
            self.code_embedding = self.param(
                "code_embedding", nn.initializers.normal(1.0), (self.codes, self.n_embd)
            )
        else:
            self.log_scale = self.param("log_scale", nn.initializers.zeros, (self.n_embd,))

    def distribution(self, consensus: jax.Array) -> distrax.Distribution:
        if self.policy == "categorical":
            return distrax.Categorical(logits=self.code_logits(consensus))
        return distrax.MultivariateNormalDiag(consensus, jnp.exp(self.log_scale))

    def conditioning(self, consensus: jax.Array, latent: jax.Array) -> jax.Array:
        """What the Actor-MLP sees in place of c, given the latent."""
        if self.policy == "categorical":
            return consensus + self.code_embedding[latent]
        return latent


class ConsensusDecoder(nn.Module):
    """Iterates the consensus: e_k = Decoder([e0..e(k-1)] + pos, Ô) at the last position.

    Causal attention makes earlier positions independent of later ones, so a key/value cache is
    exact, and gradients flow through all m iterations (the consensus is deterministic, paper
    eq. ratio). Up to `SCAN_LENGTH` iterations they are unrolled, above it one iteration is
    compiled once and scanned m times (`scan_positions`; the parameters are the same either
    way), which gives the same numbers up to float rounding (tests/test_network.py).
    """

    n_embd: int
    n_head: int
    n_block: int
    iterations: int
    gain: float = SMALL_GAIN
    scan: bool | None = None
    """Run the iterations as a scan (True) or unrolled (False); None: scan above
    `SCAN_LENGTH`."""

    def setup(self) -> None:
        self.blocks = [DecoderBlock(self.n_embd, self.n_head, self.gain, name=f"DecoderBlock_{i}")
                       for i in range(self.n_block)]
        if self.iterations > 0:
            self.positions = self.param(
                "positions", nn.initializers.normal(0.02), (self.iterations, self.n_embd))

    def __call__(self, e0: jax.Array, encoded: jax.Array) -> jax.Array:
        """e0 [..., d], encoded [..., n, d] -> E = [e0..em] as [..., m+1, d]."""
        if self.iterations == 0:
            return e0[..., None, :]
        memories = [block.encode_memory(encoded) for block in self.blocks]
        caches = [block.empty_cache(e0, self.iterations) for block in self.blocks]

        def iteration(
            module: ConsensusDecoder, carry: tuple[jax.Array, list[KeyValues]],
            position: tuple[int | jax.Array, None],
        ) -> tuple[tuple[jax.Array, list[KeyValues]], jax.Array]:
            previous, caches = carry
            k = position[0]
            x = (previous + module.positions[k])[..., None, :]
            written = []
            for layer, block in enumerate(module.blocks):
                x, cache = block.step(x, caches[layer], memories[layer], k)
                written.append(cache)
            return (x[..., 0, :], written), x[..., 0, :]

        _, sequence = scan_positions(self, iteration, (e0, caches), None, self.iterations,
                                     self.scan)
        return jnp.concatenate([e0[..., None, :], jnp.moveaxis(sequence, 0, -2)], axis=-2)


class CMATNetwork(nn.Module):
    """CMAT actor-critic over one team: obs [..., n, obs_dim] -> PolicyOutput."""

    config: NetworkConfig
    options: CMATOptions
    num_agents: int
    action_dim: int
    discrete: bool

    @property
    def iterations(self) -> int:
        """m (paper eq. decoder); defaults to the number of agents ('n', 'n/2', '2n' allowed)."""
        return self.options.iterations(self.num_agents)

    def setup(self) -> None:
        cfg, own = self.config, self.options
        gain = cfg.init_gain
        self.encoder = ObservationEncoder(cfg.n_embd, cfg.n_head, cfg.n_block, gain,
                                          own.attention_block, own.inducing_points)
        self.critic_compressor = Compressor(cfg.n_embd, own.compressor_heads, cfg.n_embd, gain)
        self.critic_mlp = ValueHead(cfg.n_embd, gain)
        self.decoder = ConsensusDecoder(
            cfg.n_embd, cfg.n_head, cfg.n_block, self.iterations, gain
        )
        self.actor_compressor = Compressor(cfg.n_embd, own.compressor_heads, cfg.n_embd, gain)
        stochastic = own.consensus_policy != "deterministic"
        actor_gain = own.latent_head_gain if stochastic else gain
        self.actor_mlp = ActionHead(
            cfg.n_embd, self.action_dim, self.discrete, actor_gain, cfg.log_std_init
        )
        if stochastic:
            self.latent_consensus = LatentConsensus(
                own.consensus_policy, own.consensus_codes, cfg.n_embd, own.latent_head_gain
            )

    def value(self, obs: jax.Array) -> jax.Array:
        """V(O) alone (encoder, Critic-Compressor, Critic-MLP): what the target critic needs."""
        return self.critic_mlp(self.critic_compressor(self.encoder(obs)))

    def __call__(
        self,
        obs: jax.Array,
        action_mask: jax.Array,
        latent: jax.Array | None = None,
        latent_key: jax.Array | None = None,
    ) -> PolicyOutput:
        """The policy and value; with a stochastic consensus the actors are conditioned on
        `latent` if given, else on one sampled with `latent_key`, else on π_c's mode."""
        encoded = self.encoder(obs)
        e0 = self.critic_compressor(encoded)
        consensus_vectors = self.decoder(e0, encoded)
        if self.options.consensus_source == "last":
            consensus = consensus_vectors[..., -1, :]
        else:
            consensus = self.actor_compressor(consensus_vectors)
        conditioning, latent_log_prob, latent_entropy = consensus, None, None
        if self.options.consensus_policy != "deterministic":
            distribution = self.latent_consensus.distribution(consensus)
            if latent is None:
                latent = (
                    distribution.mode() if latent_key is None
                    else distribution.sample(seed=latent_key)
                )
            conditioning = self.latent_consensus.conditioning(consensus, latent)
            latent_log_prob, latent_entropy = distribution.log_prob(latent), distribution.entropy()
        action_params, log_std = self.actor_mlp(encoded, conditioning)
        action_params = mask_unavailable(action_params, action_mask, self.discrete)
        return PolicyOutput(
            action_params, log_std, self.critic_mlp(e0), consensus,
            latent, latent_log_prob, latent_entropy,
        )

