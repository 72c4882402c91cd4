"""Triple-BERT (Zhao et al. 2025) as the paper's baseline: the team as one multi-action agent whose
per-agent factors see no consensus.

The joint policy is Π_i π_i(a_i | ô_i), trained exactly as CMAT: single-agent PPO on the joint
ratio Π_i π_i / π_i,old (paper eq. ratio) with a team value, through the objective both share
(`cmat.algorithms.joint`); only the network differs (`cmat.algorithms.triple_bert.network`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, cast

import distrax
import jax

from cmat.algorithms.base import ActResult, Batch, Params, chunked
from cmat.algorithms.joint import joint_ratio_loss
from cmat.algorithms.options import options_of
from cmat.algorithms.ppo import joint_log_ratio
from cmat.algorithms.sgd import PPOAlgorithm
from cmat.algorithms.triple_bert.network import TripleBERTNetwork, TripleBERTOutput
from cmat.algorithms.triple_bert.options import TripleBERTOptions
from cmat.config import AlgorithmOptions, NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.networks.heads import action_distribution, greedy_action


@dataclass(frozen=True)
class TripleBERT(PPOAlgorithm):
    network: TripleBERTNetwork

    output_axes: ClassVar[Any] = TripleBERTOutput._make((0, None, 0))
    """The network output's batch axes (`chunked`): the log-std is shared by every sample."""

    @classmethod
    def build(
        cls, config: NetworkConfig, spec: EnvSpec, ppo: PPOConfig | None = None,
        options: AlgorithmOptions | None = None,
    ) -> TripleBERT:
        return cls(TripleBERTNetwork(config, options_of(options, TripleBERTOptions),
                                     spec.num_agents, spec.action_dim, spec.discrete))

    def init(self, key: jax.Array, obs: jax.Array, action_mask: jax.Array) -> Params:
        return self.network.init(key, obs, action_mask)

    def distribution(self, output: TripleBERTOutput) -> distrax.Distribution:
        return action_distribution(output.action_params, output.log_std, self.network.discrete)

    def act(
        self, params: Params, obs: jax.Array, action_mask: jax.Array, key: jax.Array,
        global_state: jax.Array | None = None,
    ) -> ActResult:
        """Sample the team's actions (the global state is not used: V(O) reads observations)."""
        output = cast(TripleBERTOutput, self.network.apply(params, obs, action_mask))
        actions, log_probs = self.distribution(output).sample_and_log_prob(seed=key)
        return ActResult(actions, log_probs, output.value)

    def greedy(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        return greedy_action(self.action_logits(params, obs, action_mask), self.network.discrete)

    def action_logits(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        """Every agent's masked logits [n, A] (`Factorised`)."""
        output = cast(TripleBERTOutput, self.network.apply(params, obs, action_mask))
        return output.action_params

    def value(
        self, params: Params, obs: jax.Array, global_state: jax.Array | None = None
    ) -> jax.Array:
        """V(O) from the observations; the global state is not used."""
        return cast(jax.Array, self.network.apply(params, obs, method="value"))

    def loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """The joint ratio's objective (`cmat.algorithms.joint.joint_ratio_loss`) on the team
        value V(O); the network runs over the batch in `ppo.minibatch_chunks` slices."""
        output = cast(TripleBERTOutput, chunked(
            lambda obs, action_mask: self.network.apply(params, obs, action_mask),
            ppo.minibatch_chunks,
            self.output_axes,
        )(batch.obs, batch.action_mask))
        distribution = self.distribution(output)
        log_ratio = joint_log_ratio(distribution.log_prob(batch.actions), batch.log_probs)
        return joint_ratio_loss(log_ratio, distribution, output.value, batch, ppo,
                                self.network.options)
