"""The algorithm registry.

Each algorithm is a package `cmat/algorithms/<name>/` (docs/algorithms.md): its `__init__`,
which imports no JAX, names its `AlgorithmEntry`s in `ENTRIES` (one package may hold two:
`sable` holds `sable` and `ff_sable`), its `algorithm.py` holds the class (network and loss),
and modules of its own (its network) sit beside it; the modules every algorithm shares are
`base.py` (the `Algorithm` protocol), `ppo.py` and `sgd.py` here, and `cmat.networks`. The
registry finds cmat's own algorithms by scanning this package's subpackages
(`builtin_entries`), so adding one is adding a folder, and then those installed packages add
(`entries`). An entry holds what the rest of cmat needs to know about the algorithm: its label,
its `reference_defaults`, `task_reference_defaults` and `presets` (config layers), the
fine-tuning stages it supports, its `capabilities` (which algorithm-specific options it accepts)
and the network fields it reads. Everything here but `algorithm_class` and `build_algorithm`
reads the entries only, so resolving and checking a config never imports JAX.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import pkgutil
from typing import TYPE_CHECKING, Any

from cmat.algorithms.entry import AlgorithmEntry
from cmat.algorithms.options import options_of
from cmat.config import AlgorithmOptions, PPOConfig, validate
from cmat.errors import CmatError
from cmat.plugins import with_plugins

if TYPE_CHECKING:
    from cmat.algorithms.base import Algorithm
    from cmat.config import NetworkConfig, TrainConfig
    from cmat.envs.protocol import EnvSpec

__all__ = [
    "ENTRY_POINTS", "OPTION_CAPABILITIES", "AlgorithmEntry", "algorithm_class", "algorithm_entry",
    "algorithm_label", "algorithm_names", "algorithm_options", "algorithm_presets",
    "build_algorithm",
    "builtin_entries", "check_config", "entries", "finetune_stage_error", "reference_defaults",
    "task_reference_defaults",
]

ENTRY_POINTS = "cmat.algorithms"
"""The entry-point group where installed packages name their algorithms."""


@functools.cache
def builtin_entries() -> dict[str, AlgorithmEntry]:
    """The algorithms cmat ships: the `ENTRIES` of every subpackage of `cmat.algorithms`, the
    packages in the order of their names and each package's entries in its own order (the order
    `cmat config` and error messages list them). Only the packages' `__init__` modules are
    imported, none of them imports JAX."""
    found: dict[str, AlgorithmEntry] = {}
    packages = sorted(module.name for module in pkgutil.iter_modules(__path__) if module.ispkg)
    for package in packages:
        module = importlib.import_module(f"{__name__}.{package}")
        declared = getattr(module, "ENTRIES", None)
        if not isinstance(declared, dict) or not all(
            isinstance(entry, AlgorithmEntry) for entry in declared.values()
        ):
            raise TypeError(f"{module.__name__}.ENTRIES must be a dict of AlgorithmEntry "
                            f"by algorithm name, got {type(declared).__name__}")
        for name, entry in declared.items():
            if name in found:
                raise ValueError(f"algorithm {name!r} is named twice, the second time by "
                                 f"{module.__name__}")
            found[name] = entry
    return found


@functools.cache
def entries() -> dict[str, AlgorithmEntry]:
    """Every algorithm: cmat's own (`builtin_entries`), then those installed packages add under
    `ENTRY_POINTS` (cmat.plugins: a broken one is skipped with a one-line warning)."""
    return with_plugins(builtin_entries(), ENTRY_POINTS, AlgorithmEntry, "algorithm")


def algorithm_names() -> tuple[str, ...]:
    return tuple(entries())


def algorithm_entry(name: str) -> AlgorithmEntry:
    """The named algorithm's entry; CmatError for an unknown name."""
    found = entries()
    if name not in found:
        raise CmatError(f"unknown algorithm {name!r}; available: {', '.join(found)}")
    return found[name]


