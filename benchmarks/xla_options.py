"""Training time per update under other XLA compile options, in one process.

    python benchmarks/xla_options.py --env smax:6h_vs_8z --algo cmat --rounds 10 \
        --variant 'xla:{}' \
        --variant 'ynn-dots:{"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_DOT"}'

Compiles the program that trains (`cmat.runners.trainer.run_updates`, one update per call,
vmapped over the run's seeds, its state donated) once with the options cmat uses
(`cmat.runners.devices.compiler_options`, the baseline "cmat") and once per `--variant
NAME:JSON` with exactly the options in JSON (`{}`: XLA's defaults), each on its own copy of the
state, then times one update of each in rotation for `--rounds` rounds. Programs that share a
process and alternate see the same machine, so the per-round ratios (baseline time / variant
time: above 1 means the variant is faster) are less noisy than separate processes. Option names
are XLA's DebugOptions fields; an unknown name or value fails that variant with XLA's message.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from cmat.algorithms import algorithm_entry
from cmat.resolve import load_config
from cmat.runners.devices import compiler_options
from cmat.runners.trainer import JaxTrainer, run_updates


def parse_variant(text: str) -> tuple[str, dict[str, Any]]:
    """'NAME:JSON' -> (NAME, options)."""
    name, _, options = text.partition(":")
    try:
        parsed = json.loads(options)
    except json.JSONDecodeError as error:
        raise argparse.ArgumentTypeError(
            f"--variant {text!r}: options are not JSON ({error})") from None
    if not name or not isinstance(parsed, dict):
        raise argparse.ArgumentTypeError(f"--variant {text!r}: expected NAME:{{...}}")
    return name, parsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="smax:6h_vs_8z")
    parser.add_argument("--algo", default="cmat")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--variant", type=parse_variant, action="append", default=[],
                        help="NAME:JSON, the compile options of one variant")
    parser.add_argument("--set", nargs="*", default=[], help="config overrides KEY=VALUE")
    args = parser.parse_args()

    config = load_config(overrides=[f"env={args.env}", f"algo={args.algo}", "log_interval=1",
                                    *args.set])
    trainer = JaxTrainer(config)
    one_update = jax.vmap(lambda state, updates: run_updates(trainer.setup, state, 1, updates),
                          in_axes=(0, None))
    performed = jnp.int32(1)
    programs: dict[str, Any] = {}
    states: dict[str, Any] = {}
    ours = compiler_options(algorithm_entry(config.algo).ynnpack_matmuls)
    for name, options in [("cmat", ours), *args.variant]:
        state = trainer.init()
        started = time.perf_counter()
        try:
            programs[name] = (jax.jit(one_update, donate_argnums=0, compiler_options=options)
                              .lower(state, performed).compile())
        except jax.errors.JaxRuntimeError as error:
            print(f"{name}: not compiled ({str(error).splitlines()[0]})")
            continue
        print(f"{name}: {options} compiled in {time.perf_counter() - started:.0f} s", flush=True)
        states[name], _ = programs[name](state, performed)
        jax.block_until_ready(states[name])

    seconds: dict[str, list[float]] = {name: [] for name in programs}
    names = list(programs)
    for round_index in range(args.rounds):
        shift = round_index % len(names)
        for name in names[shift:] + names[:shift]:
            started = time.perf_counter()
            states[name], _ = programs[name](states[name], performed)
            jax.block_until_ready(states[name])
            seconds[name].append(time.perf_counter() - started)

    steps = config.steps_per_update * config.seeds
    baseline = np.array(seconds["cmat"])
    print(f"\n{args.env} {args.algo}, {args.rounds} rounds, {steps} env steps per update")
    print(f"{'variant':16s} {'s/update':>9s} {'steps/s':>8s}  cmat/variant median [range]")
    for name in names:
        mine = np.array(seconds[name])
        ratios = baseline / mine
        print(f"{name:16s} {np.median(mine):9.3f} {steps / np.median(mine):8.0f}  "
              f"{np.median(ratios):.3f} [{ratios.min():.3f}, {ratios.max():.3f}]")


if __name__ == "__main__":
    main()
