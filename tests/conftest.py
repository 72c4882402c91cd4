"""One JAX compilation cache per test session, shared by the xdist workers.

Many tests build the same small programs (a CMAT on ``matrix:fig1``, a SMAX 3m update) in
separate closures; XLA's persistent cache keys on the compiled program, so the second build
is a file read. The directory is fresh for every session and removed at its end, so a test
never depends on what an earlier session compiled.
"""

import os
import shutil
import tempfile

import pytest

CACHE_VARIABLE = "JAX_COMPILATION_CACHE_DIR"
CACHE_KEY = pytest.StashKey[str]()


def pytest_configure(config: pytest.Config) -> None:
    if hasattr(config, "workerinput") or CACHE_VARIABLE in os.environ:
        return
    directory = tempfile.mkdtemp(prefix="cmat-tests-jax-cache-")
    os.environ[CACHE_VARIABLE] = directory
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
    config.stash[CACHE_KEY] = directory


def pytest_unconfigure(config: pytest.Config) -> None:
    directory = config.stash.get(CACHE_KEY, None)
    if directory is not None:
        shutil.rmtree(directory, ignore_errors=True)
        os.environ.pop(CACHE_VARIABLE, None)

