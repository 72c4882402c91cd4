"""MAT (Wen et al. 2022): agents act one after another in a fixed order, each with its own
clipped ratio, per-agent values.

`algorithm.py` holds the class (acting and the loss), `network.py` the encoder-decoder (and
PMAT's order scorer). This module is its registry entry and settings, read without importing
JAX; PMAT (`cmat.algorithms.pmat`) and Sable (`cmat.algorithms.sable`) build on it.
"""

from __future__ import annotations

from typing import Any

from cmat.algorithms.entry import AlgorithmEntry
from cmat.algorithms.mat.options import MATOptions

NETWORK_FIELDS = ("n_embd", "n_head", "n_block", "init_gain", "log_std_init")
"""The encoder-decoder's sizes (MATNetwork)."""

PRESETS: dict[str, dict[str, Any]] = {"paper": {"num_envs": 8}}
"""'paper': the paper's comparison setting, the reference settings with 8 rollout
threads."""

REFERENCE_DEFAULTS: dict[str, Any] = {
    "ppo": {"target_tau": 1.0, "active_masks": True, "value_active_masks": False},
    "mat": {"per_agent_gae": True},
}
"""The reference MAT (PKU-MARL/Multi-Agent-Transformer, SMAC scripts): GAE and targets from
the collecting critic, active masks in the policy loss and entropy but not in the value
loss, per-agent GAE with value normalisation; the other hyper-parameters are the dataclass
defaults."""

ENTRIES = {
    "mat": AlgorithmEntry(
        label="MAT",
        cls="cmat.algorithms.mat.algorithm:MAT",
        network_fields=NETWORK_FIELDS,
        options=MATOptions,
        capabilities=frozenset({"minibatch_chunks"}),
        reference_defaults=REFERENCE_DEFAULTS,
        presets=PRESETS,
        ynnpack_matmuls=True,
    ),
}
