"""One run across several processes (several machines), with JAX's distributed runtime.

Every process runs the same `cmat train` (or `cmat.train`) with the same config and joins the
run through `initialize` (`--coordinator HOST:PORT --processes N --process-id I`, or
`--coordinator auto` where JAX finds the cluster itself: SLURM, Open MPI). `JaxTrainer` then
sees every process's devices as one mesh (cmat.runners.devices): the seeds, or else the
environments, are sharded across all of them, and the update's gradient means are reduced
across processes inside the compiled program (over Gloo on CPU, NCCL on GPU). Each process
starts from the same initial state (every process computes it from the same seeds) and holds
only its own shards.

Process 0 writes the run directory. The other processes run the same loop (they must: every
gather of metrics and checkpoints is a collective) into a scratch copy in the system's
temporary directory, deleted when the run ends; to resume, each reads the run directory named
by `--resume`, which therefore has to be visible to every process (a shared file system).

A process that dies (killed, out of memory, its machine lost) fails the others at their next
collective: they stop with one line naming the problem, and the run keeps its last checkpoint;
restart every process with `--resume`. A process that never joins fails the others after
`INITIALIZATION_SECONDS`. The runtime's own thread may find the loss first (the coordinator,
served by process 0, gone) and abort the process from C++; so `cmat train --coordinator`
trains in a child process (`supervise`) whose runtime log goes to a file, and says in one line
why the child stopped where it was killed by a signal.
"""

from __future__ import annotations

import re
import shutil
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from cmat.errors import CmatError

if TYPE_CHECKING:
    from cmat.config import ConfigSources
    from cmat.runners.base import Trainer, TrainerState

INITIALIZATION_SECONDS = 120
"""How long a process waits for all the others to join (`jax.distributed.initialize`)."""
HEARTBEAT_SECONDS = 60
"""How long the coordination service waits on a silent process before it ends the others. A
dead peer is usually found sooner, by the collective that waits on it."""

ADDRESS = re.compile(r"^[^\s:]+:\d{1,5}$")


def initialize(coordinator: str, processes: int | None = None,
               process_id: int | None = None) -> None:
    """Join a run of `processes` processes as process `process_id` (0-based), the coordinator
    listening at `coordinator` ('HOST:PORT', served by process 0), or with `coordinator`
    'auto' and the other two None, as JAX detects them (SLURM, Open MPI). Call it before
    anything else uses JAX.

    Raises CmatError for flags out of shape (`check_cluster`), a second call, and a cluster
    that cannot be joined (the runtime's first line).

    The runtime starts recoverable (`jax_enable_recoverability`): when a process dies, the
    runtime's own thread then mostly leaves the others alone instead of aborting them, and the
    error of the collective that waited on it reaches Python (`peer_failures`)."""
    import jax

    address = check_cluster(coordinator, processes, process_id)
    jax.config.update("jax_enable_recoverability", True)  # type: ignore[no-untyped-call]
    try:
        jax.distributed.initialize(
            address, processes, process_id, initialization_timeout=INITIALIZATION_SECONDS,
            heartbeat_timeout_seconds=HEARTBEAT_SECONDS)
    except (RuntimeError, ValueError, jax.errors.JaxRuntimeError) as error:
        raise CmatError(f"cannot join the run at {coordinator}: {first_line(error)}") from None


def check_cluster(coordinator: str, processes: int | None, process_id: int | None) -> str | None:
    """The coordinator's address (None for 'auto'); CmatError where the three flags do not fit
    together."""
    if coordinator == "auto":
        if processes is not None or process_id is not None:
            raise CmatError("--coordinator auto takes neither --processes nor --process-id "
                            "(JAX reads them from the cluster)")
        return None
    if not ADDRESS.match(coordinator):
        raise CmatError(f"--coordinator must be HOST:PORT or auto, got {coordinator!r}")
    if processes is None or process_id is None:
        raise CmatError("--coordinator HOST:PORT needs --processes N and --process-id I")
    if processes < 1 or not 0 <= process_id < processes:
        raise CmatError(f"--process-id must be in 0..{processes - 1} and --processes at "
                        f"least 1, got process {process_id} of {processes}")
    return coordinator


def active() -> bool:
    """Whether this process joined a run of several processes (`initialize`)."""
    if "jax" not in sys.modules:
        return False
    import jax

    return bool(jax.process_count() > 1)


def is_follower() -> bool:
    """Whether this is a process of a distributed run other than process 0."""
    if not active():
        return False
    import jax

    return jax.process_index() > 0


def describe() -> str:
    """'process I of N (D devices in all)'."""
    import jax

    return (f"process {jax.process_index()} of {jax.process_count()} "
            f"({len(jax.devices())} devices in all)")


