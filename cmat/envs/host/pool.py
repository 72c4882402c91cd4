"""A batch of host environments stepped together, in-process or in worker processes.

Both pools take and return batches: `step(actions [E, ...])` gives a `HostTimeStep` whose fields
have a leading environment axis. Simulator faults do not stop a run:
- an environment whose simulator raises in its own `reset`, `step` or `state`
  (`SimulatorCrash`) is closed, rebuilt and reset; its step reports `done` (reward 0, not won),
  so the episode counts as truncated, and a warning is logged. One that crashes `crash_limit`
  times in a row (`TrainConfig.host_crash_limit`) stops the run with a `CmatError` naming it;
- a worker process that dies (killed, crashed, out of memory) is started again with fresh
  environments; every environment it held reports `done` the same way.
Every environment a pool builds, restarts included, must match the first one built
(`check_alike`): a factory whose instances differ stops the run with a `CmatError`.
Anything else is not a simulator fault: a `CmatError` (a malformed observation or reward, a
non-finite value) stops the run with its one-line message, and any other exception is a bug in
cmat and surfaces as one, from a worker process too. `counters()` gives, per environment slot,
the restarts so far and the non-finite values replaced by 0 (`host_nonfinite=warn`).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import multiprocessing
import multiprocessing.connection
import signal
import traceback
from typing import Any

import numpy as np

from cmat.envs.host import make_host_env
from cmat.envs.host.protocol import HostBatch, HostEnv, HostStep, HostTimeStep, SimulatorCrash
from cmat.envs.protocol import EnvSpec
from cmat.errors import CmatError

log = logging.getLogger("cmat.host")

RESTART_SEED_STRIDE = 1_000_003
"""A restarted environment's reset seed: its slot's seed plus this times its restart count."""
DEFAULT_CRASH_LIMIT = 3
"""Crashes in a row of one environment that stop the run (`TrainConfig.host_crash_limit`)."""
COUNTERS = ("env_restarts", "env_nonfinite")
"""Per-slot counters of `counters()` (metrics.csv columns of host runs)."""


def stack(timesteps: list[HostStep]) -> HostBatch:
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


def check_alike(env_id: str, reference: dict[str, Any], env: HostEnv, index: int) -> None:
    """CmatError naming what differs where environment `index` of a pool is not built like the
    first one (`reference`, its `HostEnv.description`)."""
    description = env.description()

    def shown(values: dict[str, Any], key: str) -> str:
        return repr(values[key]) if key in values else "(none)"

    differs = [f"{key} {shown(reference, key)} vs {shown(description, key)}"
               for key in dict.fromkeys([*reference, *description])
               if key not in reference or key not in description
               or reference[key] != description[key]]
    if differs:
        more = f" and {len(differs) - 3} more" if len(differs) > 3 else ""
        raise CmatError(f"{env_id}: environment {index} differs from the first one built "
                        f"({'; '.join(differs[:3])}{more}); every instance the factory builds "
                        f"must have the same agents and spaces")


def concatenate(batches: list[HostBatch]) -> HostBatch:
    """Batches of several pools as one, in order."""
    return HostTimeStep(*(np.concatenate(fields) for fields in zip(*batches)))


class InProcessPool:
    """One environment per seed in `seeds`, stepped one after the other in this process. Each
    environment it builds must match `reference` (default: the first one's description;
    `check_alike`); `first_slot` is its first environment's index in error messages."""

    def __init__(self, env_id: str, env_kwargs: dict[str, Any], seeds: list[int],
                 envs: list[HostEnv] | None = None, crash_limit: int = DEFAULT_CRASH_LIMIT,
                 nonfinite: str = "error", reference: dict[str, Any] | None = None,
                 first_slot: int = 0) -> None:
        self.env_id = env_id
        self.env_kwargs = dict(env_kwargs)
        self.crash_limit = crash_limit
        self.nonfinite = nonfinite
        self.envs: list[HostEnv] = list(envs or [])
        self.reference = reference or (self.envs[0].description() if self.envs else None)
        self.first_slot = first_slot
        self._seeds = list(seeds)
        self.envs += [self._make(index) for index in range(len(self.envs), len(seeds))]
        self.spec: EnvSpec = self.envs[0].spec
        self._restarts = np.zeros(len(seeds), np.int64)
        self._in_a_row = np.zeros(len(seeds), np.int64)
        self._replaced_before = np.zeros(len(seeds), np.int64)
        """Non-finite values replaced by environments of the slot closed since."""

    def _make(self, index: int) -> HostEnv:
        env = make_host_env(self.env_id, seed=self._seeds[index], nonfinite=self.nonfinite,
                            **self.env_kwargs)
        if self.reference is None:
            self.reference = env.description()
        else:
            try:
                check_alike(self.env_id, self.reference, env, self.first_slot + index)
            except CmatError:
                env.close()
                raise
        return env

    def reset(self, seeds: list[int] | None = None) -> HostBatch:
        """Start an episode in every environment, environment i with `seeds[i]` (default: the
        pool's seeds); one whose simulator crashes is restarted (module doc)."""
        self._seeds = list(seeds) if seeds is not None else self._seeds
        timesteps = []
        for index, (env, seed) in enumerate(zip(self.envs, self._seeds)):
            try:
                timesteps.append(env.reset(seed))
            except SimulatorCrash as crash:
                timesteps.append(self._restart(index, str(crash)))
        return stack(timesteps)

    def step(self, actions: np.ndarray, reset: np.ndarray | None = None) -> HostBatch:
        """Step environment i with `actions[i]`, starting its next episode if this one ends
        unless `reset[i]` is False (`HostEnv.step`); one whose simulator crashes is restarted
        (module doc)."""
        timesteps = []
        for index, env in enumerate(self.envs):
            try:
                timesteps.append(env.step(actions[index],
                                          True if reset is None else bool(reset[index])))
                self._in_a_row[index] = 0
            except SimulatorCrash as crash:
                timesteps.append(self._restart(index, str(crash)))
        return stack(timesteps)

    def counters(self) -> dict[str, np.ndarray]:
        """Per slot: restarts so far and non-finite values replaced by 0 (`COUNTERS`)."""
        replaced = [env.nonfinite_replaced for env in self.envs]
        return {"env_restarts": self._restarts.copy(),
                "env_nonfinite": self._replaced_before + np.asarray(replaced, np.int64)}

    def _restart(self, index: int, reason: str) -> HostStep:
        """Rebuild and reset environment `index` until it starts, or `crash_limit` crashes in a
        row (CmatError)."""
        while True:
            self._restarts[index] += 1
            self._in_a_row[index] += 1
            if self._in_a_row[index] >= self.crash_limit:
                raise CmatError(
                    f"{self.env_id}: environment {index} crashed {self._in_a_row[index]} times in "
                    f"a row (last: {reason}); stopped (host_crash_limit={self.crash_limit})"
                )
            log.warning("%s: environment %d crashed (%s); restarted it, its episode counts as "
                        "truncated", self.env_id, index, reason)
            self._replaced_before[index] += self.envs[index].nonfinite_replaced
            with contextlib.suppress(Exception):  # a broken simulator may fail to close too
                self.envs[index].close()
            self.envs[index] = self._make(index)
            seed = self._seeds[index] + RESTART_SEED_STRIDE * int(self._restarts[index])
            try:
                timestep = self.envs[index].reset(seed)
            except SimulatorCrash as crash:
                reason = str(crash)
                continue
            return timestep._replace(reward=0.0, done=True, won=False)

    def close(self) -> None:
        """Close every environment."""
        for env in self.envs:
            with contextlib.suppress(Exception):
                env.close()
        self.envs = []


