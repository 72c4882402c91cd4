"""MAPPO's and HAPPO's section of the run config (`mappo:`, `happo:`): their MLPs' depth.
JAX-free."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

from cmat.config import AlgorithmOptions

if TYPE_CHECKING:
    from cmat.config import TrainConfig


@dataclass(frozen=True)
class MLPOptions(AlgorithmOptions):
    """The actor's and the critic's MLPs (their width is `network.n_embd`)."""

    mlp_layers: int = 2
    """Hidden layers of the actor's and the critic's MLPs (on-policy's MLPBase: 2; HARL's
    tuned SMAC configs: `hidden_sizes` [64, 64, 64], 3)."""

    network_options: ClassVar[tuple[str, ...]] = ("mlp_layers",)

    def checks(self, section: str, config: TrainConfig) -> list[tuple[bool, str]]:
        return [*super().checks(section, config),
                (self.mlp_layers > 0, f"{section}.mlp_layers must be > 0, got {self.mlp_layers}")]
