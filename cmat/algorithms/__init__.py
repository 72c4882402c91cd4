"""Algorithms by name: each module holds only its network and its loss (see base.Algorithm)."""

from __future__ import annotations

import importlib
from typing import Any

from cmat.algorithms.base import Algorithm
from cmat.config import ALGORITHMS, NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.errors import CmatError

MODULES = {
    "cmat": "cmat.algorithms.cmat:CMAT",
    "mat": "cmat.algorithms.mat:MAT",
    "pmat": "cmat.algorithms.pmat:PMAT",
    "triple_bert": "cmat.algorithms.triple_bert:TripleBERT",
    "happo": "cmat.algorithms.happo:HAPPO",
    "mappo": "cmat.algorithms.mappo:MAPPO",
}
"""Where each algorithm of `cmat.config.ALGORITHMS` lives (imported on first use)."""


def algorithm_class(name: str) -> Any:
    """The class that implements the named algorithm (its module imported on first use)."""
    if name not in ALGORITHMS:
        raise CmatError(f"unknown algorithm {name!r}; available: {', '.join(ALGORITHMS)}")
    module_name, _, class_name = MODULES[name].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError:
        raise CmatError(f"algorithm {name!r} is not available in this version of cmat") from None
    return getattr(module, class_name)


def reference_defaults(name: str) -> dict[str, Any]:
    """The named algorithm's reference settings (its class's `reference_defaults`)."""
    defaults: dict[str, Any] = algorithm_class(name).reference_defaults
    return defaults


def algorithm_presets(name: str) -> dict[str, dict[str, Any]]:
    """The named algorithm's presets (its class's `presets`: name -> config values)."""
    presets: dict[str, dict[str, Any]] = algorithm_class(name).presets
    return presets


def build_algorithm(
    name: str, config: NetworkConfig, spec: EnvSpec, ppo: PPOConfig | None = None
) -> Algorithm:
    """The named algorithm's `build(config, spec, ppo)`."""
    algorithm: Algorithm = algorithm_class(name).build(config, spec, ppo or PPOConfig())
    return algorithm
