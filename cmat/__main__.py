"""`python -m cmat ...` runs the command line; `cmat experiment` starts its runs this way.

With CMAT_PARENT_PID set (by the experiment runner), the run asks Linux to send it SIGTERM when
its parent dies, so killing an experiment never leaves a run writing into the grid. With
CMAT_CORES set (also by the experiment runner, "0,1"), it runs on those cores only.
"""

import ctypes
import os
import signal
import sys


def die_with_parent(parent: int) -> None:
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the parent died before the request was made
        sys.exit(143)


def pin_to_cores(cores: str) -> None:
    """Run on the given cores only ("0,1"), set before JAX sizes its thread pools."""
    try:
        os.sched_setaffinity(0, {int(core) for core in cores.split(",")})
    except (ValueError, OSError) as error:
        print(f"cmat: warning: CMAT_CORES={cores!r} not applied ({error})", file=sys.stderr)


if os.environ.get("CMAT_PARENT_PID", "").isdigit():
    die_with_parent(int(os.environ["CMAT_PARENT_PID"]))
if os.environ.get("CMAT_CORES"):
    pin_to_cores(os.environ["CMAT_CORES"])
from cmat.cli import run  # noqa: E402 (after the pinning, before JAX starts its threads)

run()
