"""Feed-forward actor and centralized critic of the MAPPO and HAPPO baselines.

Both follow the reference MLP base (Yu et al. 2022; HARL): LayerNorm on the input, then `layers`
hidden layers of `hidden` units (two in on-policy's MLPBase), each dense → ReLU → LayerNorm,
orthogonal init with the ReLU gain. Arrays carry any number of leading batch axes.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from cmat.networks.heads import mask_unavailable
from cmat.networks.layers import dense


class MLPTrunk(nn.Module):
    hidden: int
    layers: int = 2
    agent_ids: int = 0
    """n > 0: the input x [..., n, d] stands for [x_i; one-hot(i)] in row i, the agent's id
    appended as MAPPO's reference does, without forming the one-hot (`first_layer_with_ids`);
    the parameters are those of the explicit [..., n, d + n] input."""

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        norm, first = nn.LayerNorm(), dense(self.hidden)
        if self.agent_ids and not self.is_initializing():
            assert norm.name is not None and first.name is not None
            params = self.variables["params"]
            x = first_layer_with_ids(x, params[norm.name], params[first.name], norm.epsilon)
        else:
            if self.agent_ids:
                ids = jnp.eye(self.agent_ids, dtype=x.dtype)
                x = jnp.concatenate([x, jnp.broadcast_to(ids, (*x.shape[:-1], ids.shape[1]))], -1)
            x = first(norm(x))
        x = nn.LayerNorm()(nn.relu(x))
        for _ in range(self.layers - 1):
            x = nn.LayerNorm()(nn.relu(dense(self.hidden)(x)))
        return x


def first_layer_with_ids(
    x: jax.Array, norm: dict[str, jax.Array], first: dict[str, jax.Array], epsilon: float
) -> jax.Array:
    """Dense(LayerNorm([x_i; one-hot(i)])) for every row i of x [..., n, d] -> [..., n, h],
    with the one-hot's share in closed form: its n entries add 1 to the sums behind the
    LayerNorm's mean and variance (Flax's E[x²] − E[x]²), and its normalised entries
    (δ_ij − μ_i) / σ_i · γ_j + β_j meet the kernel's rows K_j as γ_i K_i / σ_i − μ_i / σ_i ·
    Σ_j γ_j K_j + Σ_j β_j K_j. Per row that is O(d·h + h) instead of O((d + n)·h), so a team's
    actor pass is linear in n, where the explicit one-hot makes it quadratic. The same function
    as the explicit input up to float rounding (tests/test_baselines_mlp.py)."""
    n, d = x.shape[-2], x.shape[-1]
    scale, bias, kernel = norm["scale"], norm["bias"], first["kernel"]
    mean = (jnp.sum(x, axis=-1) + 1.0) / (d + n)
    variance = jnp.maximum((jnp.sum(jnp.square(x), axis=-1) + 1.0) / (d + n) - mean**2, 0.0)
    inverse = jax.lax.rsqrt(variance + epsilon)[..., None]
    mean = mean[..., None]
    observed = ((x - mean) * inverse * scale[:d] + bias[:d]) @ kernel[:d]
    id_rows = scale[d:, None] * kernel[d:]
    ids = inverse * id_rows - mean * inverse * jnp.sum(id_rows, axis=0) + bias[d:] @ kernel[d:]
    return observed + ids + first["bias"]


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
    agent_ids: int = 0
    """`MLPTrunk.agent_ids`: n to act from [o_i; one-hot(i)] for the rows i of x [..., n, d]."""

    @nn.compact
    def __call__(self, x: jax.Array, action_mask: jax.Array) -> tuple[jax.Array, jax.Array]:
        hidden = MLPTrunk(self.hidden, self.layers, self.agent_ids)(x)
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
