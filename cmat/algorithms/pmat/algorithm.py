"""PMAT (Hu et al. 2025): MAT whose decision order is sampled from a learned Plackett-Luce model.

A scoring block on Ô gives each agent a weight w_i in (1, 10) (`OrderScorer`); the order σ is
drawn without replacement, P(σ) = Π_k w_σ(k) / Σ_{j≥k} w_σ(j), and MAT's decoder acts along it.
The order is stored with the transition; log P(σ) gets its own clipped PPO term with the team
advantage (with per-agent GAE: the mean advantage over every agent, as the reference's
`mat_trainer.py`), weighted by `pmat.order_loss_coef`, added to MAT's loss (eq. mat). The loss
decodes the stored actions along `pmat.order_in_loss`: the sampled order, or the agents' index
order as the reference's training pass does. Values, GAE and active masks are MAT's.

Reference: NUDT-BI-MARL/PMAT (8894f9e), `mat/algorithms/mat/algorithm/pma_transformer.py`,
`mat/algorithms/mat/mat_trainer.py`, `mat/scripts/train_smac.sh`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple, cast

import jax
import jax.numpy as jnp

from cmat.algorithms.base import ActResult, Batch, Params
from cmat.algorithms.mat.algorithm import MAT
from cmat.algorithms.mat.network import OrderScorer
from cmat.algorithms.options import options_of
from cmat.algorithms.pmat.options import PMATOptions
from cmat.algorithms.ppo import clipped_surrogate_loss
from cmat.algorithms.sgd import PPOAlgorithm
from cmat.config import AlgorithmOptions, NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec


class OrderSample(NamedTuple):
    """What acting stores for the loss: the decision order, its log-probability and MAT's
    per-agent values."""

    order: jax.Array
    """[n] agent acting at each decoding position."""
    log_prob: jax.Array
    """[] log P(order) under the collecting parameters."""
    agent_values: jax.Array
    """[n] V(ô_i) under the collecting parameters."""


def order_log_prob(scores: jax.Array, order: jax.Array) -> jax.Array:
    """log P(σ) = Σ_k [s_σ(k) − logsumexp(s_σ(k..n))] over the last axis, for log-weights s."""
    ordered = jnp.take_along_axis(scores, order, axis=-1)
    remaining = jax.lax.cumlogsumexp(ordered, axis=ordered.ndim - 1, reverse=True)
    return jnp.sum(ordered - remaining, axis=-1)


def sample_order(scores: jax.Array, key: jax.Array) -> jax.Array:
    """A Plackett-Luce order for log-weights s, exactly, by Gumbel-top-k: sort s_i + Gumbel
    noise, descending."""
    return jnp.argsort(-(scores + jax.random.gumbel(key, scores.shape)), axis=-1)


@dataclass(frozen=True)
class PMAT(PPOAlgorithm):
    mat: MAT
    scorer: OrderScorer
    options: PMATOptions = field(default_factory=PMATOptions)

    @classmethod
    def build(
        cls, config: NetworkConfig, spec: EnvSpec, ppo: PPOConfig | None = None,
        options: AlgorithmOptions | None = None,
    ) -> PMAT:
        own = options_of(options, PMATOptions)
        return cls(MAT.build(config, spec, ppo, own), OrderScorer(config.init_gain), own)

    def init(self, key: jax.Array, obs: jax.Array, action_mask: jax.Array) -> Params:
        mat_key, scorer_key = jax.random.split(key)
        mat = self.mat.init(mat_key, obs, action_mask)
        encoded, _ = self.mat.encode(mat, obs)
        return {"mat": mat, "scorer": self.scorer.init(scorer_key, encoded)}

    def scores(self, params: Params, obs: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Ô, the per-agent values and the agents' order scores."""
        encoded, agent_values = self.mat.encode(params["mat"], obs)
        scores = cast(jax.Array, self.scorer.apply(params["scorer"], encoded))
        return encoded, agent_values, scores

    def act(
        self, params: Params, obs: jax.Array, action_mask: jax.Array, key: jax.Array,
        global_state: jax.Array | None = None,
    ) -> ActResult:
        order_key, action_key = jax.random.split(key)
        encoded, agent_values, scores = self.scores(params, obs)
        order = sample_order(scores, order_key)
        actions, log_probs = self.mat.decode(params["mat"], encoded, action_mask, order, action_key)
        sampled = OrderSample(order, order_log_prob(scores, order), agent_values)
        value = agent_values if self.mat.per_agent_gae else jnp.mean(agent_values)
        return ActResult(actions, log_probs, value, sampled)

    def greedy(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        """Agents in descending score order, each taking its most likely action."""
        encoded, _, scores = self.scores(params, obs)
        order = jnp.argsort(-scores)
        return self.mat.decode(params["mat"], encoded, action_mask, order, None)[0]

    def value(
        self, params: Params, obs: jax.Array, global_state: jax.Array | None = None
    ) -> jax.Array:
        return self.mat.value(params["mat"], obs)

    def loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """MAT's loss along `pmat.order_in_loss` plus the clipped order term."""
        sampled: OrderSample = batch.extras
        orders = (
            sampled.order if self.options.order_in_loss == "sampled"
            else jnp.broadcast_to(self.mat.identity, sampled.order.shape)
        )
        total, metrics, output = self.mat.loss_along(
            params["mat"], batch, orders, sampled.agent_values, ppo
        )
        scores = cast(jax.Array, self.scorer.apply(params["scorer"], output.encoded))
        advantages = batch.advantages
        if advantages.ndim == 2:
            advantages = jnp.mean(advantages, axis=1)
        order_loss, diagnostics = clipped_surrogate_loss(
            order_log_prob(scores, sampled.order) - sampled.log_prob, advantages, ppo.clip_eps
        )
        return total + self.options.order_loss_coef * order_loss, {
            **metrics,
            "order_loss": order_loss,
            "order_approx_kl": diagnostics["approx_kl"],
            "order_clip_frac": diagnostics["clip_frac"],
        }
