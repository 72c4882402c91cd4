"""Each algorithm is one package of `cmat.algorithms`: a JAX-free `__init__` naming its
entries, the class in `algorithm.py`. The registry finds them by scanning, and resolving or
checking a config reads the entries only, never importing JAX."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys
import textwrap

import pytest

import cmat.algorithms
from cmat.algorithms import (
    AlgorithmEntry,
    algorithm_class,
    algorithm_names,
    builtin_entries,
    entries,
)

pytestmark = pytest.mark.unit


def algorithm_packages() -> list[str]:
    return sorted(module.name for module in pkgutil.iter_modules(cmat.algorithms.__path__)
                  if module.ispkg)


def test_the_registry_is_the_packages_entries_in_the_order_of_their_names() -> None:
    found: dict[str, AlgorithmEntry] = {}
    for package in algorithm_packages():
        found.update(importlib.import_module(f"cmat.algorithms.{package}").ENTRIES)
    assert builtin_entries() == found
    assert list(builtin_entries()) == [
        "cmat", "happo", "mappo", "mat", "pmat", "sable", "ff_sable", "triple_bert"]
    assert list(entries())[:len(found)] == list(found)


@pytest.mark.parametrize("package", algorithm_packages())
def test_each_package_names_the_classes_of_its_algorithm_module(package: str) -> None:
    declared = importlib.import_module(f"cmat.algorithms.{package}").ENTRIES
    assert declared, package
    for name, entry in declared.items():
        module, _, class_name = entry.cls.partition(":")
        assert module == f"cmat.algorithms.{package}.algorithm", name
        cls = algorithm_class(name)
        assert (cls.__module__, cls.__name__) == (module, class_name)
        assert callable(getattr(cls, "build", None)), name


@pytest.mark.parametrize("package", algorithm_packages())
def test_no_class_keeps_the_metadata_its_entry_holds(package: str) -> None:
    """The entry is the one place of an algorithm's metadata: no class attribute shadows it."""
    for name in importlib.import_module(f"cmat.algorithms.{package}").ENTRIES:
        cls = algorithm_class(name)
        kept = [field for field in AlgorithmEntry.__dataclass_fields__ if hasattr(cls, field)]
        assert kept == [], (name, kept)


def test_cmats_fine_tuning_stages_are_those_its_freeze_sets_know() -> None:
    from cmat.algorithms.cmat.blocks import FINETUNE_TRAINABLE

    assert tuple(FINETUNE_TRAINABLE) == entries()["cmat"].finetune_stages
    able = [name for name, entry in builtin_entries().items() if entry.finetune_stages]
    assert able == ["cmat"]


def test_resolving_and_checking_every_algorithms_config_imports_no_jax() -> None:
    """In a fresh interpreter: every algorithm's config resolved (its reference defaults, its
    task's, a preset where it has one) and checked, with JAX never imported."""
    script = textwrap.dedent("""
        import sys
        from cmat.algorithms import check_config, entries, finetune_stage_error
        from cmat.resolve import resolve_config

        for name, entry in entries().items():
            for preset in [None, *entry.presets]:
                overrides = [f"algo={name}", "env=matrix:fig1"]
                if preset is not None:
                    overrides.append(f"preset={preset}")
                config, _ = resolve_config(overrides=overrides)
                check_config(config)
            finetune_stage_error(name, "consensus")
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in ("jax", "jaxlib", "flax"))
        print(len(entries()), loaded)
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip() == f"{len(entries())} []", done.stdout


@pytest.mark.unit
def test_only_recurrent_algorithms_carry_a_state_and_the_others_act_through_stateless() -> None:
    """Recurrent Sable acts through its own `Recurrent` methods; every feed-forward algorithm
    (feed-forward Sable too, whose class could carry one) through `Stateless`, whose empty
    state leaves `act` as it is (checked on MAPPO, whose acting runs in milliseconds)."""
    import jax
    import numpy as np

    from cmat.algorithms import build_algorithm
    from cmat.algorithms.base import Recurrent, Stateless, is_recurrent, with_memory
    from cmat.config import NetworkConfig, PPOConfig
    from cmat.envs import make_env

    env = make_env("matrix:fig1")
    _, step = env.reset(jax.random.PRNGKey(0))
    for name in algorithm_names():
        algorithm = build_algorithm(name, NetworkConfig(n_embd=8), env.spec, PPOConfig())
        stepper = with_memory(algorithm)
        assert is_recurrent(algorithm) == (name == "sable"), name
        assert isinstance(stepper, Stateless) == (name != "sable"), name
        assert isinstance(stepper, Recurrent), name
        if name not in ("sable", "ff_sable"):
            assert not hasattr(algorithm, "act_with_memory"), name
    algorithm = build_algorithm("mappo", NetworkConfig(n_embd=8), env.spec, PPOConfig())
    stepper = with_memory(algorithm)
    params = algorithm.init(jax.random.PRNGKey(1), step.obs, step.action_mask)
    key = jax.random.PRNGKey(2)
    acted, memory = stepper.act_with_memory(params, stepper.initial_memory(), step.obs,
                                            step.action_mask, key, step.global_state,
                                            np.bool_(True))
    direct = algorithm.act(params, step.obs, step.action_mask, key, step.global_state)
    assert memory == ()
    np.testing.assert_array_equal(acted.actions, direct.actions)
    np.testing.assert_allclose(acted.log_probs, direct.log_probs)
