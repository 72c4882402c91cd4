"""Where the compiled PPO update spends its time: per-operation times of one update on CPU.

    python benchmarks/update_profile.py                          # CMAT, SMAX 6h_vs_8z
    python benchmarks/update_profile.py --algo mat --top 25
    python benchmarks/update_profile.py --set ppo.epochs=5 --program training
    python benchmarks/update_profile.py --env smax:50m --set num_envs=8 rollout_length=25 \
        --dump DIR

Collects one rollout with the algorithm's own config for `--env`, compiles `learn` (target-critic
GAE, every epoch and minibatch of the algorithm's update, the target critic's soft update) on that
fixed rollout with the trainers' compile options (`cmat.runners.devices.compiler_options`), runs it
once to warm up, then `--repeats` times under `jax.profiler.trace`. The trace's per-operation
events (XLA's CPU runtime records one per executed thunk) are matched to the optimised HLO's
instructions and summed: by kind (plain matmuls, batched matmuls, fusions that contain either,
elementwise fusions, other opcodes), by network part (forward or backward pass of a network module,
from the instructions' metadata), elementwise fusions by output shape, and the top `--top`
operations; `--dump DIR` also writes the optimised HLO and every operation's time. Shares are of
the operations' busy time; its ratio to the wall time is the average number of threads at work.
Also printed: XLA's FLOP count of the update and its achieved FLOP/s.

`--program training` profiles the program that trains instead: `cmat.runners.trainer.JaxTrainer`'s
chunk of one update (collection and update, vmapped over the run's seeds, inside the chunk's
scan), called on its own state, so XLA's choices there can be compared with `learn` alone.
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import re
import tempfile
import time
from pathlib import Path
from typing import Any


def network_part(op_name: str) -> str:
    """The pass and network part an instruction's `op_name` metadata names, such as "backward
    decoder/DecoderBlock_0.step": the first two module names after the network's class (a
    capitalised Flax module name in parentheses); "other" outside the network (losses, GAE,
    optimizer, unnamed fusions)."""
    match = re.search(r"\([A-Z]\w*(?:\.\w+)?\)+((?:/[\w.]+){1,2})", op_name)
    if not match:
        return "other"
    direction = "backward" if "transpose(" in op_name else "forward"
    return f"{direction} {match.group(1).lstrip('/')}"


def hlo_operations(hlo: str) -> dict[str, tuple[str, str, str]]:
    """Each instruction of the optimised HLO text: name -> (kind, output shape, network part
    from `network_part`). Kinds: a dot with batch dimensions ("batched dot"), a plain one
    ("matmul"), a fusion that contains either ("fused batched dot", "fused matmul"), any other
    fusion ("elementwise fusion"), or the instruction's opcode."""
    bodies: dict[str, str] = {}
    current = None
    for line in hlo.splitlines():
        header = re.match(r"^%?([\w.\-]+) .*\{\s*$", line)
        if header and not line.startswith(" "):
            current = header.group(1)
            bodies[current] = ""
        elif current is not None and line.strip() == "}":
            current = None
        elif current is not None:
            bodies[current] += line + "\n"
    operations = {}
    for line in hlo.splitlines():
        match = re.match(r"\s*(?:ROOT )?%?([\w.\-]+) = (\S+) ([\w\-]+)\(", line)
        if not match:
            continue
        name, shape, opcode = match.groups()
        shape = re.sub(r"\{.*", "", shape)
        op_name = re.search(r'op_name="([^"]*)"', line)
        part = network_part(op_name.group(1)) if op_name else "other"
        if opcode == "dot":
            kind = "batched dot" if "lhs_batch_dims" in line else "matmul"
        elif opcode == "fusion":
            called = re.search(r"calls=%?([\w.\-]+)", line)
            body = bodies.get(called.group(1), "") if called else ""
            kind = (("fused batched dot" if "lhs_batch_dims" in body else "fused matmul")
                    if " dot(" in body else "elementwise fusion")
        else:
            kind = opcode
        operations[name] = (kind, shape, part)
    return operations


