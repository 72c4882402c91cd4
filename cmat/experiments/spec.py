"""An experiment spec: a grid of environments × algorithms × variants × seeds, read from YAML.

The format, every key with its default and what a variant or a fine-tuning stage (`from`) means,
is docs/experiments.md's spec block (tests/test_experiment.py loads and plans
its example). `load_spec` checks a file against it: an unknown or duplicate key, a wrong type or
value, a `from` that names no variant or closes a cycle, or an env no variant runs on is a
one-line `CmatError` naming the file and the key.
"""

from __future__ import annotations

import contextlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from cmat.algorithms import algorithm_label, algorithm_names, finetune_stage_error
from cmat.config import FINETUNE_MODES, load_yaml
from cmat.errors import CmatError, read_text

FIGURES = ("main", "ablation", "none")
SPEC_KEYS = ("name", "description", "steps", "seeds", "seed", "seeds_per_run", "set", "envs",
             "algos", "variants", "bootstrap_reps", "score_window", "baselines", "claims")
ENV_KEYS = ("id", "steps", "set", "label", "unavailable")
VARIANT_KEYS = ("algos", "envs", "set", "steps", "from", "finetune", "figure", "label")


@dataclass(frozen=True)
class EnvEntry:
    id: str
    steps: int
    overrides: tuple[str, ...]
    label: str
    unavailable: str | None
    """Why the spec marks this environment as not runnable (it is then never tried)."""

    @property
    def slug(self) -> str:
        return self.id.replace(":", "_").replace("/", "_")


@dataclass(frozen=True)
class Variant:
    name: str
    algos: tuple[str, ...]
    overrides: tuple[str, ...]
    steps: int | None
    base: str | None
    """The variant a fine-tuning stage starts from (`from`)."""
    finetune: str | None
    figures: tuple[str, ...]
    """Which figures draw this variant: 'main' (Fig. 3 style), 'ablation' (Fig. 4 style, CMAT
    lines only)."""
    label: str | None
    envs: tuple[str, ...] | None = None
    """The environment ids this variant runs on; None: every environment of the spec."""

    def covers(self, env_id: str) -> bool:
        return self.envs is None or env_id in self.envs

    def line_label(self, algo: str) -> str:
        """The legend entry of this variant's `algo` runs (`algorithm_label`)."""
        name = algorithm_label(algo)
        if self.label is None:
            return name if self.name == "default" else f"{name} ({self.name})"
        return self.label if len(self.algos) == 1 else f"{name} {self.label}"


@dataclass(frozen=True)
class ExperimentSpec:
    name: str
    path: Path
    envs: tuple[EnvEntry, ...]
    algos: tuple[str, ...]
    variants: tuple[Variant, ...]
    seeds: int
    seed: int
    seeds_per_run: int
    overrides: tuple[str, ...]
    bootstrap_reps: int
    score_window: float = 0.0
    """Fraction of a run's env steps over whose evaluations a seed's score is averaged
    (`cmat.experiments.lines.Line.scores`); 0: the seed's last evaluation."""
    baselines: tuple[str, ...] = ()
    """Classical policies evaluated beside the learned lines on the dispatch tasks
    (`cmat.experiments.baselines`)."""
    claims: bool = False
    """Whether the report judges the CMAT paper's claims (cmat.experiments.claims) from this
    grid: for the grids built to test them, not for every grid."""

    def variant(self, name: str) -> Variant:
        return next(v for v in self.variants if v.name == name)


SPECS = Path(__file__).parent / "specs"
"""The experiment specs shipped with cmat: the grids behind the results pages, and smoke."""


def spec_names() -> list[str]:
    """The names `load_spec` accepts for the specs shipped with cmat."""
    return sorted(path.stem for path in SPECS.glob("*.yaml"))


def find_spec(path: Path | str) -> Path:
    """`path` itself where it exists or names a file (has a suffix or a folder), else the
    shipped spec of that name where there is one."""
    path = Path(path)
    shipped = SPECS / f"{path.name}.yaml"
    if not path.exists() and path.suffix == "" and path.parent == Path(".") and shipped.is_file():
        return shipped
    return path


