"""User-facing errors: the CLI prints their message on one line and exits with code 2."""


class CmatError(Exception):
    """A problem with the user's input (environment id, config, run directory, checkpoint)."""


class SuiteUnavailable(CmatError):
    """An environment suite that cannot be built on this machine because a package it needs is
    missing. An experiment grid reports its tasks as unavailable and skips them; any other
    CmatError about an environment (an unknown id, an option it does not take, a bad option
    value) is the user's to fix and stops the grid."""