def algorithm_label(algo: str) -> str:
    """The name of `algo`'s line, as its authors name it (its entry's label): `Sable` is the
    Sable paper's recurrent Sable, `Sable (feed-forward)` Mava's `ff_sable`."""
    return algorithm_entry(algo).label


def algorithm_options(name: str) -> type[AlgorithmOptions]:
    """The class of the named algorithm's config section (its entry's `options`); CmatError
    for an unknown name."""
    return algorithm_entry(name).options


OPTION_CAPABILITIES = {
    "ppo.minibatch_chunks": ("minibatch_chunks", 1),
}
"""Shared options only some algorithms support: field -> (the capability it needs, the value
every algorithm accepts). An option only one algorithm has is in its own section instead."""


@functools.cache
def algorithm_class(name: str) -> type[Algorithm]:
    """The class that implements the named algorithm (its entry's `cls`), its module imported
    on first use; CmatError for an unknown name."""
    module_name, _, class_name = algorithm_entry(name).cls.partition(":")
    cls: type[Algorithm] = getattr(importlib.import_module(module_name), class_name)
    return cls


def reference_defaults(name: str) -> dict[str, Any]:
    """The named algorithm's reference settings (its entry's `reference_defaults`)."""
    return algorithm_entry(name).reference_defaults


def task_reference_defaults(name: str, env_id: str) -> dict[str, Any]:
    """The named algorithm's reference settings for one task (its entry's
    `task_reference_defaults`; empty where its reference has no per-task values)."""
    return algorithm_entry(name).task_reference_defaults.get(env_id, {})


def algorithm_presets(name: str) -> dict[str, dict[str, Any]]:
    """The named algorithm's presets (its entry's `presets`: name -> config values)."""
    return algorithm_entry(name).presets


def build_algorithm(
    name: str, config: NetworkConfig, spec: EnvSpec, ppo: PPOConfig | None = None,
    options: AlgorithmOptions | None = None,
) -> Algorithm:
    """The named algorithm's `build(config, spec, ppo, options)` (None: the defaults)."""
    algorithm: Algorithm = algorithm_class(name).build(
        config, spec, ppo or PPOConfig(), own_options(name, options))
    return algorithm


def own_options(name: str, options: AlgorithmOptions | None) -> AlgorithmOptions:
    """`options` as the named algorithm's section (`options_of`)."""
    return options_of(options, algorithm_options(name))


def finetune_stage_error(algo: str, stage: str) -> str | None:
    """Why the named algorithm cannot run the fine-tuning stage (not among its entry's
    `finetune_stages`), or None; the one message of `cmat train`, `cmat finetune` and an
    experiment spec."""
    if stage in algorithm_entry(algo).finetune_stages:
        return None
    able = [name for name, entry in entries().items() if stage in entry.finetune_stages]
    return (f"fine-tuning stage {stage!r} freezes CMAT's blocks and is supported only for algo "
            f"{', '.join(able) or 'none'}, got {algo!r}")


def check_config(config: TrainConfig) -> TrainConfig:
    """Reject a config whose algorithm is unknown, cannot fine-tune in `config.finetune`, or
    lacks the capability one of its options needs (`OPTION_CAPABILITIES`); returns it, its
    section the algorithm's own (`own_options`).

    Raises CmatError naming the field and the algorithms that accept it."""
    entry = algorithm_entry(config.algo)
    options = own_options(config.algo, config.options)
    if options is not config.options:
        config = validate(dataclasses.replace(config, options=options))
    if config.finetune is not None and (error := finetune_stage_error(config.algo,
                                                                      config.finetune)):
        raise CmatError(f"invalid config: {error}")
    for field, (capability, neutral) in OPTION_CAPABILITIES.items():
        section, _, name = field.partition(".")
        value = getattr(getattr(config, section), name)
        if value != neutral and capability not in entry.capabilities:
            able = [n for n, other in entries().items() if capability in other.capabilities]
            raise CmatError(
                f"invalid config: {field}={value} applies to the "
                f"{capability.replace('_', '-')} algorithms ({', '.join(able)}), not to "
                f"{config.algo!r}"
            )
    return config