def worker_main(conn: multiprocessing.connection.Connection, env_id: str,
                env_kwargs: dict[str, Any], seeds: list[int], crash_limit: int,
                nonfinite: str, reference: dict[str, Any] | None, first_slot: int) -> None:
    """A worker process: an `InProcessPool` of one environment per seed serving its parent
    (which first gets ("ready", the pool's reference description)). Each reply is ("ok", batch,
    counters), ("error", a CmatError's message) or ("bug", a traceback)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and closes us
    try:
        pool = InProcessPool(env_id, env_kwargs, seeds, crash_limit=crash_limit,
                             nonfinite=nonfinite, reference=reference, first_slot=first_slot)
    except CmatError as error:
        conn.send(("error", str(error)))
        return
    except Exception as error:
        conn.send(("error", f"{env_id}: a worker could not build its environments "
                            f"({type(error).__name__}: {error})"))
        return
    conn.send(("ready", pool.reference))
    while True:
        try:
            command, data = conn.recv()
        except (EOFError, OSError):  # the parent exited without closing us
            break
        if command not in ("step", "reset"):
            break
        try:
            batch = pool.step(*data) if command == "step" else pool.reset(data)
            reply: tuple[Any, ...] = ("ok", batch, pool.counters())
        except CmatError as error:
            reply = ("error", str(error))
        except Exception:
            reply = ("bug", traceback.format_exc())
        try:
            conn.send(reply)
        except (EOFError, OSError):
            break
    pool.close()
    conn.close()


class Worker:
    """One worker process and the slice of environment slots it holds."""

    def __init__(self, env_id: str, env_kwargs: dict[str, Any], slots: slice,
                 seeds: list[int], crash_limit: int, nonfinite: str,
                 reference: dict[str, Any] | None) -> None:
        context = multiprocessing.get_context("spawn")
        self.slots = slots
        self.counters = {name: np.zeros(slots.stop - slots.start, np.int64) for name in COUNTERS}
        """The worker's last reported `InProcessPool.counters()`."""
        self.conn, child = context.Pipe()
        self.process = context.Process(
            target=worker_main, daemon=True,
            args=(child, env_id, env_kwargs, seeds, crash_limit, nonfinite, reference,
                  slots.start),
        )
        self.process.start()
        child.close()
        try:
            status, message = self.conn.recv()
        except (EOFError, OSError):
            status, message = "error", (f"{env_id}: a worker could not build its environments "
                                        f"(worker exited with code {self.process.exitcode})")
        if status != "ready":
            self.stop()
            raise CmatError(message)
        self.reference: dict[str, Any] = message
        """The description every environment of the pool must match (`check_alike`)."""

    def stop(self) -> None:
        """Ask the worker to close; kill it if it does not."""
        with contextlib.suppress(OSError, ValueError):
            self.conn.send(("close", None))
        self.process.join(timeout=5)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.conn.close()


