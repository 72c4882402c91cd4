"""HAPPO (Kuba et al. 2022; HARL, Zhong et al. 2024): heterogeneous agents updated one by one.

`algorithm.py` holds the class (MAPPO's networks, one actor per agent, and the sequential
update). This module is its registry entry and settings, read without importing JAX.
"""

from __future__ import annotations

from typing import Any

from cmat.algorithms import mappo
from cmat.algorithms.entry import AlgorithmEntry
from cmat.algorithms.mappo.options import MLPOptions

REFERENCE_DEFAULTS: dict[str, Any] = {
    "ppo": {"clip_eps": 0.2, "epochs": 5, "target_tau": 1.0, "active_masks": True},
    "network": {"n_embd": 128},
}
"""HARL's default HAPPO config (harl/configs/algos_cfgs/happo.yaml): clip 0.2, 5 epochs,
two hidden layers of 128, GAE and targets from the collecting critic, policy active masks;
the maps HARL tuned override it (`TASK_REFERENCE_DEFAULTS`)."""

TASK_REFERENCE_DEFAULTS: dict[str, dict[str, Any]] = {
    f"smax:{name}": {
        "ppo": {"clip_eps": clip, "gamma": gamma, "epochs": epochs,
                "num_minibatches": minibatches},
        "network": {"n_embd": 64},
        "happo": {"mlp_layers": 3},
    }
    for name, clip, gamma, epochs, minibatches in (
        ("3s5z", 0.2, 0.99, 5, 1),
        ("25m", 0.2, 0.99, 5, 1),
        ("5m_vs_6m", 0.05, 0.95, 5, 1),
        ("10m_vs_11m", 0.05, 0.95, 5, 1),
        ("27m_vs_30m", 0.05, 0.95, 5, 1),
        ("3s5z_vs_3s6z", 0.1, 0.95, 5, 2),
        ("6h_vs_8z", 0.05, 0.95, 10, 2),
        ("MMM2", 0.2, 0.95, 5, 1),
    )
}
"""HARL's tuned SMAC configs (`tuned_configs/smac/MAP/happo/config.json` at d539bad):
`hidden_sizes` [64, 64, 64] on every map, and per map `clip_param`, `gamma`, `ppo_epoch` and
`actor_num_mini_batch` (the critic's epochs and minibatches equal the actor's on each).
Maps HARL did not tune (2s3z, 3m, 8m, SMACv2) run `happo.yaml`. Not modelled: their
recurrent actors, 20 × 160-step rollouts and `use_proper_time_limits` (docs/algorithms.md)."""

ENTRIES = {
    "happo": AlgorithmEntry(
        label="HAPPO",
        cls="cmat.algorithms.happo.algorithm:HAPPO",
        network_fields=mappo.NETWORK_FIELDS,
        options=MLPOptions,
        reference_defaults=REFERENCE_DEFAULTS,
        task_reference_defaults=TASK_REFERENCE_DEFAULTS,
        presets=mappo.PRESETS,
    ),
}
