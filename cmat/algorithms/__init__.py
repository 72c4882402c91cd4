"""Algorithms by name: each module holds only its network and its loss (see base.Algorithm)."""

from __future__ import annotations

import importlib

from cmat.algorithms.base import Algorithm
from cmat.config import ALGORITHMS, NetworkConfig
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


def build_algorithm(name: str, config: NetworkConfig, spec: EnvSpec) -> Algorithm:
    """The named algorithm's `build(config, spec)`."""
    if name not in ALGORITHMS:
        raise CmatError(f"unknown algorithm {name!r}; available: {', '.join(ALGORITHMS)}")
    module_name, _, class_name = MODULES[name].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError:
        raise CmatError(f"algorithm {name!r} is not available in this version of cmat") from None
    return getattr(module, class_name).build(config, spec)
