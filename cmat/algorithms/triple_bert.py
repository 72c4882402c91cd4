"""Triple-BERT (Zhao et al. 2025) as the paper's baseline: the team as one multi-action agent whose
per-agent factors see no consensus.

The joint policy is Π_i π_i(a_i | ô_i), trained exactly as CMAT: single-agent PPO on the joint
ratio Π_i π_i / π_i,old (paper eq. ratio) with a team value. Acting and the loss are CMAT's;
only the network differs (cmat.networks.triple_bert).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from cmat.algorithms.cmat import CMAT
from cmat.algorithms.sgd import PPOAlgorithm
from cmat.config import NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.networks.triple_bert import TripleBERTNetwork, TripleBERTOutput


@dataclass(frozen=True)
class TripleBERT(CMAT):
    network: TripleBERTNetwork  # type: ignore[assignment]

    name: ClassVar[str] = "triple_bert"
    reference_defaults: ClassVar[dict[str, Any]] = {}
    """The paper's baseline setting: the reference MAT's (the dataclass defaults), trained as
    the paper trains CMAT (joint ratio clipped to [1 − ε, 1 + ε], target critic τ = 0.1)."""
    finetune_stages: ClassVar[tuple[str, ...]] = ()
    capabilities: ClassVar[frozenset[str]] = frozenset({"joint_ratio", "minibatch_chunks"})
    network_fields: ClassVar[tuple[str, ...]] = (
        "n_embd", "n_head", "n_block", "compressor_heads", "init_gain", "log_std_init",
        "attention_block")
    """CMAT's sizes without its decoder and consensus (TripleBERTNetwork), and how its encoder
    attends."""
    output_axes: ClassVar[Any] = TripleBERTOutput._make((0, None, 0))
    ynnpack_matmuls: ClassVar[bool] = False
    """Measured no faster with them (1.00 on SMAX 2s3z; docs/speed.md)."""
    finetune_labels = PPOAlgorithm.finetune_labels

    @classmethod
    def build(
        cls, config: NetworkConfig, spec: EnvSpec, ppo: PPOConfig | None = None
    ) -> TripleBERT:
        return cls(TripleBERTNetwork(config, spec.num_agents, spec.action_dim, spec.discrete))
