"""A run config as text: `config.yaml` written with each value's source, read back from any
layout this version knows, and the dotted field names and docstrings `cmat config` shows.

The algorithm's section (`TrainConfig.options`, its entry's `options` class) is written and read
under the algorithm's name: `cmat: {consensus_iterations: n}`, `--set sable.retention_chunk=16`.
This module sits above the algorithm registry because that section's class comes from it;
reading a config imports no JAX.
"""

from __future__ import annotations

import ast
import functools
import inspect
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

import cmat.config
from cmat.algorithms import algorithm_options
from cmat.config import (
    ConfigSources,
    TrainConfig,
    load_yaml,
    one_line,
    validate,
)
from cmat.errors import CmatError

SHARED_SECTIONS = ("network", "ppo")
"""The sections every algorithm reads; the third is the algorithm's own, named by it."""
OPTIONS = "options"
"""`TrainConfig`'s field that holds the algorithm's section."""
VERSION_HEADER = "# written by cmat "
"""The first line of a config.yaml: the version of cmat that wrote it (`written_by`)."""
LAYOUT_HEADER = "# config layout "
CONFIG_LAYOUT = 3
"""The layout of the config.yaml this version writes, on its second line (`LAYOUT_HEADER`).
Layout 1 (no such line; run directories written before 2026-12-06) chose Sable's variant with
`network.recurrent`; layout 2 named it by the algorithm, `sable` (recurrent) or `ff_sable`, and
kept every algorithm's options in the shared `network` and `ppo` sections; layout 3 moves each
algorithm's own options into its section (`MOVED`). `upgrade` converts 1 and 2."""

MOVED = {
    "network": ("mlp_layers", "compressor_heads", "consensus_iterations", "consensus_source",
                "consensus_policy", "consensus_codes", "latent_head_gain", "retention_decay",
                "retention_chunk", "attention_block"),
    "ppo": ("per_agent_gae", "joint_clip", "entropy_reduction", "consensus_ent_coef",
            "order_loss_coef", "order_in_loss"),
}
"""The fields layout 2 kept in a shared section that layout 3 keeps in the algorithm's own
(where the algorithm has them; the others it never read)."""


def to_mapping(config: TrainConfig) -> dict[str, Any]:
    """The config as plain values, its algorithm's section under the algorithm's name."""
    values = asdict(config)
    values[config.algo] = values.pop(OPTIONS)
    return values


def from_mapping(values: dict[str, Any]) -> TrainConfig:
    """A config from plain values as `to_mapping` gives them (any field may be missing: it
    takes its default). Raises CmatError for an unknown algorithm or field, a wrong type, and
    every check of `validate`."""
    algo = values.get("algo", TrainConfig.algo)
    options = algorithm_options(algo)
    if OPTIONS in values:
        raise CmatError(f"unreadable run config: unknown key {OPTIONS} (the algorithm's "
                        f"section is named by it: {algo})")
    inner = {key: value for key, value in values.items() if key != algo}
    if algo in values:
        inner[OPTIONS] = values[algo]
    try:
        config = OmegaConf.to_object(OmegaConf.merge(
            OmegaConf.structured(TrainConfig(algo=algo, options=options())),
            OmegaConf.create(inner)))
    except (OmegaConfBaseException, ValueError) as error:
        raise CmatError(f"unreadable run config: {external_key(one_line(error), algo)}") from None
    assert isinstance(config, TrainConfig)
    return validate(config)


def external_key(text: str, algo: str) -> str:
    """`text` with the section field's name (`options.`) replaced by the algorithm's."""
    return text.replace(f"{OPTIONS}.", f"{algo}.")


def sections(algo: str) -> tuple[str, ...]:
    """The section keys of a config of `algo`: the shared ones, then the algorithm's own."""
    return (*SHARED_SECTIONS, algo)


def field_names(algo: str = TrainConfig.algo) -> list[str]:
    """Every field of a config of `algo` by dotted name (`ppo.lr`,
    `cmat.consensus_iterations`; `env_kwargs` as one field)."""
    return layer_fields(
        to_mapping(TrainConfig(algo=algo, options=algorithm_options(algo)())), algo)


def layer_fields(values: Any, algo: str) -> list[str]:
    """The dotted field names a config layer (a nested mapping) of `algo` sets."""
    if not isinstance(values, dict):
        return []
    names: list[str] = []
    for key, value in values.items():
        if key in sections(algo) and isinstance(value, dict):
            names += [f"{key}.{inner}" for inner in value]
        else:
            names.append(str(key))
    return names


def to_yaml(config: TrainConfig, sources: ConfigSources | None = None) -> str:
    """The config as YAML (read back by `from_yaml`); with `sources`, every value carries its
    source as a comment (`lr: 5.0e-05  # suite mamujoco`)."""
    from cmat.version import __version__

    header = f"{VERSION_HEADER}{__version__}\n{LAYOUT_HEADER}{CONFIG_LAYOUT}\n"
    values = to_mapping(config)
    if sources is None:
        dumped: str = yaml.safe_dump(values, sort_keys=False)
        return header + dumped
    lines = [
        *header.splitlines(),
        "# Resolved run config. Each value's comment says where it came from: default (the",
        "# dataclasses in cmat/config.py and the algorithm's options), suite",
        "# (cmat/envs/suites.py), algorithm (its reference_defaults), preset, file, command line.",
    ]
    for key, value in values.items():
        if key in sections(config.algo):
            lines.append(f"{key}:")
            lines += [source_line(f"  {inner}", item, sources.get(f"{key}.{inner}"))
                      for inner, item in value.items()]
        else:
            lines.append(source_line(key, value, sources.get(key)))
    return "\n".join(lines) + "\n"


