"""The algorithm registry: the one place algorithms are listed.

Each algorithm is one `AlgorithmEntry` (`ALGORITHMS`, and those installed packages add:
`entries`), whose class declares what the rest of cmat needs to know about it (see
`cmat.algorithms.base.Algorithm`): its `name`, its `reference_defaults`,
`task_reference_defaults` and `presets` (config layers), the fine-tuning stages it supports and
its `capabilities` (which algorithm-specific options it accepts). Config checks that depend on
the algorithm (`check_config`) read them.
"""

from __future__ import annotations

import functools
import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from cmat.config import PPOConfig
from cmat.errors import CmatError
from cmat.plugins import with_plugins

if TYPE_CHECKING:
    from cmat.algorithms.base import Algorithm
    from cmat.config import NetworkConfig, TrainConfig
    from cmat.envs.protocol import EnvSpec

@dataclass(frozen=True)
class AlgorithmEntry:
    """What cmat knows of an algorithm without importing it (nor JAX): its name, the name of
    its line in tables and figures, and where its class lives. A package adds an algorithm by
    naming an `AlgorithmEntry` under the `cmat.algorithms` entry-point group, the entry point's
    name being the algorithm's (docs/algorithms.md)."""

    label: str
    """Its name in tables, figures and claims (the papers' spelling)."""
    cls: str
    """`module:Class` of its `cmat.algorithms.base.Algorithm` subclass, imported on first use."""


ALGORITHMS = {
    "cmat": AlgorithmEntry("CMAT", "cmat.algorithms.cmat:CMAT"),
    "mat": AlgorithmEntry("MAT", "cmat.algorithms.mat:MAT"),
    "pmat": AlgorithmEntry("PMAT", "cmat.algorithms.pmat:PMAT"),
    "triple_bert": AlgorithmEntry("Triple-BERT", "cmat.algorithms.triple_bert:TripleBERT"),
    "happo": AlgorithmEntry("HAPPO", "cmat.algorithms.happo:HAPPO"),
    "mappo": AlgorithmEntry("MAPPO", "cmat.algorithms.mappo:MAPPO"),
    "sable": AlgorithmEntry("Sable", "cmat.algorithms.sable:Sable"),
    "ff_sable": AlgorithmEntry("Sable (feed-forward)", "cmat.algorithms.sable:FFSable"),
}
"""The algorithms cmat ships, in the order `cmat config` and error messages list them."""

ENTRY_POINTS = "cmat.algorithms"
"""The entry-point group where installed packages name their algorithms."""


@functools.cache
def entries() -> dict[str, AlgorithmEntry]:
    """Every algorithm: cmat's own (`ALGORITHMS`), then those installed packages add under
    `ENTRY_POINTS` (cmat.plugins: a broken one is skipped with a one-line warning)."""
    return with_plugins(ALGORITHMS, ENTRY_POINTS, AlgorithmEntry, "algorithm")


def algorithm_label(algo: str) -> str:
    """The name of `algo`'s line, as its authors name it (its entry's label): `Sable` is the
    Sable paper's recurrent Sable, `Sable (feed-forward)` Mava's `ff_sable`."""
    return entries()[algo].label


OPTION_CAPABILITIES = {
    "network.consensus_policy": ("consensus", "deterministic"),
    "ppo.joint_clip": ("joint_ratio", "joint"),
    "ppo.entropy_reduction": ("joint_ratio", "mean"),
    "ppo.per_agent_gae": ("per_agent_values", False),
    "ppo.minibatch_chunks": ("minibatch_chunks", 1),
    "ppo.order_in_loss": ("sampled_order", "sampled"),
}
"""Options only some algorithms have: field -> (the capability it needs, the value every
algorithm accepts)."""


def registry() -> dict[str, type[Algorithm]]:
    """Every algorithm's class by its name (the modules imported on first use)."""
    return {name: algorithm_class(name) for name in entries()}


def algorithm_names() -> tuple[str, ...]:
    return tuple(entries())


@functools.cache
def algorithm_class(name: str) -> type[Algorithm]:
    """The class that implements the named algorithm, its module imported on first use;
    CmatError for an unknown name."""
    if name not in entries():
        raise CmatError(f"unknown algorithm {name!r}; available: {', '.join(entries())}")
    module_name, _, class_name = entries()[name].cls.partition(":")
    cls: type[Algorithm] = getattr(importlib.import_module(module_name), class_name)
    return cls


def reference_defaults(name: str) -> dict[str, Any]:
    """The named algorithm's reference settings (its class's `reference_defaults`)."""
    defaults: dict[str, Any] = algorithm_class(name).reference_defaults
    return defaults


def task_reference_defaults(name: str, env_id: str) -> dict[str, Any]:
    """The named algorithm's reference settings for one task (its class's
    `task_reference_defaults`; empty where its reference has no per-task values)."""
    defaults: dict[str, Any] = algorithm_class(name).task_reference_defaults.get(env_id, {})
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


def finetune_stage_error(algo: str, stage: str) -> str | None:
    """Why the named algorithm cannot run the fine-tuning stage (not among its class's
    `finetune_stages`), or None; the one message of `cmat train`, `cmat finetune` and an
    experiment spec."""
    if stage in algorithm_class(algo).finetune_stages:
        return None
    able = [name for name, cls in registry().items() if stage in cls.finetune_stages]
    return (f"fine-tuning stage {stage!r} freezes CMAT's blocks and is supported only for algo "
            f"{', '.join(able) or 'none'}, got {algo!r}")


def check_config(config: TrainConfig) -> TrainConfig:
    """Reject a config whose algorithm is unknown, cannot fine-tune in `config.finetune`, or
    lacks the capability one of its options needs (`OPTION_CAPABILITIES`); returns it.

    Raises CmatError naming the field and the algorithms that accept it."""
    cls = algorithm_class(config.algo)
    if config.finetune is not None and (error := finetune_stage_error(config.algo,
                                                                      config.finetune)):
        raise CmatError(f"invalid config: {error}")
    for field, (capability, neutral) in OPTION_CAPABILITIES.items():
        section, _, name = field.partition(".")
        value = getattr(getattr(config, section), name)
        if value != neutral and capability not in cls.capabilities:
            able = [n for n, other in registry().items() if capability in other.capabilities]
            raise CmatError(
                f"invalid config: {field}={value} applies to the "
                f"{capability.replace('_', '-')} algorithms ({', '.join(able)}), not to "
                f"{config.algo!r}"
            )
    return config
