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
    algorithm_options,
    algorithm_presets,
    check_config,
    reference_defaults,
    task_reference_defaults,
)
from cmat.config import (
    ConfigSources,
    TrainConfig,
    load_yaml,
    one_line,
    validate,
)
from cmat.configfile import OPTIONS, external_key, field_names, layer_fields
from cmat.envs.suites import registry
from cmat.errors import CmatError, read_text

Layer = tuple[str, dict[str, Any]]
"""A config layer: its label (the source `cmat config` shows) and its values as a user writes
them, the algorithm's section under the algorithm's name."""


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
    dataclass defaults and the algorithm's section's (or `base`, whose values keep
    `base_sources`), the environment suite's settings (cmat.envs.suites), the algorithm's
    reference defaults (its entry's `reference_defaults`, then its `task_reference_defaults`
    for the environment id), its preset, a YAML file, then `key=value` overrides, then
    `values` (the Python API's keyword arguments: `{"num_envs": 8, "ppo": {"lr": 1e-4},
    "network.n_embd": 32, "cmat.consensus_iterations": 2}`, a dotted key naming a field of a
    section). The algorithm's section is named by the algorithm; the named layers' sections
    of other algorithms are left out (a suite setting for CMAT applies to CMAT runs only).

    Raises CmatError for an unreadable file, a malformed override, an unknown preset or field,
    a section of another algorithm than the run's in the file, overrides or `values`, and every
    check of `validate` and `check_config`."""
    algo, layers = config_layers(yaml_file, overrides, base, values)
    schema = OmegaConf.structured(
        base if base is not None else TrainConfig(algo=algo, options=algorithm_options(algo)()))
    try:
        config = OmegaConf.to_object(OmegaConf.merge(
            schema, *(OmegaConf.create(internal(layer, algo)) for _, layer in layers)))
    except OmegaConfBaseException as error:
        raise CmatError(f"invalid config: {config_error(error, algo)}") from None
    assert isinstance(config, TrainConfig)
    sources = dict.fromkeys(field_names(algo), "default")
    sources.update(base_sources or {})
    for label, layer in layers:
        sources.update(dict.fromkeys(layer_fields(layer, algo), label))
    return check_config(validate(config)), sources


def internal(layer: dict[str, Any], algo: str) -> dict[str, Any]:
    """A layer as `TrainConfig` holds it: the algorithm's section under `options`."""
    values = {key: value for key, value in layer.items() if key != algo}
    if algo in layer:
        values[OPTIONS] = layer[algo]
    return values


def explain(
    key: str, yaml_file: Path | None = None, overrides: list[str] | tuple[str, ...] = ()
) -> list[tuple[str, Any]]:
    """Every layer's value of the field `key` (`ppo.lr`, `cmat.consensus_iterations`), top to
    bottom: the default, then each layer of `resolve_config` that sets it (the last one wins).
    Raises CmatError for a key that is no field of the run's algorithm's config, and as
    `resolve_config` for the file and overrides."""
    algo, layers = config_layers(yaml_file, overrides)
    names = field_names(algo)
    if key not in names:
        close = difflib.get_close_matches(key, names, n=1)
        raise CmatError(f"no config field {key!r} for algo {algo}" + (
            f"; did you mean {close[0]!r}?" if close else "; see `cmat config`"))
    section, _, field = key.rpartition(".")
    defaults: dict[str, Any] = {"": TrainConfig(), algo: algorithm_options(algo)()}
    default = defaults[section] if section in defaults else getattr(TrainConfig(), section)
    rows: list[tuple[str, Any]] = [("default", getattr(default, field))]
    for label, layer in layers:
        if key in layer_fields(layer, algo):
            rows.append((label, layer[section][field] if section else layer[field]))
    return rows


def config_layers(
    yaml_file: Path | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    base: TrainConfig | None = None,
    values: Mapping[str, Any] | None = None,
) -> tuple[str, list[Layer]]:
    """The run's algorithm and the layers over the defaults (or `base`), in the order of
    `resolve_config`. Raises CmatError as `resolve_config`."""
    layers: list[Layer] = []
    try:
        if yaml_file is not None:
            text = read_text(yaml_file, "config file")
            loaded = load_yaml(text) or {}
            if not isinstance(loaded, dict):
                raise CmatError(f"config file {yaml_file} must hold a mapping of keys to values")
            layers.append((f"file {yaml_file}", loaded))
        for item in overrides:
            if "=" not in item:
                raise CmatError(f"override {item!r} must look like key=value")
        if overrides:
            dotlist = OmegaConf.to_container(OmegaConf.from_dotlist(list(overrides)))
            assert isinstance(dotlist, dict)
            layers.append(("command line", {str(key): value for key, value in dotlist.items()}))
        if values:
            layers.append(("arguments", nested(values)))
    except FileNotFoundError:
        raise CmatError(f"config file not found: {yaml_file}") from None
    except yaml.YAMLError as error:
        raise CmatError(f"config file {yaml_file} is not valid YAML: {one_line(error)}") from None
    except OmegaConfBaseException as error:
        raise CmatError(f"invalid config: {config_error(error, TrainConfig.algo)}") from None
    start = base if base is not None else TrainConfig()
    chosen = {name: getattr(start, name) for name in ("env", "algo", "preset")}
    for _, layer in layers:
        chosen |= {name: layer[name] for name in chosen if name in layer}
    algo = chosen["algo"]
    if not isinstance(algo, str) or algo not in algorithm_names():
        raise CmatError(f"invalid config: unknown algorithm {algo!r}; available: "
                        f"{', '.join(algorithm_names())}")
    if base is not None and algo != base.algo:
        raise CmatError(f"invalid config: algo is {base.algo!r} in the run this one continues; "
                        f"it cannot change")
    for label, layer in layers:
        for key, value in layer.items():
            if key == OPTIONS:
                raise CmatError(f"invalid config ({label}): unknown key {OPTIONS}; the "
                                f"algorithm's section is named by it: {algo}.KEY")
            if key in algorithm_names() and key != algo:
                field = next(iter(value), "KEY") if isinstance(value, dict) and value else "KEY"
                raise CmatError(f"invalid config ({label}): {key}.{field} is an option of "
                                f"{key}, and this run's algo is {algo}")
    if base is None:
        layers[:0] = named_layers(str(chosen["env"]), algo, chosen["preset"])
    return algo, layers


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

def config_error(error: OmegaConfBaseException, algo: str) -> str:
    """OmegaConf's message, worded for the user and naming the key as the user writes it (the
    algorithm's section by `algo`): `ppo.epochs: expected an integer, got 'abc'`; `unknown key
    ppo.epoch. Did you mean: 'epochs'?`; `network: a section (set its keys as
    network.KEY=VALUE), got 5`."""
    message = external_key(one_line(error), algo)
    key = getattr(error, "full_key", None)
    key = external_key(f"{key}.", algo)[:-1] if key else key
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
    names = {"NetworkConfig": "network", "PPOConfig": "ppo",
             algorithm_options(algo).__name__: algo}
    if section is not None and section[1] in names:
        name = names[section[1]]
        return f"{name}: a section (set its keys as {name}.KEY=VALUE), got {section[2]}"
    return f"{key}: {message}" if key else message


def named_layers(env: str, algo: str, preset: str | None) -> list[Layer]:
    """The suite, algorithm and preset layers for `env`, `algo` and `preset`, without the
    sections of other algorithms than `algo`.

    Raises CmatError for a preset the algorithm does not declare."""
    named: list[Layer] = []
    suite = env.partition(":")[0]
    if suite in registry():
        named.append((f"suite {suite}", registry()[suite].settings))
    named.append((f"algorithm {algo}", reference_defaults(algo)))
    task_values = task_reference_defaults(algo, env)
    if task_values:
        named.append((f"algorithm {algo} on {env}", task_values))
    if preset is not None:
        presets = algorithm_presets(algo)
        if preset not in presets:
            raise CmatError(f"unknown preset {preset!r} for {algo}; available: "
                            f"{', '.join(presets) or 'none'}")
        named.append((f"preset {preset}", presets[preset]))
    others = set(algorithm_names()) - {algo}
    return [(label, {key: value for key, value in values.items() if key not in others})
            for label, values in named]
