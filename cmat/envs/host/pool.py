"""A batch of host environments stepped together, in-process or in worker processes.

Both pools take and return batches: `step(actions [E, ...])` gives a `HostTimeStep` whose fields
have a leading environment axis. Faults do not stop a run:
- an environment that raises in `step` is closed, rebuilt and reset; its step reports `done`
  (reward 0, not won), so the episode counts as truncated, and a warning is logged;
- a worker process that dies (killed, crashed, out of memory) is started again with fresh
  environments; every environment it held reports `done` the same way.
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import signal
from typing import Any

import numpy as np

from cmat.envs.host import make_host_env
from cmat.envs.host.protocol import HostEnv, HostTimeStep
from cmat.envs.protocol import EnvSpec
from cmat.errors import CmatError

log = logging.getLogger("cmat.host")

RESTART_SEED_STRIDE = 1_000_003
"""A restarted environment's reset seed: its slot's seed plus this times its restart count."""


def stack(timesteps: list[HostTimeStep]) -> HostTimeStep:
    """Per-environment timesteps as one batch with a leading environment axis."""
    return HostTimeStep(
        obs=np.stack([t.obs for t in timesteps]).astype(np.float32, copy=False),
        action_mask=np.stack([t.action_mask for t in timesteps]),
        reward=np.asarray([t.reward for t in timesteps], np.float32),
        done=np.asarray([t.done for t in timesteps], bool),
        won=np.asarray([t.won for t in timesteps], bool),
        alive=np.stack([t.alive for t in timesteps]).astype(bool, copy=False),
        global_state=np.stack([t.global_state for t in timesteps]).astype(np.float32, copy=False),
    )


def concatenate(batches: list[HostTimeStep]) -> HostTimeStep:
    """Batches of several pools as one, in order."""
    return HostTimeStep(*(np.concatenate(fields) for fields in zip(*batches)))


class InProcessPool:
    """One environment per seed in `seeds`, stepped one after the other in this process."""

    def __init__(self, env_id: str, env_kwargs: dict[str, Any], seeds: list[int],
                 envs: list[HostEnv] | None = None) -> None:
        self.env_id = env_id
        self.env_kwargs = dict(env_kwargs)
        self.envs: list[HostEnv] = list(envs or [])
        self._seeds = list(seeds)
        self.envs += [self._make(index) for index in range(len(self.envs), len(seeds))]
        self.spec: EnvSpec = self.envs[0].spec
        self._restarts = [0] * len(seeds)
        self.faults = 0
        """Environments restarted so far."""

    def _make(self, index: int) -> HostEnv:
        return make_host_env(self.env_id, seed=self._seeds[index], **self.env_kwargs)

    def reset(self, seeds: list[int] | None = None) -> HostTimeStep:
        """Start an episode in every environment, environment i with `seeds[i]` (default: the
        pool's seeds)."""
        self._seeds = list(seeds) if seeds is not None else self._seeds
        return stack([env.reset(seed) for env, seed in zip(self.envs, self._seeds)])

    def step(self, actions: np.ndarray) -> HostTimeStep:
        """Step environment i with `actions[i]`; one that raises is restarted (module doc)."""
        timesteps = []
        for index, env in enumerate(self.envs):
            try:
                timesteps.append(env.step(actions[index]))
            except Exception as error:  # any simulator error: restart, don't stop the run
                timesteps.append(self._restart(index, f"{type(error).__name__}: {error}"))
        return stack(timesteps)

    def _restart(self, index: int, reason: str) -> HostTimeStep:
        self.faults += 1
        self._restarts[index] += 1
        log.warning(
            "%s: environment %d raised (%s); restarted it, its episode counts as truncated",
            self.env_id, index, reason,
        )
        try:
            self.envs[index].close()
        except Exception:  # a broken simulator may fail to close too
            pass
        self.envs[index] = self._make(index)
        seed = self._seeds[index] + RESTART_SEED_STRIDE * self._restarts[index]
        return self.envs[index].reset(seed)._replace(reward=0.0, done=True, won=False)

    def worker_pids(self) -> list[int]:
        return []

    def close(self) -> None:
        """Close every environment."""
        for env in self.envs:
            try:
                env.close()
            except Exception:
                pass
        self.envs = []


def worker_main(conn: multiprocessing.connection.Connection, env_id: str,
                env_kwargs: dict[str, Any], seeds: list[int]) -> None:
    """A worker process: an `InProcessPool` of one environment per seed serving its parent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and closes us
    try:
        pool = InProcessPool(env_id, env_kwargs, seeds)
    except Exception as error:
        conn.send(("error", f"{type(error).__name__}: {error}"))
        return
    conn.send(("ready", None))
    while True:
        try:
            command, data = conn.recv()
            if command == "step":
                conn.send(pool.step(data))
                continue
            if command == "reset":
                conn.send(pool.reset(data))
                continue
        except (EOFError, OSError):  # the parent exited without closing us
            pass
        pool.close()
        conn.close()
        return


class Worker:
    """One worker process and the slice of environment slots it holds."""

    def __init__(self, env_id: str, env_kwargs: dict[str, Any], slots: slice,
                 seeds: list[int]) -> None:
        context = multiprocessing.get_context("spawn")
        self.slots = slots
        self.conn, child = context.Pipe()
        self.process = context.Process(
            target=worker_main, args=(child, env_id, env_kwargs, seeds), daemon=True
        )
        self.process.start()
        child.close()
        try:
            status, message = self.conn.recv()
        except (EOFError, OSError):
            status, message = "error", f"worker exited with code {self.process.exitcode}"
        if status != "ready":
            self.stop()
            raise CmatError(f"{env_id}: a worker could not build its environments ({message})")

    def stop(self) -> None:
        """Ask the worker to close; kill it if it does not."""
        try:
            self.conn.send(("close", None))
        except (OSError, ValueError):
            pass
        self.process.join(timeout=5)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.conn.close()


class WorkerPool:
    """One environment per seed, split over `workers` processes that step their slices at once."""

    def __init__(self, env_id: str, env_kwargs: dict[str, Any], seeds: list[int],
                 workers: int) -> None:
        self.env_id = env_id
        self.env_kwargs = dict(env_kwargs)
        self._seeds = list(seeds)
        count = len(seeds)
        bounds = np.linspace(0, count, min(workers, count) + 1).round().astype(int)
        slots = [slice(int(a), int(b)) for a, b in zip(bounds, bounds[1:])]
        self.workers = [Worker(env_id, env_kwargs, s, self._seeds[s]) for s in slots]
        self._restarts = 0
        self.faults = 0
        """Environments restarted because their worker died (an environment that raises is
        restarted, and logged, inside its worker)."""
        self.spec: EnvSpec | None = None

    def reset(self, seeds: list[int] | None = None) -> HostTimeStep:
        """Start an episode in every environment, environment i with `seeds[i]` (default: the
        pool's seeds)."""
        self._seeds = list(seeds) if seeds is not None else self._seeds
        return self._all("reset", lambda w: self._seeds[w.slots])

    def step(self, actions: np.ndarray) -> HostTimeStep:
        """Step environment i with `actions[i]`; a dead worker is replaced (module doc)."""
        return self._all("step", lambda w: actions[w.slots])

    def _all(self, command: str, data: Any) -> HostTimeStep:
        sent = []
        for worker in self.workers:
            try:
                worker.conn.send((command, data(worker)))
                sent.append(True)
            except (OSError, ValueError):
                sent.append(False)
        results = []
        for index, worker in enumerate(self.workers):
            try:
                if not sent[index]:
                    raise EOFError
                results.append(worker.conn.recv())
            except (EOFError, OSError):
                results.append(self._restart(index))
        return concatenate(results)

    def _restart(self, index: int) -> HostTimeStep:
        old = self.workers[index]
        old.process.join(timeout=1)
        code = old.process.exitcode
        old.stop()
        count = old.slots.stop - old.slots.start
        self.faults += count
        self._restarts += 1
        log.warning(
            "%s: worker process %d died (exit code %s); restarted it, the episodes of its %d "
            "environments count as truncated", self.env_id, index, code, count,
        )
        seeds = [s + RESTART_SEED_STRIDE * self._restarts for s in self._seeds[old.slots]]
        worker = Worker(self.env_id, self.env_kwargs, old.slots, seeds)
        self.workers[index] = worker
        worker.conn.send(("reset", seeds))
        batch: HostTimeStep = worker.conn.recv()
        return batch._replace(
            reward=np.zeros_like(batch.reward), done=np.ones_like(batch.done),
            won=np.zeros_like(batch.won),
        )

    def worker_pids(self) -> list[int]:
        """Process ids of the workers (tests kill one)."""
        return [worker.process.pid or 0 for worker in self.workers]

    def close(self) -> None:
        """Stop every worker."""
        for worker in self.workers:
            worker.stop()
        self.workers = []


def make_pool(
    env_id: str, env_kwargs: dict[str, Any], seeds: list[int], workers: int,
    envs: list[HostEnv] | None = None,
) -> InProcessPool | WorkerPool:
    """One environment per seed, in this process (`workers` = 0) or over `workers` processes;
    `envs` are already built environments an in-process pool starts with (a worker pool closes
    them)."""
    if workers <= 0:
        return InProcessPool(env_id, env_kwargs, seeds, envs)
    for env in envs or []:
        env.close()
    return WorkerPool(env_id, env_kwargs, seeds, workers)
