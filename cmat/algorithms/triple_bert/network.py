"""The Triple-BERT network as the paper uses it as a baseline (Sec. Multi-Agent Transformer and Its
Variants): CMAT without the consensus.

O --Encoder--> Ô --Compressor--> e --MLP--> V(O);  Actor-MLP(ô_i) --> agent i's distribution.

The encoder has no positional embedding and the compressor pools a set, so permuting the agents
permutes their distributions and leaves V unchanged; each agent acts from its own ô_i alone.
"""

from __future__ import annotations

from typing import NamedTuple

import flax.linen as nn
import jax

from cmat.algorithms.triple_bert.options import TripleBERTOptions
from cmat.config import NetworkConfig
from cmat.networks.heads import ActionHead, ValueHead, mask_unavailable
from cmat.networks.layers import Compressor, ObservationEncoder


class TripleBERTOutput(NamedTuple):
    action_params: jax.Array
    """[..., n, A]: masked logits (discrete) or Gaussian means (continuous)."""
    log_std: jax.Array
    """[A] learned state-independent log-std (continuous); zeros for discrete heads."""
    value: jax.Array
    """[...] team value V(O), in the value normaliser's space."""


class TripleBERTNetwork(nn.Module):
    """Triple-BERT actor-critic over one team: obs [..., n, obs_dim] -> TripleBERTOutput."""

    config: NetworkConfig
    options: TripleBERTOptions
    num_agents: int
    action_dim: int
    discrete: bool

    def setup(self) -> None:
        cfg, own = self.config, self.options
        gain = cfg.init_gain
        self.encoder = ObservationEncoder(cfg.n_embd, cfg.n_head, cfg.n_block, gain,
                                          own.attention_block, own.inducing_points)
        self.critic_compressor = Compressor(cfg.n_embd, own.compressor_heads, cfg.n_embd, gain)
        self.critic_mlp = ValueHead(cfg.n_embd, gain)
        self.actor_mlp = ActionHead(
            cfg.n_embd, self.action_dim, self.discrete, gain, cfg.log_std_init
        )

    def value(self, obs: jax.Array) -> jax.Array:
        return self.critic_mlp(self.critic_compressor(self.encoder(obs)))

    def __call__(self, obs: jax.Array, action_mask: jax.Array) -> TripleBERTOutput:
        encoded = self.encoder(obs)
        action_params, log_std = self.actor_mlp(encoded)
        action_params = mask_unavailable(action_params, action_mask, self.discrete)
        return TripleBERTOutput(
            action_params, log_std, self.critic_mlp(self.critic_compressor(encoded))
        )
