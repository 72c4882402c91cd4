"""MAT's section of the run config (`mat:`): its encoder's attention and per-agent values.
JAX-free."""

from __future__ import annotations

from dataclasses import dataclass

from cmat.algorithms.options import EncoderOptions, PerAgentValueOptions


@dataclass(frozen=True)
class MATOptions(EncoderOptions, PerAgentValueOptions):
    """MAT's options: how its encoder attends, and per-agent GAE."""
