"""`python -m cmat ...` runs the command line; `cmat experiment` starts its runs this way.

With CMAT_PARENT_PID set (by the experiment runner), the run asks Linux to send it SIGTERM when
its parent dies, so killing an experiment never leaves a run writing into the grid.
"""

import ctypes
import os
import signal
import sys

from cmat.cli import main


def die_with_parent(parent: int) -> None:
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the parent died before the request was made
        sys.exit(143)


if os.environ.get("CMAT_PARENT_PID", "").isdigit():
    die_with_parent(int(os.environ["CMAT_PARENT_PID"]))
sys.exit(main())