def load_spec(path: Path | str) -> ExperimentSpec:
    """Read and check a spec: a YAML file, or the name of one shipped with cmat
    (`spec_names`: `dispatch` is cmat/experiments/specs/dispatch.yaml). Every problem is a
    one-line CmatError naming the file and key."""
    path = find_spec(path)
    try:
        raw = load_yaml(read_text(path, "experiment spec"))
    except FileNotFoundError:
        raise CmatError(f"experiment spec not found: {path} (the specs shipped with cmat: "
                        f"{', '.join(spec_names())})") from None
    except yaml.YAMLError as error:
        first = str(error).strip().splitlines()[0]
        raise CmatError(f"experiment spec {path} is not valid YAML: {first}") from None
    where = f"experiment spec {path}"
    if not isinstance(raw, dict):
        raise CmatError(f"{where} must hold a mapping of keys to values")
    check_keys(raw, SPEC_KEYS, where)
    for key in ("envs", "algos", "steps"):
        if key not in raw:
            raise CmatError(f"{where}: missing key {key!r}")
    steps = positive_int(raw["steps"], f"{where}: steps")
    seeds = positive_int(raw.get("seeds", 1), f"{where}: seeds")
    seed = integer(raw.get("seed", 0), f"{where}: seed")
    seeds_per_run = positive_int(raw.get("seeds_per_run", seeds), f"{where}: seeds_per_run")
    algos = algo_list(raw["algos"], f"{where}: algos")
    envs = tuple(env_entry(item, steps, f"{where}: envs[{i}]")
                 for i, item in enumerate(listed(raw["envs"], f"{where}: envs")))
    ids = [env.id for env in envs]
    if len(set(ids)) != len(ids):
        twice = min(i for i in ids if ids.count(i) > 1)
        raise CmatError(f"{where}: envs lists {twice!r} twice")
    variants_raw = raw.get("variants") or {"default": {}}
    if not isinstance(variants_raw, dict):
        raise CmatError(f"{where}: variants must be a mapping of names to settings")
    variants = tuple(variant(str(name), settings, algos, ids, f"{where}: variants.{name}")
                     for name, settings in variants_raw.items())
    check_stages(variants, where)
    idle = [env_id for env_id in ids if not any(v.covers(env_id) for v in variants)]
    if idle:
        raise CmatError(f"{where}: no variant runs on {idle[0]!r} (see the variants' envs)")
    spec_overrides = overrides(raw.get("set"), f"{where}: set")
    check_sections(spec_overrides, {a for v in variants for a in v.algos}, f"{where}: set")
    for i, env in enumerate(envs):
        check_sections(env.overrides, {a for v in variants if v.covers(env.id) for a in v.algos},
                       f"{where}: envs[{i}].set")
    for v in variants:
        check_sections(v.overrides, set(v.algos), f"{where}: variants.{v.name}.set")
    return ExperimentSpec(
        name=str(raw.get("name") or path.stem),
        path=path,
        envs=envs,
        algos=algos,
        variants=variants,
        seeds=seeds,
        seed=seed,
        seeds_per_run=min(seeds_per_run, seeds),
        overrides=spec_overrides,
        bootstrap_reps=positive_int(raw.get("bootstrap_reps", 2000), f"{where}: bootstrap_reps"),
        score_window=fraction(raw.get("score_window", 0.0), f"{where}: score_window"),
        baselines=baseline_list(raw.get("baselines"), ids, f"{where}: baselines"),
        claims=boolean(raw.get("claims", False), f"{where}: claims"),
    )


def boolean(value: Any, where: str) -> bool:
    if not isinstance(value, bool):
        raise CmatError(f"{where} must be true or false, got {value!r}")
    return value


def baseline_list(value: Any, ids: list[str], where: str) -> tuple[str, ...]:
    """The spec's `baselines`: names of `cmat.envs.dispatch.baselines.POLICIES`, for a spec
    with a dispatch task."""
    if value is None:
        return ()
    from cmat.envs.dispatch.baselines import POLICIES

    names = tuple(str(name) for name in listed(value, where))
    unknown = [name for name in names if name not in POLICIES]
    if unknown:
        raise CmatError(f"{where}: unknown baseline {unknown[0]!r}; available: "
                        f"{', '.join(POLICIES)}")
    if len(set(names)) != len(names):
        raise CmatError(f"{where}: lists {min(n for n in names if names.count(n) > 1)!r} twice")
    if not any(env_id.startswith("dispatch:") for env_id in ids):
        raise CmatError(f"{where}: baselines apply to dispatch tasks, and this spec has none")
    return names


