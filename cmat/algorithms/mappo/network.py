"""Feed-forward actor and centralized critic of the MAPPO and HAPPO baselines.

Both follow the reference MLP base (Yu et al. 2022; HARL): LayerNorm on the input, then `layers`
hidden layers of `hidden` units (two in on-policy's MLPBase), each dense → ReLU → LayerNorm,
orthogonal init with the ReLU gain. Arrays carry any number of leading batch axes.
"""

from __future__ import annotations

import flax.linen as nn
import jax

from cmat.networks.heads import mask_unavailable
from cmat.networks.layers import dense


class MLPTrunk(nn.Module):
    hidden: int
    layers: int = 2

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        x = nn.LayerNorm()(x)
        for _ in range(self.layers):
            x = nn.LayerNorm()(nn.relu(dense(self.hidden)(x)))
        return x


class MLPActor(nn.Module):
    """One agent's policy from its input vector [..., in] -> (action params [..., A], log_std)."""

    hidden: int
    action_dim: int
    discrete: bool
    init_gain: float
    log_std_init: float = 1.0
    """Initial log-std of continuous actions (std = sigmoid(log_std) · 0.5, as every cmat
    policy; the reference MAPPO's DiagGaussian uses std = exp(log_std), docs/algorithms.md)."""
    layers: int = 2

    @nn.compact
    def __call__(self, x: jax.Array, action_mask: jax.Array) -> tuple[jax.Array, jax.Array]:
        hidden = MLPTrunk(self.hidden, self.layers)(x)
        action_params = dense(self.action_dim, self.init_gain)(hidden)
        log_std = self.param(
            "log_std", nn.initializers.constant(self.log_std_init),
            (0 if self.discrete else self.action_dim,),
        )
        return mask_unavailable(action_params, action_mask, self.discrete), log_std


class MLPCritic(nn.Module):
    """V(s) of the team from a global state vector s (the reference R_Critic: output layer
    gain 1)."""

    hidden: int
    layers: int = 2

    @nn.compact
    def __call__(self, state: jax.Array) -> jax.Array:
        """state [..., s] -> [...]"""
        return dense(1, 1.0)(MLPTrunk(self.hidden, self.layers)(state))[..., 0]