@contextmanager
def peer_failures(run: Path) -> Iterator[None]:
    """Turn the error a collective raises when another process of the run (the one written to
    `run`) died into CmatError with the runtime's first line and how to go on; elsewhere
    nothing changes."""
    import jax

    try:
        yield
    except (jax.errors.JaxRuntimeError, ValueError) as error:
        if not active():
            raise
        raise CmatError(f"{describe()}: another process of the run stopped "
                        f"({first_line(error)}); {run} keeps its last checkpoint: start every "
                        f"process again with --resume {run}") from None


def follow(trainer: Trainer, sources: ConfigSources, out: Path, resume: bool) -> None:
    """Train as a process other than 0 of the run that process 0 writes to `out`: the same
    loop, into a scratch run directory (a copy of `out`'s run where `resume`), deleted at the
    end."""
    from cmat.rundir import RunDir
    from cmat.runners.loop import run_training

    with tempfile.TemporaryDirectory(prefix="cmat-follower-") as scratch:
        path = Path(scratch) / "run"
        start: TrainerState | None = None
        if resume:
            shutil.copytree(out, path, ignore=shutil.ignore_patterns(
                "tb", "step-*.ckpt", "run.lock", "*.png", "*.pdf"))
            run_dir = RunDir.open(path)
        else:
            start = trainer.init()
            run_dir = RunDir.create(path, trainer.config, sources)
        with peer_failures(out):
            run_training(trainer, run_dir, resume=resume, start=start)


def finish(code: int) -> None:
    """End this process's part of the run. With `code` 0, wait for every process to get here,
    then process 0 shuts the runtime down and the others leave without a word to it (it may
    be gone by then, which the runtime would take for a failure). Otherwise leave at once: a
    shutdown would wait on a process that is gone."""
    import os

    import jax
    from jax.experimental import multihost_utils

    sys.stdout.flush()
    sys.stderr.flush()
    if code == 0:
        multihost_utils.sync_global_devices("cmat: run finished")
        if not is_follower():
            jax.distributed.shutdown()  # type: ignore[no-untyped-call]
            return
    os._exit(code)


SUPERVISED = "CMAT_SUPERVISED_BY"
"""Set in the environment of the child `supervise` starts: the parent's process id."""


def supervise(argv: list[str], process: str, run: Path | None) -> int:
    """Run `cmat ARGV` (the training of `process`, e.g. 'process 1 of 2') in a child process
    and return its exit status; where a signal ended it
    (the runtime's abort, the kernel's out-of-memory killer), print one line saying so instead
    of the runtime's C++ log, which the child writes to a file (`quiet_runtime_log`), and
    return 2 (the line starts on a line of its own: the child's progress bar may have left one
    unfinished). The child dies with this process (Linux); Ctrl-C reaches both from the terminal,
    so this process leaves it to the child, and a SIGTERM it passes on."""
    import os
    import signal
    import subprocess

    child = subprocess.Popen([sys.executable, "-m", "cmat", *argv],
                             env={**os.environ, SUPERVISED: str(os.getpid())},
                             preexec_fn=die_with_parent)
    interrupt = signal.signal(signal.SIGINT, signal.SIG_IGN)
    terminate = signal.signal(signal.SIGTERM, lambda signum, frame: child.send_signal(signum))
    try:
        code = child.wait()
    finally:
        signal.signal(signal.SIGINT, interrupt)
        signal.signal(signal.SIGTERM, terminate)
    if code == 0:
        runtime_log_path(child.pid).unlink(missing_ok=True)
    if code >= 0:
        return code
    name = signal.Signals(-code).name
    where = (f"; {run} keeps its last checkpoint: start every process again with "
             f"--resume {run}") if run is not None else ""
    print(f"\ncmat: error: {process}: stopped by {name}, most likely because another process of "
          f"the run stopped (or this one ran out of memory; the runtime's log: "
          f"{runtime_log_path(child.pid)}){where}", file=sys.stderr)
    return 2


def die_with_parent() -> None:
    """In the child, before exec: ask Linux for SIGKILL when the parent dies (elsewhere
    nothing)."""
    import contextlib
    import ctypes
    import signal

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def runtime_log_path(pid: int) -> Path:
    return Path(tempfile.gettempdir()) / f"cmat-runtime-{pid}.log"


def quiet_runtime_log() -> None:
    """Send what C++ writes to file descriptor 2 (the runtime's log) to `runtime_log_path`,
    keeping Python's `sys.stderr` (messages, progress bars) on the terminal."""
    import os

    terminal = os.dup(2)
    sys.stderr.flush()
    sys.stderr = open(terminal, "w", buffering=1, encoding="utf-8", errors="replace")  # noqa: SIM115
    log = os.open(runtime_log_path(os.getpid()), os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    os.dup2(log, 2)
    os.close(log)


def first_line(error: BaseException) -> str:
    lines = str(error).strip().splitlines()
    return lines[0] if lines else type(error).__name__
