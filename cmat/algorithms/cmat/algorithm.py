"""CMAT: the whole team is one multi-action agent trained with single-agent PPO.

The joint ratio is Π_i π_i(a_i | O, μ_θ(O)) / Π_i π_i,old(a_i | O, μ_θ-(O)) (paper eq. ratio):
the deterministic consensus has probability 1, so only the per-agent factors enter, and the
gradient reaches μ_θ through c. The critic is one team value V(O) from e0 (paper eq. cmat).

With a stochastic consensus (`cmat.consensus_policy` categorical or gaussian) the latent z
is sampled at acting time and stored with the transition, and the joint log-probability is
log π(A, z | O) = log π_c(z | O) + Σ_i log π_i(a_i | O, z) (eq. joint-stochastic), so its
ratio is the product of the consensus ratio and the per-agent ratios. π_c's entropy gets its
own coefficient, `cmat.consensus_ent_coef`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple, cast

import distrax
import jax
import jax.numpy as jnp

from cmat.algorithms.base import ActResult, Batch, Params, chunked
from cmat.algorithms.cmat.blocks import finetune_labels
from cmat.algorithms.cmat.network import CMATNetwork, PolicyOutput
from cmat.algorithms.cmat.options import CMATOptions
from cmat.algorithms.joint import joint_ratio_loss
from cmat.algorithms.options import options_of
from cmat.algorithms.ppo import joint_log_ratio
from cmat.algorithms.sgd import PPOAlgorithm
from cmat.config import AlgorithmOptions, NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.networks.heads import action_distribution, greedy_action


class LatentSample(NamedTuple):
    """What acting stores for a stochastic consensus: the latent and its log-probability."""

    latent: jax.Array
    """[] code (categorical) or [d] vector (gaussian)."""
    log_prob: jax.Array
    """[] log π_c(latent | O) under the collecting parameters."""


@dataclass(frozen=True)
class CMAT(PPOAlgorithm):
    network: CMATNetwork

    output_axes: ClassVar[Any] = PolicyOutput._make((0, None, 0, 0, 0, 0, 0))
    """The network output's batch axes (`chunked`): the log-std is shared by every sample."""

    @classmethod
    def build(
        cls, config: NetworkConfig, spec: EnvSpec, ppo: PPOConfig | None = None,
        options: AlgorithmOptions | None = None,
    ) -> CMAT:
        return cls(CMATNetwork(config, options_of(options, CMATOptions), spec.num_agents,
                               spec.action_dim, spec.discrete))

    def init(self, key: jax.Array, obs: jax.Array, action_mask: jax.Array) -> Params:
        return self.network.init(key, obs, action_mask)

    def act(
        self, params: Params, obs: jax.Array, action_mask: jax.Array, key: jax.Array,
        global_state: jax.Array | None = None,
    ) -> ActResult:
        """Sample the team's actions (the global state is not used: V(O) reads observations)."""
        latent: dict[str, Any] = {}
        if self.stochastic:
            latent_key, key = jax.random.split(key)
            latent = {"latent_key": latent_key}
        output = cast(PolicyOutput, self.network.apply(params, obs, action_mask, **latent))
        distribution = action_distribution(
            output.action_params, output.log_std, self.network.discrete
        )
        actions, log_probs = distribution.sample_and_log_prob(seed=key)
        if self.stochastic:
            sample = LatentSample(output.latent, output.latent_log_prob)
            return ActResult(actions, log_probs, output.value, sample)
        return ActResult(actions, log_probs, output.value)

    @property
    def stochastic(self) -> bool:
        return self.network.options.consensus_policy != "deterministic"

    def greedy(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        return greedy_action(self.action_logits(params, obs, action_mask), self.network.discrete)

    def action_logits(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        """Every agent's masked logits [n, A] on the consensus `greedy` acts on (`Factorised`):
        given it, the agents decide independently (paper eq. policy)."""
        output = cast(PolicyOutput, self.network.apply(params, obs, action_mask))
        return output.action_params

    def value(
        self, params: Params, obs: jax.Array, global_state: jax.Array | None = None
    ) -> jax.Array:
        """V(O) from the observations (paper eq. critic); the global state is not used."""
        return cast(jax.Array, self.network.apply(params, obs, method="value"))

    def log_ratio(
        self, params: Params, batch: Batch, chunks: int = 1
    ) -> tuple[jax.Array, PolicyOutput, distrax.Distribution]:
        """log π(A, z | O) − log π_old(A, z | O) per sample: Σ_i of the per-agent log-ratios
        (eq. ratio), plus log π_c(z | O) − log π_c,old(z | O) with a stochastic consensus
        (eq. joint-stochastic). Also returns the network output and the action distribution.
        The network runs over the batch in `chunks` sequential slices (`chunked`)."""
        # `()` with a deterministic consensus, read only with a stochastic one.
        sampled: LatentSample = batch.extras
        latent: dict[str, Any] = {"latent": sampled.latent} if self.stochastic else {}
        output = cast(PolicyOutput, chunked(
            lambda obs, action_mask, given: self.network.apply(params, obs, action_mask, **given),
            chunks,
            self.output_axes,
        )(batch.obs, batch.action_mask, latent))
        distribution = action_distribution(
            output.action_params, output.log_std, self.network.discrete
        )
        log_ratio = joint_log_ratio(distribution.log_prob(batch.actions), batch.log_probs)
        if self.stochastic:
            log_ratio = log_ratio + output.latent_log_prob - sampled.log_prob
        return log_ratio, output, distribution

    def finetune_labels(self, params: Params, mode: str) -> Any:
        """CMAT's fine-tuning stages (`blocks.FINETUNE_TRAINABLE`, Algorithm 1, B)."""
        return finetune_labels(params, mode)

    def loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """The joint ratio's objective (`cmat.algorithms.joint.joint_ratio_loss`) on the team
        value V(O); with a stochastic consensus, π_c's entropy gets its own bonus
        (`cmat.consensus_ent_coef`)."""
        log_ratio, output, distribution = self.log_ratio(params, batch, ppo.minibatch_chunks)
        total, metrics = joint_ratio_loss(
            log_ratio, distribution, output.value, batch, ppo, self.network.options)
        if self.stochastic:
            consensus_entropy = jnp.mean(output.latent_entropy)
            total = total - self.network.options.consensus_ent_coef * consensus_entropy
            metrics["consensus_entropy"] = consensus_entropy
        return total, metrics
