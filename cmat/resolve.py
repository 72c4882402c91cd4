"""The run config a user gets: the layers of `cmat.config` resolved, with each value's source.

Layers, later ones winning: the dataclass defaults, the environment suite's settings
(`cmat.envs.suites`), the algorithm's reference defaults (and its reference's values for the
task, where they differ), its preset, a YAML file, then `key=value` overrides from the command
line. This module sits above the algorithms because two
of the layers (and the checks that depend on the algorithm) come from the algorithm registry.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from cmat.algorithms import (
    algorithm_names,
    algorithm_presets,
    check_config,
    reference_defaults,
    task_reference_defaults,
)
from cmat.config import (
    NESTED_FIELDS,
    ConfigSources,
    TrainConfig,
    field_names,
    layer_fields,
    load_yaml,
    one_line,
    validate,
)
from cmat.envs.suites import registry
from cmat.errors import CmatError, read_text


def load_config(
    yaml_file: Path | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    base: TrainConfig | None = None,
) -> TrainConfig:
    """`resolve_config` without the sources."""
    return resolve_config(yaml_file, overrides, base)[0]


def resolve_config(
    yaml_file: Path | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    base: TrainConfig | None = None,
    base_sources: ConfigSources | None = None,
    values: Mapping[str, Any] | None = None,
) -> tuple[TrainConfig, ConfigSources]:
    """A checked config and where each value came from. Layers, later ones winning: the
    dataclass defaults (or `base`, whose values keep `base_sources`), the environment suite's
    settings (cmat.envs.suites), the algorithm's reference defaults (its entry's
    `reference_defaults`, then its `task_reference_defaults` for the environment id), its
    preset, a YAML file, then `key=value` overrides, then `values` (the Python API's keyword
    arguments: `{"num_envs": 8, "ppo": {"lr": 1e-4}, "network.n_embd": 32}`, a dotted key
    naming a field of a section).

    Raises CmatError for an unreadable file, a malformed override, an unknown preset or field,
    and every check of `validate` and `check_config`."""
    schema, layers = config_layers(yaml_file, overrides, base, values)
    try:
        config = OmegaConf.to_object(OmegaConf.merge(schema, *(layer for _, layer in layers)))
    except OmegaConfBaseException as error:
        raise CmatError(f"invalid config: {config_error(error)}") from None
    assert isinstance(config, TrainConfig)
    sources = dict.fromkeys(field_names(), "default")
    sources.update(base_sources or {})
    for label, layer in layers:
        sources.update(dict.fromkeys(layer_fields(OmegaConf.to_container(layer)), label))
    return check_config(validate(config)), sources


def explain(
    key: str, yaml_file: Path | None = None, overrides: list[str] | tuple[str, ...] = ()
) -> list[tuple[str, Any]]:
    """Every layer's value of the field `key` (`ppo.lr`), top to bottom: the default, then each
    layer of `resolve_config` that sets it (the last one wins). Raises CmatError for a key
    that is no field, and as `resolve_config` for the file and overrides."""
    if key not in field_names():
        close = difflib.get_close_matches(key, field_names(), n=1)
        raise CmatError(f"no config field {key!r}" + (f"; did you mean {close[0]!r}?"
                                                       if close else "; see `cmat config`"))
    section, _, field = key.rpartition(".")
    default = getattr(TrainConfig(), section) if section else TrainConfig()
    rows: list[tuple[str, Any]] = [("default", getattr(default, field))]
    for label, layer in config_layers(yaml_file, overrides)[1]:
        values = OmegaConf.to_container(layer)
        if key in layer_fields(values):
            assert isinstance(values, dict)
            rows.append((label, values[section][field] if section else values[field]))
    return rows


def config_layers(
    yaml_file: Path | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    base: TrainConfig | None = None,
    values: Mapping[str, Any] | None = None,
) -> tuple[Any, list[tuple[str, Any]]]:
    """The schema (`base` or TrainConfig's defaults) and the layers over it, in the order of
    `resolve_config`: (label, OmegaConf mapping) each."""
    schema = OmegaConf.structured(base if base is not None else TrainConfig)
    layers: list[tuple[str, Any]] = []
    try:
        if yaml_file is not None:
            text = read_text(yaml_file, "config file")
            loaded = load_yaml(text) or {}
            if not isinstance(loaded, dict):
                raise CmatError(f"config file {yaml_file} must hold a mapping of keys to values")
            layers.append((f"file {yaml_file}", OmegaConf.create(loaded)))
        for item in overrides:
            if "=" not in item:
                raise CmatError(f"override {item!r} must look like key=value")
        if overrides:
            layers.append(("command line", OmegaConf.from_dotlist(list(overrides))))
        if values:
            layers.append(("arguments", OmegaConf.create(nested(values))))
        merged = OmegaConf.merge(schema, *(layer for _, layer in layers))
        if base is None:
            layers[:0] = named_layers(merged.env, merged.algo, merged.preset)
    except FileNotFoundError:
        raise CmatError(f"config file not found: {yaml_file}") from None
    except yaml.YAMLError as error:
        raise CmatError(f"config file {yaml_file} is not valid YAML: {one_line(error)}") from None
    except OmegaConfBaseException as error:
        raise CmatError(f"invalid config: {config_error(error)}") from None
    return schema, layers


def nested(values: Mapping[str, Any]) -> dict[str, Any]:
    """`values` with each dotted key (`ppo.lr`) turned into its section's mapping (`ppo:
    {lr: ...}`), merged with a section given as a mapping."""
    result: dict[str, Any] = {}
    for key, value in values.items():
        section, dot, field = key.partition(".")
        if dot:
            entry = result.setdefault(section, {})
            if not isinstance(entry, dict):
                raise CmatError(f"{section}: a section (set its keys as {section}.KEY), got "
                                f"{entry!r}")
            entry[field] = value
        elif isinstance(value, Mapping) and isinstance(result.get(key), dict):
            result[key].update(value)
        else:
            result[key] = dict(value) if isinstance(value, Mapping) else value
    return result


TYPE_NAMES = {"Integer": "an integer", "Float": "a number", "Boolean": "true or false",
              "String": "text"}

SECTIONS = {type(getattr(TrainConfig(), name)).__name__: name for name in NESTED_FIELDS}
"""Config class name -> its section's key (`PPOConfig` -> `ppo`)."""


def config_error(error: OmegaConfBaseException) -> str:
    """OmegaConf's message, worded for the user and naming the key: `ppo.epochs: expected an
    integer, got 'abc'`; `unknown key ppo.epoch. Did you mean: 'epochs'?`; `network: a section
    (set its keys as network.KEY=VALUE), got 5`."""
    message = one_line(error)
    key = getattr(error, "full_key", None)
    converted = (re.fullmatch(r"Value '(.*)' of type '\w+' could not be converted to (\w+)",
                              message)
                 or re.fullmatch(r"Value '(.*)' is not a valid (bool) \(type \w+\)", message))
    if key and converted is not None:
        expected = TYPE_NAMES.get(converted[2], TYPE_NAMES["Boolean"] if converted[2] == "bool"
                                  else converted[2].lower())
        return f"{key}: expected {expected}, got {converted[1]!r}"
    unknown = re.fullmatch(r"Key '\w+' not in '\w+'\.?(.*)", message)
    if key and unknown is not None:
        return f"unknown key {key}.{unknown[1]}".rstrip(".")
    section = re.fullmatch(r"Merge error: \w+ is not a subclass of (\w+)\. value: (.*)", message)
    if section is not None and section[1] in SECTIONS:
        name = SECTIONS[section[1]]
        return f"{name}: a section (set its keys as {name}.KEY=VALUE), got {section[2]}"
    return f"{key}: {message}" if key else message


def named_layers(env: str, algo: str, preset: str | None) -> list[tuple[str, Any]]:
    """The suite, algorithm and preset layers (label, values) for `env`, `algo` and `preset`.

    Raises CmatError for a preset the algorithm does not declare."""
    layers: list[tuple[str, Any]] = []
    suite = env.partition(":")[0]
    if suite in registry():
        layers.append((f"suite {suite}", OmegaConf.create(registry()[suite].settings)))
    if algo in algorithm_names():
        layers.append((f"algorithm {algo}", OmegaConf.create(reference_defaults(algo))))
        task_values = task_reference_defaults(algo, env)
        if task_values:
            layers.append((f"algorithm {algo} on {env}", OmegaConf.create(task_values)))
        if preset is not None:
            presets = algorithm_presets(algo)
            if preset not in presets:
                raise CmatError(f"unknown preset {preset!r} for {algo}; available: "
                                f"{', '.join(presets) or 'none'}")
            layers.append((f"preset {preset}", OmegaConf.create(presets[preset])))
    return layers
