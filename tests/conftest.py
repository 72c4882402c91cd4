"""One JAX compilation cache per test session, shared by the xdist workers; XLA's optimisations
skipped for the tests marked `quick_compiles` (the learning checks among them marked `optimised`).

Many tests build the same small programs (a CMAT on ``matrix:fig1``, a SMAX 3m update) in
separate closures; XLA's persistent cache keys on the compiled program, so the second build
is a file read. The directory is fresh for every session and removed at its end, so a test
never depends on what an earlier session compiled.

Where XLA's optimisations are skipped, its CPU fusion emitters are off as well
(`xla_cpu_use_fusion_emitters`): unoptimised programs then compile in about two thirds of the
time (tests/test_network.py: 93 s against 149 s on the 2-core EPYC, 2026-12-07), where for
optimised ones the emitters pay (the Fig. 1 learning check: 49 s with them, 88 s without).

The workers' OpenBLAS (LAPACK's QR in the orthogonal initialisers) runs on one thread, as the
trainers' initialisation does (`cmat.runners.base.single_threaded_lapack`): with two workers
on two cores, its threads otherwise spin against XLA's for up to a second per initialisation.
"""

import functools
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from typing import Any

import pytest

CACHE_VARIABLE = "JAX_COMPILATION_CACHE_DIR"
CACHE_KEY = pytest.StashKey[str]()
FUSION_EMITTERS = "xla_cpu_use_fusion_emitters"


def pytest_configure(config: pytest.Config) -> None:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    if hasattr(config, "workerinput") or CACHE_VARIABLE in os.environ:
        return
    directory = tempfile.mkdtemp(prefix="cmat-tests-jax-cache-")
    os.environ[CACHE_VARIABLE] = directory
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
    config.stash[CACHE_KEY] = directory


LONGEST_FIRST = (
    "test_experiment.py", "test_policy.py", "test_host_envs.py", "test_sable.py",
    "test_config_command.py", "test_mat.py", "test_finetune.py", "test_training.py",
    "test_fair_comparisons.py", "test_baselines_mlp.py", "test_jumanji_envs.py",
    "test_user_jax_envs.py",
)
"""The test files that take longest (summed test durations of a two-worker run on the project's
2-core machine, about 4-10 minutes of a worker each), longest first."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The long files first, the rest in their usual order: the workers take whole files in
    collection order (`--dist loadfile`), so short files fill in at the end instead of one
    worker waiting on a long file started last."""
    rank = {name: index for index, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def pytest_unconfigure(config: pytest.Config) -> None:
    directory = config.stash.get(CACHE_KEY, None)
    if directory is not None:
        shutil.rmtree(directory, ignore_errors=True)
        os.environ.pop(CACHE_VARIABLE, None)


def without_fusion_emitters_when_unoptimised(
    get_compile_options: Callable[..., Any],
) -> Callable[..., Any]:
    """JAX's `get_compile_options` that also turns XLA's CPU fusion emitters off whenever
    `jax_disable_most_optimizations` is on and JAX computes on the CPU (as
    `compiler_options={FUSION_EMITTERS: False}` would for one program; an option the program
    sets itself wins)."""
    import jax

    @functools.wraps(get_compile_options)
    def wrapped(*args: Any, **kwargs: Any) -> Any:
        options = get_compile_options(*args, **kwargs)
        if jax.config.read("jax_disable_most_optimizations") and jax.default_backend() == "cpu":
            overrides = dict(options.env_option_overrides)
            overrides.setdefault(FUSION_EMITTERS, False)
            options.env_option_overrides = list(overrides.items())
        return options

    return wrapped


@pytest.fixture(scope="session", autouse=True)
def quick_compiles_skip_fusion_emitters() -> Iterator[None]:
    from jax._src import compiler  # JAX's one place where compile options are made

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(compiler, "get_compile_options",
                      without_fusion_emitters_when_unoptimised(compiler.get_compile_options))
        yield


def set_optimisations_off(off: bool) -> Iterator[None]:
    import jax  # not at the top: JAX reads JAX_COMPILATION_CACHE_DIR when it is first imported

    previous = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", off)
    yield
    jax.config.update("jax_disable_most_optimizations", previous)


@pytest.fixture(scope="module", autouse=True)
def quick_compiles(request: pytest.FixtureRequest) -> Iterator[None]:
    """Modules marked `quick_compiles` run programs for milliseconds, so compiling is nearly all
    their cost: skipping XLA's optimisations halves it, for their module fixtures and the
    processes they start as well."""
    if request.node.get_closest_marker("quick_compiles") is None:
        yield
        return
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
        flags = os.environ.get("XLA_FLAGS", "")
        patch.setenv("XLA_FLAGS", f"{flags} --{FUSION_EMITTERS}=false".strip())
        yield from set_optimisations_off(True)


@pytest.fixture(autouse=True)
def quick_compiles_per_test(request: pytest.FixtureRequest) -> Iterator[None]:
    """A test marked `quick_compiles` (or in such a module) compiles without XLA's optimisations
    unless it is a learning check, marked `slow` or `optimised`: those run long programs."""
    marked = request.node.get_closest_marker
    quick = marked("quick_compiles") is not None
    yield from set_optimisations_off(
        quick and marked("slow") is None and marked("optimised") is None)