def env_entry(item: Any, steps: int, where: str) -> EnvEntry:
    if isinstance(item, str):
        item = {"id": item}
    if not isinstance(item, dict) or "id" not in item:
        raise CmatError(f"{where} must be an environment id or a mapping with an id")
    check_keys(item, ENV_KEYS, where)
    env_id = item["id"]
    if not isinstance(env_id, str) or ":" not in env_id:
        raise CmatError(f"{where}: id must look like PREFIX:NAME, got {env_id!r}")
    unavailable = item.get("unavailable")
    if unavailable is not None and not isinstance(unavailable, str):
        raise CmatError(f"{where}: unavailable must be a reason (text)")
    return EnvEntry(
        id=env_id,
        steps=positive_int(item.get("steps", steps), f"{where}: steps"),
        overrides=overrides(item.get("set"), f"{where}: set"),
        label=str(item.get("label", env_id)),
        unavailable=unavailable,
    )


def variant(
    name: str, settings: Any, algos: tuple[str, ...], env_ids: list[str], where: str
) -> Variant:
    settings = {} if settings is None else settings
    if not isinstance(settings, dict):
        raise CmatError(f"{where} must be a mapping of settings")
    check_keys(settings, VARIANT_KEYS, where)
    base, finetune = settings.get("from"), settings.get("finetune")
    if (base is None) != (finetune is None):
        raise CmatError(f"{where}: a fine-tuning stage needs both 'from' (a variant) and "
                        f"'finetune' ({' or '.join(FINETUNE_MODES)})")
    if finetune is not None and finetune not in FINETUNE_MODES:
        raise CmatError(f"{where}: finetune must be one of {', '.join(FINETUNE_MODES)}, "
                        f"got {finetune!r}")
    variant_algos = (
        algo_list(settings["algos"], f"{where}: algos") if "algos" in settings else algos
    )
    if finetune is not None:
        for algo in variant_algos:
            if error := finetune_stage_error(algo, finetune):
                raise CmatError(f"{where}: {error}")
    figure = settings.get("figure", "main")
    figures = tuple(figure) if isinstance(figure, list) else (figure,)
    for kind in figures:
        if kind not in FIGURES:
            raise CmatError(f"{where}: figure must be one or a list of {', '.join(FIGURES)}, "
                            f"got {kind!r}")
    steps = settings.get("steps")
    label = settings.get("label")
    envs = None
    if "envs" in settings:
        envs = tuple(str(e) for e in listed(settings["envs"], f"{where}: envs"))
        unknown = [e for e in envs if e not in env_ids]
        if unknown:
            raise CmatError(f"{where}: envs names {unknown[0]!r}, which is not one of the "
                            f"spec's envs ({', '.join(env_ids)})")
    return Variant(
        name=name,
        algos=variant_algos,
        overrides=overrides(settings.get("set"), f"{where}: set"),
        steps=None if steps is None else positive_int(steps, f"{where}: steps"),
        base=None if base is None else str(base),
        finetune=finetune,
        figures=tuple(f for f in figures if f != "none"),
        label=None if label is None else str(label),
        envs=envs,
    )


