"""What cmat knows of an algorithm without importing it (nor JAX): `AlgorithmEntry`.

Each algorithm package of cmat (`cmat/algorithms/<name>/__init__.py`) names its entries in
`ENTRIES`; an installed package names one under the `cmat.algorithms` entry point
(docs/algorithms.md). This module imports nothing but the standard library and `cmat.config`, so
that reading an entry never imports JAX.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from cmat.config import AlgorithmOptions


@dataclass(frozen=True)
class AlgorithmEntry:
    """An algorithm as the registry (`cmat.algorithms`) sees it: its label, where its class
    lives, and what the rest of cmat needs to know about it (the config layers it adds, the
    options and fine-tuning stages it accepts, the network fields it reads), all read without
    importing its class. Its name is the key it is registered under (`--algo NAME`)."""

    label: str
    """Its name in tables, figures and claims (the papers' spelling)."""
    cls: str
    """`module:Class` of its `cmat.algorithms.base.Algorithm` subclass (network and loss),
    imported on first use (`cmat.algorithms.algorithm_class`)."""
    network_fields: tuple[str, ...]
    """The shared `NetworkConfig` fields its networks read; the others leave it unchanged
    (`cmat config --algo NAME` marks them)."""
    options: type[AlgorithmOptions] = AlgorithmOptions
    """Its own section of the run config (a frozen dataclass importing no JAX, in the
    package's `options.py`): the network and loss options no other algorithm reads, with their
    defaults and docstrings, under the algorithm's name in config files and `--set`."""
    capabilities: frozenset[str] = frozenset()
    """What the algorithm has of `cmat.algorithms.OPTION_CAPABILITIES` (shared options that
    not every algorithm supports): 'minibatch_chunks' promises a loss whose reductions over
    the minibatch are means with parameter-independent denominators, so that without active
    masks equal slices' losses average to the minibatch's
    (`cmat.algorithms.base.loss_is_sample_mean`), and whose network pass with
    `ppo.minibatch_chunks` = k runs through `cmat.algorithms.base.chunked`."""
    finetune_stages: tuple[str, ...] = ()
    """The fine-tuning stages (`TrainConfig.finetune`) its class's `finetune_labels` knows."""
    reference_defaults: dict[str, Any] = field(default_factory=dict)
    """Config values of the algorithm's reference implementation where they differ from the
    dataclass defaults (the reference MAT's SMAC settings); `cmat.resolve.resolve_config` puts
    them between those defaults and a YAML file."""
    task_reference_defaults: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Config values the reference runs one task with (an environment id such as
    'smax:5m_vs_6m' -> values), where its per-task scripts differ from `reference_defaults`;
    `cmat.resolve.resolve_config` puts them right after those."""
    presets: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Named sets of config values (`TrainConfig.preset`); 'paper' is the paper's setting."""
    ynnpack_matmuls: bool = False
    """A hint to the CPU back-end, not part of the algorithm: whether its programs run their
    matmuls through YNNPACK on CPU (XLA's other YNNPACK fusions stay off either way;
    `cmat.runners.devices.compiler_options`): True where that was measured faster
    (docs/speed.md)."""
