"""Milliseconds per parameter initialisation of a run's learner, with the process's OpenBLAS at
its default thread count and limited to one thread (`cmat.runners.base.single_threaded_lapack`),
on an idle machine and beside processes that keep every core busy.

    python benchmarks/init_time.py [--env smax:3s5z_vs_3s6z] [--algo cmat] [--busy 2] [--repeats 5]

The initialisation is the compiled program `JaxTrainer.init` runs once per seed (orthogonal
initialisers, hence LAPACK QR calls from XLA's threads). `--busy N` starts N processes that
spin for the duration of the loaded measurements, as a second run or a test worker would on
this machine. Compile time is excluded (one call first).
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import time
from collections.abc import Callable, Iterator
from typing import Any

import jax

from cmat.resolve import load_config
from cmat.runners.base import seed_keys, single_threaded_lapack
from cmat.runners.trainer import build_setup, init_state


def spin(stop: Any) -> None:
    while not stop.is_set():
        pass


@contextlib.contextmanager
def busy_cores(processes: int) -> Iterator[None]:
    context = multiprocessing.get_context("spawn")
    stop = context.Event()
    workers = [context.Process(target=spin, args=(stop,)) for _ in range(processes)]
    for worker in workers:
        worker.start()
    try:
        yield
    finally:
        stop.set()
        for worker in workers:
            worker.join()


def milliseconds_per_init(init: Callable[[jax.Array], Any], key: jax.Array, repeats: int,
                          limited: bool) -> float:
    context = single_threaded_lapack() if limited else contextlib.nullcontext()
    with context:
        start = time.perf_counter()
        for _ in range(repeats):
            jax.block_until_ready(init(key))
    return (time.perf_counter() - start) / repeats * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="smax:3s5z_vs_3s6z")
    parser.add_argument("--algo", default="cmat")
    parser.add_argument("--busy", type=int, default=2, help="spinning processes, loaded rows")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    config = load_config(overrides=[f"env={args.env}", f"algo={args.algo}"])
    setup = build_setup(config)
    init = jax.jit(lambda rng: init_state(setup, rng))
    key = seed_keys(config)[0]
    jax.block_until_ready(init(key))
    print(f"{args.algo} on {args.env}, ms per initialisation (mean of {args.repeats})")
    print("| machine | OpenBLAS default threads | one thread | ratio |")
    print("|---|---|---|---|")
    for label, busy in (("idle", 0), (f"{args.busy} spinning processes", args.busy)):
        with busy_cores(busy):
            default = milliseconds_per_init(init, key, args.repeats, limited=False)
            single = milliseconds_per_init(init, key, args.repeats, limited=True)
        print(f"| {label} | {default:.1f} | {single:.1f} | {default / single:.1f} |")


if __name__ == "__main__":
    main()
