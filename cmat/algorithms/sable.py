"""Sable (Mahjoub et al., ICML 2025): MAT's autoregressive PPO on a retention network.

Acting, values and the per-agent clipped objective are MAT's (cmat.algorithms.mat), on
`cmat.networks.sable.SableNetwork`. What the reference (instadeepai/Mava,
mava/systems/sable/anakin/ff_sable.py) does differently, and cmat does with it:

- Every epoch permutes the agents of the whole batch with one random permutation, so the
  decoder is trained along a new agent order each epoch while acting keeps the index order; the
  stored log-probs stay those of acting (`shuffle_agents`, `permute_agents`).
- Advantages are normalised per minibatch over all agents, not per update
  (`ppo.normalize_advantages` is off and the loss normalises).
- Per-agent values and GAE with the team reward, squared-error value loss (½·MSE, clipped with
  `clip_eps`, weight 0.5), no value normalisation, no active masks, lr 2.5e-4, 4 epochs of
  2 minibatches, clip 0.2, gradient norm 0.5 (mava/configs/system/sable/ff_sable.yaml); one block
  of width 64 with one head (mava/configs/network/ff_retention.yaml).

Rollout length and number of environments stay the suite's (SMAX: 100 steps × 32 envs) so that
Sable and the other methods collect the same batches; the reference's 128 steps × 16 envs × 2
vectorised updates per device is the same 4,096-sample batch split into two gradient steps.
Continuous actions use cmat's Gaussian head (MAT's), not the reference's tanh-squashed Normal.

This module is the feed-forward variant (`ff_sable`): no memory across timesteps.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import jax
import optax

from cmat.algorithms.base import Batch, Params
from cmat.algorithms.mat import MAT
from cmat.algorithms.ppo import normalize
from cmat.algorithms.sgd import Metrics, minibatch_sgd
from cmat.config import NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.networks.sable import SableNetwork


def permute_agents(batch: Batch, key: jax.Array) -> Batch:
    """`batch` with its agents [B, n, ...] in one random order (the same for every sample):
    observations, masks, actions, log-probs, activity, stored extras and the per-agent values,
    advantages and targets; team quantities [B] and the global state as they are."""
    num_agents = batch.obs.shape[1]
    order = jax.random.permutation(key, num_agents)

    def per_agent(x: jax.Array) -> jax.Array:
        return x[:, order] if x.ndim >= 2 else x

    return batch._replace(
        obs=batch.obs[:, order],
        action_mask=batch.action_mask[:, order],
        actions=batch.actions[:, order],
        log_probs=batch.log_probs[:, order],
        values=per_agent(batch.values),
        advantages=per_agent(batch.advantages),
        targets=per_agent(batch.targets),
        extras=jax.tree.map(per_agent, batch.extras),
        alive=None if batch.alive is None else batch.alive[:, order],
    )


@dataclass(frozen=True)
class Sable(MAT):
    network: SableNetwork
    shuffle_agents: bool = True
    """Permute the agents anew every epoch (the reference's `agent_perm`)."""

    name: ClassVar[str] = "sable"
    capabilities: ClassVar[frozenset[str]] = frozenset({"per_agent_values"})
    network_fields: ClassVar[tuple[str, ...]] = ("n_embd", "n_head", "n_block", "log_std_init")
    """The retention encoder-decoder's sizes (SableNetwork)."""

    presets: ClassVar[dict[str, dict[str, Any]]] = {}

    reference_defaults: ClassVar[dict[str, Any]] = {
        "ppo": {
            "lr": 2.5e-4, "epochs": 4, "num_minibatches": 2, "clip_eps": 0.2, "ent_coef": 0.01,
            "value_coef": 0.5, "max_grad_norm": 0.5, "target_tau": 1.0, "active_masks": False,
            "per_agent_gae": True, "value_norm": False, "huber_loss": False,
            "clipped_value_loss": True, "normalize_advantages": False,
        },
    }
    """Mava's ff_sable system and network configs (module docstring)."""

    @classmethod
    def build(
        cls, config: NetworkConfig, spec: EnvSpec, ppo: PPOConfig | None = None
    ) -> Sable:
        ppo = ppo if ppo is not None else PPOConfig()
        network = SableNetwork(config, spec.num_agents, spec.action_dim, spec.discrete)
        return cls(network, ppo.per_agent_gae)

    def loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """MAT's loss on the minibatch's advantages normalised over all its entries (the
        reference normalises per minibatch)."""
        return super().loss(params, batch._replace(advantages=normalize(batch.advantages)), ppo)

    def update(
        self, optimizer: optax.GradientTransformation, params: Params, opt_state: Any,
        batch: Batch, rng: jax.Array, ppo: PPOConfig,
    ) -> tuple[Params, Any, Metrics]:
        """PPO's epochs × minibatches, the agents permuted anew each epoch."""
        return minibatch_sgd(
            self.loss, optimizer, params, opt_state, batch, rng, ppo,
            permute_agents if self.shuffle_agents else None,
        )
