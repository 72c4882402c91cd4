"""Triple-BERT (Zhao et al. 2025) as the paper's baseline: the team as one multi-action agent whose
per-agent factors see no consensus.

The joint policy is Π_i π_i(a_i | ô_i), trained exactly as CMAT: single-agent PPO on the joint
ratio Π_i π_i / π_i,old (paper eq. ratio) with a team value. Acting and the loss are CMAT's;
only the network differs (`cmat.algorithms.triple_bert.network`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from cmat.algorithms.cmat.algorithm import CMAT
from cmat.algorithms.options import options_of
from cmat.algorithms.sgd import PPOAlgorithm
from cmat.algorithms.triple_bert.network import TripleBERTNetwork, TripleBERTOutput
from cmat.algorithms.triple_bert.options import TripleBERTOptions
from cmat.config import AlgorithmOptions, NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec


@dataclass(frozen=True)
class TripleBERT(CMAT):
    network: TripleBERTNetwork  # type: ignore[assignment]

    output_axes: ClassVar[Any] = TripleBERTOutput._make((0, None, 0))
    finetune_labels = PPOAlgorithm.finetune_labels

    @classmethod
    def build(
        cls, config: NetworkConfig, spec: EnvSpec, ppo: PPOConfig | None = None,
        options: AlgorithmOptions | None = None,
    ) -> TripleBERT:
        return cls(TripleBERTNetwork(config, options_of(options, TripleBERTOptions),
                                     spec.num_agents, spec.action_dim, spec.discrete))

    @property
    def stochastic(self) -> bool:
        """Never: Triple-BERT has no consensus."""
        return False
