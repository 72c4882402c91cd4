"""Sable's sections of the run config (`sable:`, `ff_sable:`): the retention's decay, the
recurrent one's training chunks, per-agent values. JAX-free."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

from cmat.algorithms.options import PerAgentValueOptions

if TYPE_CHECKING:
    from cmat.config import TrainConfig


@dataclass(frozen=True)
class FFSableOptions(PerAgentValueOptions):
    """Feed-forward Sable's options (Mava's `ff_sable`)."""

    retention_decay: float = 0.8
    """Scale in [0, 1] of every head's decay κ (Mava's `decay_scaling_factor`,
    mava/configs/network/rec_retention.yaml and ff_retention.yaml)."""

    network_options: ClassVar[tuple[str, ...]] = ("retention_decay",)

    def checks(self, section: str, config: TrainConfig) -> list[tuple[bool, str]]:
        return [*super().checks(section, config),
                (0.0 <= self.retention_decay <= 1.0,
                 f"{section}.retention_decay must be in [0, 1], got {self.retention_decay}")]


@dataclass(frozen=True)
class SableOptions(FFSableOptions):
    """Sable's options (the recurrent one, Mava's `rec_sable`): the feed-forward one's and how
    its training pass runs over time."""

    retention_chunk: int | None = None
    """Timesteps per chunk of the chunkwise training pass (memory O(chunk²) instead of
    O(rollout_length²); a pass's last chunk is shorter where the chunk does not divide its
    steps); None: the whole rollout in one parallel pass (Mava's default)."""

    network_options: ClassVar[tuple[str, ...]] = ("retention_decay", "retention_chunk")

    def checks(self, section: str, config: TrainConfig) -> list[tuple[bool, str]]:
        ppo = config.ppo
        return [
            *super().checks(section, config),
            (self.retention_chunk is None or self.retention_chunk > 0,
             f"{section}.retention_chunk must be > 0 or null, got {self.retention_chunk}"),
            (ppo.num_minibatches <= 0 or config.num_envs % ppo.num_minibatches == 0,
             f"Sable's minibatches are whole sequences: num_envs ({config.num_envs}) must be "
             f"divisible by ppo.num_minibatches ({ppo.num_minibatches})"),
        ]
