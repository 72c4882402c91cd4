"""MAPPO (Yu et al. 2022): one actor shared by all agents, a centralized critic, per-agent PPO.

`algorithm.py` holds the class (acting and the loss), `network.py` the MLP actor and critic,
which HAPPO (`cmat.algorithms.happo`) shares. This module is its registry entry and settings,
read without importing JAX.
"""

from __future__ import annotations

from typing import Any

from cmat.algorithms.entry import AlgorithmEntry
from cmat.algorithms.mappo.options import MLPOptions

NETWORK_FIELDS = ("n_embd", "init_gain", "log_std_init")
"""`n_embd` is the hidden width of the actor's and the critic's MLPs (`mappo.mlp_layers`
their depth), `init_gain` the actor output layer's gain (on-policy's `--gain`)."""

PRESETS: dict[str, dict[str, Any]] = {"paper": {"num_envs": 8}}
"""'paper': the paper's comparison setting, the reference settings with 8 rollout
threads."""

REFERENCE_DEFAULTS: dict[str, Any] = {
    "ppo": {"clip_eps": 0.2, "epochs": 5, "target_tau": 1.0, "active_masks": True},
}
"""Yu et al. 2022 (marlbenchmark/on-policy, SMAC scripts): clip 0.2, 5 epochs, GAE and
targets from the collecting critic, active masks."""

TASK_REFERENCE_DEFAULTS: dict[str, dict[str, Any]] = {
    "smax:3m": {"ppo": {"epochs": 15}},
    "smax:8m": {"ppo": {"epochs": 15}},
    "smax:25m": {"ppo": {"epochs": 10}},
    "smax:5m_vs_6m": {"ppo": {"epochs": 10, "clip_eps": 0.05}},
    "smax:10m_vs_11m": {"ppo": {"epochs": 10}},
    "smax:3s_vs_5z": {"ppo": {"epochs": 15, "clip_eps": 0.05}},
    "smax:MMM2": {"ppo": {"num_minibatches": 2}, "network": {"init_gain": 1.0}},
}
"""on-policy's per-map SMAC scripts (`onpolicy/scripts/train_smac_scripts/train_smac_MAP.sh`
at de66d7a) where they differ from clip 0.2, 5 epochs, 1 minibatch, gain 0.01; 3s5z,
3s5z_vs_3s6z, 6h_vs_8z and 27m_vs_30m run those, and maps without a script (2s3z, SMACv2)
too. 3s_vs_5z's stacked frames are not modelled."""

ENTRIES = {
    "mappo": AlgorithmEntry(
        label="MAPPO",
        cls="cmat.algorithms.mappo.algorithm:MAPPO",
        network_fields=NETWORK_FIELDS,
        options=MLPOptions,
        reference_defaults=REFERENCE_DEFAULTS,
        task_reference_defaults=TASK_REFERENCE_DEFAULTS,
        presets=PRESETS,
    ),
}
