"""Triple-BERT's section of the run config (`triple_bert:`): CMAT's compressors and joint-ratio
loss options, without its consensus. JAX-free."""

from __future__ import annotations

from dataclasses import dataclass

from cmat.algorithms.cmat.options import CompressorOptions
from cmat.algorithms.options import JointRatioOptions


@dataclass(frozen=True)
class TripleBERTOptions(CompressorOptions, JointRatioOptions):
    """Triple-BERT's options: the critic's compressor and the joint ratio."""
