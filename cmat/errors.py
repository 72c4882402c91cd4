"""User-facing errors: the CLI prints their message on one line and exits with code 2."""

import os
from pathlib import Path


class CmatError(Exception):
    """A problem with the user's input (environment id, config, run directory, checkpoint)."""


class SuiteUnavailable(CmatError):
    """An environment suite that cannot be built on this machine because a package it needs is
    missing. An experiment grid reports its tasks as unavailable and skips them; any other
    CmatError about an environment (an unknown id, an option it does not take, a bad option
    value) is the user's to fix and stops the grid."""


def read_text(path: os.PathLike[str] | str, what: str) -> str:
    """The UTF-8 text of the file `what` names (config file, experiment spec, …). Raises
    CmatError where it is not UTF-8 text, naming the file and the first bad byte; other
    OSErrors (a missing file) propagate to the caller."""
    try:
        return Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise CmatError(f"{what} {path} is not UTF-8 text (byte {error.start})") from None
