"""Extensions from installed packages: entries they name under one of cmat's entry-point groups
(`cmat.suites`, `cmat.algorithms`), the entry point's name being the suite's prefix or the
algorithm's name. Loading an entry imports only the module that defines it, which should not
import JAX (docs/own-environment.md, docs/algorithms.md)."""

from __future__ import annotations

import importlib.metadata
import sys
from typing import TypeVar

Entry = TypeVar("Entry")


def with_plugins(builtin: dict[str, Entry], group: str, kind: type[Entry],
                 what: str) -> dict[str, Entry]:
    """`builtin`, then the entries installed packages name under `group`, by name. An entry
    that cannot be loaded, is not a `kind` or takes a name `builtin` has is skipped with a
    one-line warning on stderr naming it as `what` (e.g. 'suite')."""
    found = dict(builtin)
    for entry in sorted(importlib.metadata.entry_points(group=group),
                        key=lambda entry: entry.name):
        try:
            value = entry.load()
        except Exception as error:  # a broken plugin must not stop cmat
            problem: str | None = f"cannot be loaded ({type(error).__name__}: {error})"
        else:
            problem = (f"is not a {kind.__module__}.{kind.__qualname__} "
                       f"({type(value).__name__})" if not isinstance(value, kind)
                       else "takes a name cmat has" if entry.name in found else None)
        if problem is not None:
            print(f"cmat: warning: the {what} {entry.name!r} ({entry.value}) "
                  f"{problem.splitlines()[0]}; skipped", file=sys.stderr)
            continue
        found[entry.name] = value
    return found