def source_line(key: str, value: Any, source: str | None) -> str:
    text = yaml.safe_dump(value, default_flow_style=True, width=1 << 30)
    text = text.removesuffix("\n...\n").rstrip("\n")
    return f"{key}: {text}" + (f"  # {source}" if source else "")


@functools.cache
def field_docs(algo: str = TrainConfig.algo) -> dict[str, str]:
    """Every field's docstring (the string literal after it in its dataclass) of a config of
    `algo` by dotted name, `ppo.lr`, `cmat.consensus_iterations`; what `cmat config` prints."""
    docs = {f"network.{name}": doc for name, doc in class_docs(cmat.config.NetworkConfig).items()}
    docs |= {f"ppo.{name}": doc for name, doc in class_docs(cmat.config.PPOConfig).items()}
    docs |= {name: doc for name, doc in class_docs(TrainConfig).items() if name != OPTIONS}
    docs |= {f"{algo}.{name}": doc
             for name, doc in class_docs(algorithm_options(algo)).items()}
    return docs


def class_docs(cls: type) -> dict[str, str]:
    """The docstrings of a dataclass's fields, its bases' included: the string literal after
    each annotated field in the class body (whitespace collapsed)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if klass is object:
            continue
        tree = ast.parse(Path(inspect.getfile(klass)).read_text())
        node = next((node for node in ast.walk(tree)
                     if isinstance(node, ast.ClassDef) and node.name == klass.__name__), None)
        if node is None:
            continue
        for field_node, after in zip(node.body, node.body[1:]):
            if (isinstance(field_node, ast.AnnAssign) and isinstance(field_node.target, ast.Name)
                    and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                    and isinstance(after.value.value, str)):
                docs[field_node.target.id] = " ".join(after.value.value.split())
    names = {item.name for item in fields(cls)}
    return {name: doc for name, doc in docs.items() if name in names}


def read_sources(text: str) -> ConfigSources:
    """The sources written by `to_yaml` into a config.yaml (empty for one written without),
    keyed by today's field names (`upgrade`)."""
    sources: ConfigSources = {}
    section = ""
    algo = TrainConfig.algo
    for line in text.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        indented = line.startswith(" ")
        key, _, rest = line.strip().partition(":")
        if not indented:
            section = key if not rest.strip() else ""
        value, marker, source = rest.rpartition("  # ")
        if key == "algo" and not indented:
            algo = (value if marker else rest).strip()
        if marker and value.strip():
            sources[f"{section}.{key}" if indented and section else key] = source.strip()
    if layout(text) < 3:
        for old, moved in MOVED.items():
            for name in moved:
                if f"{old}.{name}" in sources:
                    sources[f"{algo}.{name}"] = sources.pop(f"{old}.{name}")
    return sources


def written_by(text: str) -> str | None:
    """The cmat version named in a config.yaml's first line (None: written before 0.1.0
    recorded it)."""
    first = text.partition("\n")[0]
    return first.removeprefix(VERSION_HEADER).strip() if first.startswith(VERSION_HEADER) else None


def layout(text: str) -> int:
    """The layout of a config.yaml (`CONFIG_LAYOUT`): its `LAYOUT_HEADER` line's, else 1."""
    for line in text.splitlines()[:2]:
        if line.startswith(LAYOUT_HEADER) and line.removeprefix(LAYOUT_HEADER).isdigit():
            return int(line.removeprefix(LAYOUT_HEADER))
    return 1


def upgrade(loaded: Any, written_in: int) -> Any:
    """A config mapping of layout `written_in` in today's layout (`CONFIG_LAYOUT`); raises
    CmatError for a layout newer than this version reads."""
    if written_in > CONFIG_LAYOUT:
        raise CmatError(f"config layout {written_in} is newer than this cmat reads "
                        f"({CONFIG_LAYOUT}); update cmat")
    if not isinstance(loaded, dict):
        return loaded
    if written_in == 1 and isinstance(loaded.get("network"), dict):
        network = {k: v for k, v in loaded["network"].items() if k != "recurrent"}
        algo = loaded.get("algo")
        if algo == "sable" and not loaded["network"].get("recurrent", False):
            algo = "ff_sable"
        loaded = {**loaded, "algo": algo, "network": network}
    if written_in <= 2:
        algo = loaded.get("algo", TrainConfig.algo)
        own = {item.name for item in fields(algorithm_options(algo))}
        options: dict[str, Any] = {}
        for section, moved in MOVED.items():
            if isinstance(loaded.get(section), dict):
                options |= {k: v for k, v in loaded[section].items() if k in own}
                loaded = {**loaded, section: {k: v for k, v in loaded[section].items()
                                              if k not in moved}}
        loaded = {**loaded, algo: options}
    return loaded


def from_yaml(text: str) -> TrainConfig:
    """Read a resolved config written by `to_yaml` (a run directory's config.yaml), of any
    layout (`upgrade`). Raises CmatError for text that is not such a config."""
    try:
        loaded = upgrade(load_yaml(text), layout(text))
    except yaml.YAMLError as error:
        raise CmatError(f"unreadable run config: {one_line(error)}") from None
    if not isinstance(loaded, dict):
        raise CmatError("unreadable run config: not a mapping of keys to values")
    return from_mapping(loaded)
