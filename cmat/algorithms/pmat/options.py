"""PMAT's section of the run config (`pmat:`): MAT's, with the order term of its loss.
JAX-free."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from cmat.algorithms.mat.options import MATOptions

if TYPE_CHECKING:
    from cmat.config import TrainConfig

LOSS_ORDERS = ("sampled", "index")


@dataclass(frozen=True)
class PMATOptions(MATOptions):
    """PMAT's options: MAT's, the order term's weight and the order its loss decodes along."""

    order_loss_coef: float = 1.0
    """Weight of the clipped PPO term on the sampled agent order's log-probability."""
    order_in_loss: str = "sampled"
    """The decision order the loss decodes the stored actions along: 'sampled' (the order
    acting sampled them in, the paper's reading) or 'index' (the agents' index order, as the
    reference's training pass does)."""

    def checks(self, section: str, config: TrainConfig) -> list[tuple[bool, str]]:
        return [
            *super().checks(section, config),
            (self.order_loss_coef >= 0,
             f"{section}.order_loss_coef must be in [0.0, inf), got {self.order_loss_coef}"),
            (self.order_in_loss in LOSS_ORDERS, f"{section}.order_in_loss must be one of "
             f"{', '.join(LOSS_ORDERS)}, got {self.order_in_loss!r}"),
        ]
