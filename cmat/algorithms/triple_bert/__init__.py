"""Triple-BERT (Zhao et al. 2025) as the paper's baseline: the team as one multi-action agent
whose per-agent factors see no consensus, trained as CMAT.

`algorithm.py` holds the class (acting, and the joint-ratio objective it shares with CMAT,
`cmat.algorithms.joint`), `network.py` the network. This module
is its registry entry and settings, read without importing JAX.
"""

from __future__ import annotations

from typing import Any

from cmat.algorithms.cmat import NETWORK_FIELDS
from cmat.algorithms.cmat import PRESETS as CMAT_PRESETS
from cmat.algorithms.entry import AlgorithmEntry
from cmat.algorithms.triple_bert.options import TripleBERTOptions

REFERENCE_DEFAULTS: dict[str, Any] = {}
"""The paper's baseline setting: the reference MAT's (the dataclass defaults), trained as
the paper trains CMAT (joint ratio clipped to [1 − ε, 1 + ε], target critic τ = 0.1)."""

PRESETS: dict[str, dict[str, Any]] = {
    name: {**{key: value for key, value in values.items() if key != "cmat"},
           "triple_bert": {key: value for key, value in values.get("cmat", {}).items()
                           if key in TripleBERTOptions.__dataclass_fields__}}
    for name, values in CMAT_PRESETS.items()
}
"""CMAT's, its section's values that Triple-BERT has (the joint ratio's) in Triple-BERT's:
'paper' the paper's setting (the baseline trained as the paper trains CMAT), 'tuned' the
study's two changes."""

YNNPACK_MATMULS = False
"""Measured no faster with them (1.00 on SMAX 2s3z; docs/speed.md)."""

ENTRIES = {
    "triple_bert": AlgorithmEntry(
        label="Triple-BERT",
        cls="cmat.algorithms.triple_bert.algorithm:TripleBERT",
        network_fields=NETWORK_FIELDS,
        options=TripleBERTOptions,
        capabilities=frozenset({"minibatch_chunks"}),
        reference_defaults=REFERENCE_DEFAULTS,
        presets=PRESETS,
        ynnpack_matmuls=YNNPACK_MATMULS,
    ),
}
