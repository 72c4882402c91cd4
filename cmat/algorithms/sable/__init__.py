"""Sable (Mahjoub et al., ICML 2025): MAT's autoregressive PPO on a retention network, as two
algorithms: `sable`, the Sable paper's recurrent Sable (Mava's `rec_sable`), and `ff_sable`,
Mava's feed-forward Sable.

`algorithm.py` holds the classes (`Sable`, `FFSable`: MAT's acting and loss on sequences),
`network.py` the retention encoder-decoder; its module docstrings say what both references do
and cmat does with them. This module is their registry entries and settings, read without
importing JAX.
"""

from __future__ import annotations

from typing import Any

from cmat.algorithms.entry import AlgorithmEntry
from cmat.algorithms.sable.options import FFSableOptions, SableOptions

NETWORK_FIELDS = ("n_embd", "n_head", "n_block", "log_std_init")
"""The retention encoder-decoder's sizes (SableNetwork)."""

REFERENCE_DEFAULTS: dict[str, Any] = {
    "ppo": {
        "lr": 5e-4, "epochs": 10, "num_minibatches": 1, "clip_eps": 0.2, "ent_coef": 0.01,
        "value_coef": 0.5, "max_grad_norm": 10.0, "target_tau": 1.0, "active_masks": False,
        "value_norm": False, "huber_loss": False, "clipped_value_loss": True,
        "normalize_advantages": False,
    },
    "sable": {"per_agent_gae": True},
}
"""Mava's rec_sable system and network configs (mava/configs/system/sable/rec_sable.yaml at
18c0f2d: lr 5e-4, 10 epochs of one minibatch, clip 0.2, gradient norm 10; `algorithm.py`'s
module docstring)."""

FF_REFERENCE_DEFAULTS: dict[str, Any] = {
    "ppo": {**REFERENCE_DEFAULTS["ppo"], "lr": 2.5e-4, "epochs": 4, "num_minibatches": 2,
            "max_grad_norm": 0.5},
    "ff_sable": REFERENCE_DEFAULTS["sable"],
}
"""Mava's ff_sable system and network configs (ff_sable.yaml at b53e2de: lr 2.5e-4, 4 epochs
of 2 minibatches, clip 0.2, gradient norm 0.5; `algorithm.py`'s module docstring)."""

YNNPACK_MATMULS = False
"""Measured no faster with them (0.97 on SMAX 2s3z; docs/speed.md)."""

ENTRIES = {
    "sable": AlgorithmEntry(
        label="Sable",
        cls="cmat.algorithms.sable.algorithm:Sable",
        network_fields=NETWORK_FIELDS,
        options=SableOptions,
        reference_defaults=REFERENCE_DEFAULTS,
        ynnpack_matmuls=YNNPACK_MATMULS,
    ),
    "ff_sable": AlgorithmEntry(
        label="Sable (feed-forward)",
        cls="cmat.algorithms.sable.algorithm:FFSable",
        network_fields=NETWORK_FIELDS,
        options=FFSableOptions,
        reference_defaults=FF_REFERENCE_DEFAULTS,
        ynnpack_matmuls=YNNPACK_MATMULS,
    ),
}