def check_stages(variants: tuple[Variant, ...], where: str) -> None:
    """Every `from` names another variant that runs the same algorithms; no cycles."""
    by_name = {v.name: v for v in variants}
    for v in variants:
        if v.base is None:
            continue
        if v.base not in by_name:
            raise CmatError(f"{where}: variants.{v.name}: from names no variant: {v.base!r}")
        missing = sorted(set(v.algos) - set(by_name[v.base].algos))
        if missing:
            raise CmatError(f"{where}: variants.{v.name}: variant {v.base!r} it starts from "
                            f"has no {missing[0]} runs")
        base = by_name[v.base]
        if base.envs is not None and (v.envs is None or not all(map(base.covers, v.envs))):
            raise CmatError(f"{where}: variants.{v.name}: variant {v.base!r} it starts from "
                            f"does not run on every environment this stage runs on")
        seen, current = {v.name}, by_name[v.base]
        while current.base is not None:
            if current.name in seen:
                raise CmatError(f"{where}: variants.{v.name}: fine-tuning stages form a cycle")
            seen.add(current.name)
            current = by_name[current.base]
        if current.name in seen:
            raise CmatError(f"{where}: variants.{v.name}: fine-tuning stages form a cycle")


def overrides(value: Any, where: str) -> tuple[str, ...]:
    """`key=value` strings from a list of them or a (nested) mapping; values as JSON (which
    OmegaConf's dotlist reads as YAML), so lists and strings like 'n/2' keep their type."""
    if value is None:
        return ()
    if isinstance(value, dict):
        return tuple(f"{key}={json.dumps(item)}" for key, item in flatten(value))
    if isinstance(value, list) and all(isinstance(item, str) and "=" in item for item in value):
        return tuple(value)
    raise CmatError(f"{where} must be a mapping or a list of key=value strings")


def algorithm_section(override: str) -> str | None:
    """The algorithm whose options section `override` (`key=value`) sets (`cmat` for
    `cmat.consensus_iterations=2`), or None for a setting every algorithm has."""
    section = override.partition("=")[0].partition(".")[0]
    return section if section in algorithm_names() else None


def for_algorithm(settings: tuple[str, ...], algo: str) -> tuple[str, ...]:
    """The `settings` that apply to a run of `algo`: a setting in another algorithm's options
    section applies to that algorithm's runs only, so one spec-level `set` can give CMAT its m
    beside MAT and MAPPO."""
    return tuple(item for item in settings if algorithm_section(item) in (None, algo))


def check_sections(settings: tuple[str, ...], algos: set[str], where: str) -> None:
    """CmatError where a setting names the options of an algorithm that no run in its scope
    trains (it would apply to nothing)."""
    for item in settings:
        section = algorithm_section(item)
        if section is not None and section not in algos:
            raise CmatError(f"{where}: {item.partition('=')[0]} is an option of {section}, "
                            f"and none of the runs it applies to trains {section}")


def flatten(mapping: dict[Any, Any], prefix: str = "") -> list[tuple[str, Any]]:
    items: list[tuple[str, Any]] = []
    for key, value in mapping.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and value:
            items.extend(flatten(value, f"{name}."))
        else:
            items.append((name, value))
    return items


def check_keys(mapping: dict[Any, Any], allowed: tuple[str, ...], where: str) -> None:
    unknown = sorted(str(key) for key in mapping if key not in allowed)
    if unknown:
        raise CmatError(f"{where}: unknown key {unknown[0]!r}; allowed: {', '.join(allowed)}")


def listed(value: Any, where: str) -> list[Any]:
    if not isinstance(value, list) or not value:
        raise CmatError(f"{where} must be a non-empty list")
    return value


def algo_list(value: Any, where: str) -> tuple[str, ...]:
    names = listed(value, where)
    for name in names:
        if name not in algorithm_names():
            raise CmatError(f"{where}: unknown algorithm {name!r}; available: "
                            f"{', '.join(algorithm_names())}")
    if len(set(names)) != len(names):
        raise CmatError(f"{where} lists an algorithm twice")
    return tuple(names)


def integer(value: Any, where: str) -> int:
    """An integer, also written as 1e7 (which YAML reads as text) or 1.0e+7."""
    if isinstance(value, str):
        with contextlib.suppress(ValueError):
            value = float(value)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value):
        raise CmatError(f"{where} must be an integer, got {value!r}")
    return int(value)


def fraction(value: Any, where: str) -> float:
    """A number in [0, 1)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < 1:
        raise CmatError(f"{where} must be a number in [0, 1), got {value!r}")
    return float(value)


def positive_int(value: Any, where: str) -> int:
    number = integer(value, where)
    if number <= 0:
        raise CmatError(f"{where} must be > 0, got {value!r}")
    return number
