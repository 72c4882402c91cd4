"""Loading a user's environment factory from an id's `package.module:factory` part
(`pettingzoo:…` host environments, `jax:…` in-graph ones)."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from typing import Any

from cmat.errors import CmatError, SuiteUnavailable


def load_factory(env_id: str, target: str) -> Callable[..., Any]:
    """The callable named by `package.module:factory` (the factory may be dotted: `Class.make`).

    Raises CmatError where the module itself cannot be found (a typo or a missing PYTHONPATH:
    the user's to fix, so a grid stops on it) and SuiteUnavailable where the module imports a
    package that is not installed (a grid reports the task unavailable, as for a suite)."""
    module_name, _, attribute = target.rpartition(":")
    if not module_name or not attribute:
        prefix = env_id.partition(":")[0]
        raise CmatError(f"{env_id!r} must look like {prefix}:package.module:factory")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as error:
        missing = error.name or ""
        if module_name == missing or module_name.startswith(f"{missing}."):
            raise CmatError(
                f"{env_id}: cannot import {module_name!r} ({error}); it must be importable from "
                f"the Python running cmat ({sys.executable}): put its directory on PYTHONPATH "
                f"or pip-install its package"
            ) from None
        raise SuiteUnavailable(f"{env_id}: cannot import {module_name!r}: it imports "
                               f"{missing!r}, which is not installed ({error})") from None
    except Exception as error:  # the user's module: any error while importing it
        raise CmatError(f"{env_id}: importing {module_name!r} raised "
                        f"{type(error).__name__}: {error}") from None
    factory: Any = module
    for part in attribute.split("."):
        if not hasattr(factory, part):
            raise CmatError(f"{env_id}: module {module_name!r} has no {attribute!r}")
        factory = getattr(factory, part)
    if not callable(factory):
        raise CmatError(f"{env_id}: {attribute!r} is not callable")
    found: Callable[..., Any] = factory
    return found