def trace_events(directory: Path) -> list[dict[str, Any]]:
    """The complete events ("ph": "X") of the perfetto trace jax.profiler wrote under
    `directory`."""
    paths = sorted(directory.rglob("*.trace.json.gz"))
    if not paths:
        raise SystemExit(f"no trace written under {directory}")
    with gzip.open(paths[-1], "rt") as file:
        data = json.load(file)
    events = data["traceEvents"] if isinstance(data, dict) else data
    return [e for e in events if e.get("ph") == "X" and "dur" in e]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="smax:6h_vs_8z")
    parser.add_argument("--algo", default="cmat")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--top", type=int, default=20)
    parser.add_argument("--set", nargs="*", default=[], help="config overrides")
    parser.add_argument("--program", choices=["update", "training"], default="update",
                        help="update: `learn` alone on a fixed rollout; training: the program "
                             "that trains (one chunk of one update: collection, update, vmapped "
                             "over seeds, inside the chunk's scan)")
    parser.add_argument("--dump", type=Path, default=None,
                        help="write the optimised HLO (update.hlo) and every operation's seconds "
                             "per update (operations.json) into this folder")
    args = parser.parse_args()

    import jax

    from cmat.algorithms import algorithm_entry
    from cmat.errors import CmatError
    from cmat.resolve import load_config
    from cmat.runners import trainer
    from cmat.runners.devices import compiler_options
    from cmat.runners.learner import learn

    try:
        config = load_config(
            overrides=[f"env={args.env}", f"algo={args.algo}", *args.set, "log_interval=1"])
        setup = trainer.build_setup(config)
    except CmatError as error:
        parser.error(str(error))
    if args.program == "training":
        runner = trainer.JaxTrainer(config)
        state = runner.init()
        one = jax.numpy.asarray(1, jax.numpy.int32)
        compiled = runner.compile_chunk(state)

        def run_once() -> Any:
            nonlocal state
            state, _ = compiled(state, one)
            return state
    else:
        fresh = trainer.init_state(setup, jax.random.PRNGKey(0))
        _, rollout = jax.jit(setup.collector.collect)(fresh.learner.params, fresh.envs,
                                                      jax.random.PRNGKey(1))
        update = jax.jit(
            lambda learner, rollout: learn(setup.learner, learner, rollout),
            compiler_options=compiler_options(algorithm_entry(config.algo).ynnpack_matmuls),
        )
        compiled = update.lower(fresh.learner, rollout).compile()

        def run_once() -> Any:
            return compiled(fresh.learner, rollout)
    flops = float((compiled.cost_analysis() or {}).get("flops", float("nan")))
    jax.block_until_ready(run_once())
    with tempfile.TemporaryDirectory() as directory:
        with jax.profiler.trace(directory, create_perfetto_trace=True):
            start = time.perf_counter()
            for _ in range(args.repeats):
                jax.block_until_ready(run_once())
            wall = (time.perf_counter() - start) / args.repeats
        events = trace_events(Path(directory))
    operations = hlo_operations(compiled.as_text() or "")
    totals: collections.Counter[str] = collections.Counter()
    counts: collections.Counter[str] = collections.Counter()
    threads: collections.Counter[Any] = collections.Counter()
    unmatched: collections.Counter[str] = collections.Counter()
    for event in events:
        seconds = event["dur"] / 1e6 / args.repeats
        if event["name"] in operations:
            totals[event["name"]] += seconds
            counts[event["name"]] += 1
            threads[event.get("tid")] += seconds
        else:
            unmatched[event["name"]] += seconds
    measured = sum(totals.values())
    if args.dump is not None:
        args.dump.mkdir(parents=True, exist_ok=True)
        (args.dump / "update.hlo").write_text(compiled.as_text() or "")
        (args.dump / "operations.json").write_text(json.dumps(
            {name: {"kind": operations[name][0], "shape": operations[name][1],
                    "part": operations[name][2],
                    "seconds": seconds, "calls": counts[name] // args.repeats}
             for name, seconds in totals.most_common()}, indent=1))
    what = ("one training chunk of one update" if args.program == "training"
            else "one update alone")
    steps = config.steps_per_update * (config.seeds if args.program == "training" else 1)
    print(f"{args.algo} on {args.env} ({' '.join(args.set) or 'its defaults'}): {what} "
          f"{wall:.3f} s ({steps / wall:.0f} env steps/s); "
          f"{flops / 1e9:.2f} GFLOP, {flops / wall / 1e9:.1f} GFLOP/s; operations "
          f"busy {measured:.3f} s per update ({measured / wall:.2f} threads on average)")
    print("operations' busy seconds by thread: " + ", ".join(
        f"{seconds:.3f}" for _, seconds in threads.most_common(8)))
    print("other trace events (not an instruction of the program; nested, so they overlap): "
          + ", ".join(f"{name} {seconds:.3f} s" for name, seconds in unmatched.most_common(6)))
    kinds: collections.Counter[str] = collections.Counter()
    parts: collections.Counter[str] = collections.Counter()
    elementwise: collections.Counter[str] = collections.Counter()
    for name, seconds in totals.items():
        kind, shape, part = operations[name]
        kinds[kind] += seconds
        parts[part] += seconds
        if kind == "elementwise fusion":
            elementwise[shape] += seconds
    print("by kind: " + ", ".join(f"{kind} {seconds / measured:.0%}"
                                  for kind, seconds in kinds.most_common()))
    print("by network part: " + ", ".join(f"{part} {seconds / measured:.1%}"
                                          for part, seconds in parts.most_common(12)))
    print("elementwise fusions by output shape: " + ", ".join(
        f"{shape} {seconds / measured:.1%}" for shape, seconds in elementwise.most_common(8)))
    print(f"{'share':>6} {'s/update':>9} {'calls':>6}  operation")
    for name, seconds in totals.most_common(args.top):
        kind, shape, _ = operations[name]
        print(f"{seconds / measured:>6.1%} {seconds:>9.4f} {counts[name] // args.repeats:>6}  "
              f"{name} ({kind}, {shape})")


if __name__ == "__main__":
    main()