class WorkerPool:
    """One environment per seed, split over `workers` processes that step their slices at once;
    each environment must match `reference` (default: the first one built; `check_alike`)."""

    def __init__(self, env_id: str, env_kwargs: dict[str, Any], seeds: list[int],
                 workers: int, crash_limit: int = DEFAULT_CRASH_LIMIT,
                 nonfinite: str = "error", reference: dict[str, Any] | None = None) -> None:
        self.env_id = env_id
        self.env_kwargs = dict(env_kwargs)
        self.crash_limit = crash_limit
        self.nonfinite = nonfinite
        self._seeds = list(seeds)
        count = len(seeds)
        bounds = np.linspace(0, count, min(workers, count) + 1).round().astype(int)
        slots = [slice(int(a), int(b)) for a, b in itertools.pairwise(bounds)]
        self.reference = reference
        self.workers: list[Worker] = []
        try:
            for s in slots:
                self.workers.append(self._worker(s, self._seeds[s]))
        except CmatError:
            self.close()
            raise
        self._restarts = 0
        self._lost = {name: np.zeros(count, np.int64) for name in COUNTERS}
        """Counters of dead workers' environments, and their environments restarted."""
        self.spec: EnvSpec | None = None

    def _worker(self, slots: slice, seeds: list[int]) -> Worker:
        worker = Worker(self.env_id, self.env_kwargs, slots, seeds, self.crash_limit,
                        self.nonfinite, self.reference)
        self.reference = self.reference or worker.reference
        return worker

    def reset(self, seeds: list[int] | None = None) -> HostBatch:
        """Start an episode in every environment, environment i with `seeds[i]` (default: the
        pool's seeds)."""
        self._seeds = list(seeds) if seeds is not None else self._seeds
        return self._all("reset", lambda w: self._seeds[w.slots])

    def step(self, actions: np.ndarray, reset: np.ndarray | None = None) -> HostBatch:
        """Step environment i with `actions[i]` (`InProcessPool.step`); a dead worker is
        replaced (module doc)."""
        return self._all("step", lambda w: (actions[w.slots],
                                            None if reset is None else reset[w.slots]))

    def counters(self) -> dict[str, np.ndarray]:
        """Per slot: restarts so far (inside workers and of dead workers) and non-finite values
        replaced by 0 (`COUNTERS`)."""
        return {name: self._lost[name] + np.concatenate([w.counters[name] for w in self.workers])
                for name in COUNTERS}

    def _all(self, command: str, data: Any) -> HostBatch:
        sent = []
        for worker in self.workers:
            try:
                worker.conn.send((command, data(worker)))
                sent.append(True)
            except (OSError, ValueError):
                sent.append(False)
        replies = []
        for index, worker in enumerate(self.workers):
            try:
                if not sent[index]:
                    raise EOFError
                replies.append(worker.conn.recv())
            except (EOFError, OSError):
                replies.append(self._restart(index))
        results = []
        for worker, reply in zip(self.workers, replies):
            if reply[0] == "error":
                raise CmatError(reply[1])
            if reply[0] == "bug":
                raise RuntimeError(f"a host environment worker raised:\n{reply[1]}")
            results.append(reply[1])
            worker.counters = reply[2]
        return concatenate(results)

    def _restart(self, index: int) -> tuple[Any, ...]:
        """A fresh worker in place of dead worker `index`, its environments reset: the reply of
        the command it did not answer, with every episode done."""
        old = self.workers[index]
        old.process.join(timeout=1)
        code = old.process.exitcode
        old.stop()
        count = old.slots.stop - old.slots.start
        for name in COUNTERS:
            self._lost[name][old.slots] += old.counters[name]
        self._lost["env_restarts"][old.slots] += 1
        self._restarts += 1
        log.warning(
            "%s: worker process %d died (exit code %s); restarted it, the episodes of its %d "
            "environments count as truncated", self.env_id, index, code, count,
        )
        seeds = [s + RESTART_SEED_STRIDE * self._restarts for s in self._seeds[old.slots]]
        worker = self._worker(old.slots, seeds)
        self.workers[index] = worker
        worker.conn.send(("reset", seeds))
        reply: tuple[Any, ...] = worker.conn.recv()
        if reply[0] != "ok":
            return reply
        batch: HostBatch = reply[1]
        return ("ok", batch._replace(
            reward=np.zeros_like(batch.reward), done=np.ones_like(batch.done),
            won=np.zeros_like(batch.won),
        ), reply[2])

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
    envs: list[HostEnv] | None = None, crash_limit: int = DEFAULT_CRASH_LIMIT,
    nonfinite: str = "error", reference: dict[str, Any] | None = None,
) -> InProcessPool | WorkerPool:
    """One environment per seed, in this process (`workers` = 0) or over `workers` processes;
    `envs` are already built environments an in-process pool starts with (a worker pool closes
    them); `crash_limit` and `nonfinite` as `TrainConfig.host_crash_limit` and
    `host_nonfinite`; every environment must match `reference` (default: the first of `envs`,
    else the first one built; `check_alike`)."""
    reference = reference or (envs[0].description() if envs else None)
    if workers <= 0:
        return InProcessPool(env_id, env_kwargs, seeds, envs, crash_limit, nonfinite, reference)
    for env in envs or []:
        env.close()
    return WorkerPool(env_id, env_kwargs, seeds, workers, crash_limit, nonfinite, reference)
