"""Where the compiled PPO update spends its time: per-operation times of one update on CPU.

    python benchmarks/update_profile.py                          # CMAT, SMAX 6h_vs_8z
    python benchmarks/update_profile.py --algo mat --top 25
    python benchmarks/update_profile.py --set network.compute_dtype=bfloat16

Collects one rollout with the algorithm's own config for `--env`, compiles `learn` (target-critic
GAE, every epoch and minibatch of the algorithm's update, the target critic's soft update) on that
fixed rollout, runs it once to warm up, then `--repeats` times under `jax.profiler.trace`. The
trace's per-operation events (XLA's CPU runtime records one per executed thunk: a fusion, a dot,
a loop) are summed by operation, and the top `--top` are printed with their share of the update's
wall time, grouped into kinds (dot, convolution, fusion, loop control, copy, other) and listed
with the HLO of the fusion where one is named. Also printed: XLA's FLOP count of the update and
its achieved FLOP/s.
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


def operation_kind(name: str) -> str:
    lowered = name.lower()
    for kind in ("dot", "convolution", "fusion", "while", "conditional", "copy", "transpose",
                 "reduce", "sort", "custom-call", "all-reduce"):
        if kind in lowered:
            return kind
    return "other"


def trace_events(directory: Path) -> list[dict]:
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
    args = parser.parse_args()

    import jax

    from cmat.resolve import load_config
    from cmat.runners import trainer
    from cmat.runners.learner import learn

    config = load_config(overrides=[f"env={args.env}", f"algo={args.algo}", *args.set])
    setup = trainer.build_setup(config)
    state = trainer.init_state(setup, jax.random.PRNGKey(0))
    _, rollout = jax.jit(setup.collector.collect)(state.learner.params, state.envs,
                                                  jax.random.PRNGKey(1))
    update = jax.jit(lambda learner, rollout: learn(setup.learner, learner, rollout))
    compiled = update.lower(state.learner, rollout).compile()
    flops = float((compiled.cost_analysis() or {}).get("flops", float("nan")))
    jax.block_until_ready(compiled(state.learner, rollout))
    with tempfile.TemporaryDirectory() as directory:
        with jax.profiler.trace(directory, create_perfetto_trace=True):
            start = time.perf_counter()
            for _ in range(args.repeats):
                jax.block_until_ready(compiled(state.learner, rollout))
            wall = (time.perf_counter() - start) / args.repeats
        events = trace_events(Path(directory))
    totals: collections.Counter[str] = collections.Counter()
    counts: collections.Counter[str] = collections.Counter()
    for event in events:
        name = event["name"]
        if re.match(r"^(PjitFunction|PjRt|Execute|Thunk|jit_|TfrtCpu|\$)", name):
            continue
        totals[name] += event["dur"] / 1e6 / args.repeats
        counts[name] += 1
    measured = sum(totals.values())
    print(f"{args.algo} on {args.env}: one update {wall:.3f} s "
          f"({config.steps_per_update / wall:.0f} env steps/s for the update alone); "
          f"{flops / 1e9:.2f} GFLOP, {flops / wall / 1e9:.1f} GFLOP/s; "
          f"{len(totals)} operations, {measured:.3f} s of events per update "
          f"(thread time; above the wall time where threads overlap)")
    kinds: collections.Counter[str] = collections.Counter()
    for name, seconds in totals.items():
        kinds[operation_kind(name)] += seconds
    print("by kind: " + ", ".join(f"{kind} {seconds / measured:.0%}"
                                  for kind, seconds in kinds.most_common()))
    print(f"{'share':>6} {'s/update':>9} {'calls':>7}  operation")
    for name, seconds in totals.most_common(args.top):
        print(f"{seconds / measured:>6.1%} {seconds:>9.4f} {counts[name] // args.repeats:>7}  "
              f"{name[:110]}")


if __name__ == "__main__":
    main()
