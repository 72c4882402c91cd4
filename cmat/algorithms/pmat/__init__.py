"""PMAT (Hu et al. 2025): MAT whose decision order is sampled from a learned Plackett-Luce
model.

`algorithm.py` holds the class (acting and the loss; its network is MAT's with the order
scorer of `cmat.algorithms.mat.network`). This module is its registry entry and settings, read
without importing JAX.
"""

from __future__ import annotations

from typing import Any

from cmat.algorithms import mat
from cmat.algorithms.entry import AlgorithmEntry
from cmat.algorithms.pmat.options import PMATOptions

NETWORK_FIELDS = mat.NETWORK_FIELDS
"""MAT's; the order scorer's output layer has gain `init_gain`, its hidden layers the
reference's fixed 2 × 64."""

REFERENCE_DEFAULTS: dict[str, Any] = {
    "ppo": mat.REFERENCE_DEFAULTS["ppo"],
    "pmat": {**mat.REFERENCE_DEFAULTS["mat"], "order_loss_coef": 1e-4, "order_in_loss": "index"},
}
"""PMAT is built on the reference MAT code and trains as it does, with the reference SMAC
script's `--ranking_loss_coef 1e-4` and its training pass's decision order: `forward` in
`pma_transformer.py` decodes the stored actions with `discrete_parallel_act` on the encoder
output in index order (acting reindexed it along the sampled order)."""

ENTRIES = {
    "pmat": AlgorithmEntry(
        label="PMAT",
        cls="cmat.algorithms.pmat.algorithm:PMAT",
        network_fields=NETWORK_FIELDS,
        options=PMATOptions,
        capabilities=frozenset({"minibatch_chunks"}),
        reference_defaults=REFERENCE_DEFAULTS,
        presets=mat.PRESETS,
        ynnpack_matmuls=True,
    ),
}
