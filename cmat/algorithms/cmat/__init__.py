"""CMAT, the paper's method: the whole team is one multi-action agent trained with single-agent
PPO on the joint ratio, its actions conditioned on a consensus, with a team critic.

`algorithm.py` holds the class (acting and the loss), `network.py` the network (paper Fig. 2),
`blocks.py` its parameter blocks by name (fine-tuning's freeze sets, m at evaluation time). This
module is its registry entry and settings, read without importing JAX.
"""

from __future__ import annotations

from typing import Any

from cmat.algorithms.cmat.options import CMATOptions
from cmat.algorithms.entry import AlgorithmEntry
from cmat.config import NetworkConfig

PAPER_SETTINGS: dict[str, Any] = {
    "num_envs": 8,
    "ppo": {
        "clip_eps": 0.05, "value_coef": 1.0, "gamma": 0.99, "gae_lambda": 0.95,
        "target_tau": 0.1, "value_norm": True, "huber_loss": True, "huber_delta": 10.0,
        "clipped_value_loss": True, "normalize_advantages": True, "active_masks": False,
        "target_kl": None,
    },
    "network": {"n_embd": 64, "n_head": 1, "n_block": 1, "init_gain": 0.01, "log_std_init": 1.0},
    "cmat": {
        "consensus_iterations": "n", "consensus_source": "mixture",
        "consensus_policy": "deterministic", "joint_clip": "joint", "entropy_reduction": "mean",
    },
}
"""The paper's settings (Experiments supplement): "the model configurations follow those
established in MAT, with the exception of setting the rollout threads to 8". The suite layer
(cmat.envs.suites) gives MAT's column for the benchmark (SMAC: lr 5e-4, 15 epochs, one
minibatch, entropy 0.01, grad norm 10, 100-step rollouts; MA-MuJoCo and GRF their own); this
preset adds 8 rollout threads, MAT's shared values, m = n, the mixture consensus, the joint
ratio clipped to [1 − ε, 1 + ε] (eq. cmat), entropy averaged over agents, and the target critic
(τ not given in the paper: 0.1, docs/algorithms.md)."""


TUNED_SETTINGS: dict[str, Any] = {"ppo": {"target_tau": 1.0}, "cmat": {"joint_clip": "per_agent"}}
"""CMAT's default since the learning-speed study (docs/results/index.md), where it
learned faster per env step than the paper's settings, MAT and MAPPO on SMAX 6h_vs_8z, 5m_vs_6m
and 3s5z_vs_3s6z: the per-agent clip of the joint ratio (`cmat.joint_clip=per_agent`, which
replaces clip(R, 1 − ε, 1 + ε) of eq. cmat by clip(R, (1 − ε)^k, (1 + ε)^k) for k active agents)
and no lag in the target critic (τ = 1: V_φ- is the critic as the last update left it, standard
PPO). Joint ratio, consensus, team critic and order independence are unchanged. `--preset paper`
restores the paper's clip and τ = 0.1 with the rest of its settings."""

NETWORK_FIELDS = tuple(NetworkConfig.__dataclass_fields__)
"""Every shared `NetworkConfig` field."""

FINETUNE_STAGES = ("consensus", "action")
"""Algorithm 1, B: consensus enhancement, then action-policy enhancement; the blocks each one
trains are `blocks.FINETUNE_TRAINABLE`'s."""

REFERENCE_DEFAULTS = TUNED_SETTINGS
"""The reference MAT's settings (the dataclass defaults and the suite's column) with the
study's two changes (`TUNED_SETTINGS`); the paper's own are `--preset paper`."""

PRESETS: dict[str, dict[str, Any]] = {"paper": PAPER_SETTINGS, "tuned": TUNED_SETTINGS}
"""'paper': the paper's settings, for reproduction; 'tuned': the default's own values
(kept so that specs and commands that name it keep their meaning)."""

ENTRIES = {
    "cmat": AlgorithmEntry(
        label="CMAT",
        cls="cmat.algorithms.cmat.algorithm:CMAT",
        network_fields=NETWORK_FIELDS,
        options=CMATOptions,
        capabilities=frozenset({"minibatch_chunks"}),
        finetune_stages=FINETUNE_STAGES,
        reference_defaults=REFERENCE_DEFAULTS,
        presets=PRESETS,
        ynnpack_matmuls=True,
    ),
}
