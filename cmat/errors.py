"""User-facing errors: the CLI prints their message on one line and exits with code 2."""


class CmatError(Exception):
    """A problem with the user's input (environment id, config, run directory, checkpoint)."""
