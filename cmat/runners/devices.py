"""Several local devices: a run's seeds, or else its environments, sharded across them.

`JaxTrainer` uses every device (`jax.devices()`: this process's; restrict them with
`CUDA_VISIBLE_DEVICES` or JAX's platform flags). Its state is placed with a `NamedSharding` over
a one-axis mesh of those devices: the seed axis (the leading axis of every leaf) when the
devices divide the number of seeds, else the environment axis of the in-graph environments
(axis 1 of the `envs` leaves) when they divide `num_envs`, else nothing (one device computes).
The jitted programs keep that placement, and XLA's SPMD partitioner adds the communication the
program needs: with the environments sharded, each device steps its share of them and the
update's means over the batch (the loss, hence the gradients) are reduced across devices. A run
on several devices therefore computes what it computes on one, up to floating-point order
(tests/test_devices.py). Host runs (`HostTrainer`) stay on one device.

In a run of several processes (cmat.runners.distributed) the mesh holds every process's devices
(`jax.devices()`); each process puts only its own shards (`put`), and reads results back with
`to_host`, which gathers what is spread over processes.

On CPU the trainers compile their programs with XLA options of their own (`compiler_options`).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from cmat.runners.base import TrainerState

AXIS = "devices"

YNNPACK_FUSIONS = "xla_cpu_experimental_ynn_fusion_type"
"""The XLA option that says which operations XLA's CPU backend hands to YNNPACK (by default in
jax 0.10: elementwise operations and reductions among them)."""
YNNPACK_MATMULS = "LIBRARY_FUSION_TYPE_DOT"
"""Its value for matmuls only."""

partition_spec: Callable[..., PartitionSpec] = PartitionSpec
"""`PartitionSpec`, whose constructor jax leaves untyped."""


def sharded_axis(devices: int, seeds: int, num_envs: int) -> str | None:
    """'seeds', 'envs' or None: what a run of `seeds` × `num_envs` shards over `devices`."""
    if devices <= 1:
        return None
    if seeds % devices == 0:
        return "seeds"
    if num_envs % devices == 0:
        return "envs"
    return None


def place(state: TrainerState, devices: list[Any], axis: str | None) -> TrainerState:
    """`state` put on `devices`, sharded over `axis` (`sharded_axis`); as it is for None."""
    if axis is None:
        return state
    mesh = Mesh(np.array(devices), (AXIS,))
    replicated = NamedSharding(mesh, partition_spec())
    by_seed = NamedSharding(mesh, partition_spec(AXIS))
    by_env = NamedSharding(mesh, partition_spec(None, AXIS))
    if axis == "seeds":
        shardings: Any = jax.tree.map(lambda _: by_seed, state)
    else:
        shardings = TrainerState(
            learner=jax.tree.map(lambda _: replicated, state.learner),
            envs=jax.tree.map(lambda _: by_env, state.envs),
        )
    placed: TrainerState = put(state, shardings)
    return placed


def put(tree: Any, shardings: Any) -> Any:
    """`jax.device_put(tree, shardings)`; where the shardings span several processes, each
    process makes its own shards from its copy of `tree`, which must hold the same values in
    every process."""
    if jax.process_count() == 1:
        return jax.device_put(tree, shardings)

    def global_array(leaf: Any, sharding: NamedSharding) -> jax.Array:
        values = np.asarray(leaf)
        return jax.make_array_from_callback(values.shape, sharding, lambda index: values[index])

    return jax.tree.map(global_array, tree, shardings)


def to_host(tree: Any) -> Any:
    """`tree` with every leaf a NumPy array. Arrays sharded over several processes are
    gathered from all of them: a collective, so every process of the run calls it at the same
    point of the same program."""
    leaves, treedef = jax.tree.flatten(tree)
    spread = [index for index, leaf in enumerate(leaves)
              if isinstance(leaf, jax.Array) and not leaf.is_fully_addressable]
    if spread:
        from jax.experimental import multihost_utils

        gathered = multihost_utils.process_allgather([leaves[i] for i in spread], tiled=True)
        for index, value in zip(spread, gathered, strict=True):
            leaves[index] = value
    return jax.tree.unflatten(treedef, [np.asarray(leaf) for leaf in leaves])


def compiler_options(ynnpack_matmuls: bool = False) -> dict[str, str]:
    """`jax.jit(..., compiler_options=...)` for the trainers' programs on CPU: no elementwise or
    reduction fusions through YNNPACK, and matmuls through YNNPACK where `ynnpack_matmuls` (the
    hint of the algorithm's entry, `AlgorithmEntry.ynnpack_matmuls`), else through XLA's own
    kernels. Nothing where JAX computes on another platform, where the installed XLA does not
    know the option or value, or where the user's `XLA_FLAGS` set YNNPACK's fusions themselves
    (their choice wins).
    Training steps/s against XLA's defaults: docs/speed.md; the measurements in
    benchmarks/results/speed_notes_2026-12-05.md ("YNNPACK fusions")."""
    return dict(_cpu_compiler_options(ynnpack_matmuls))


@functools.cache
def _cpu_compiler_options(ynnpack_matmuls: bool) -> tuple[tuple[str, str], ...]:
    if jax.default_backend() != "cpu" or "ynn_fusion_type" in os.environ.get("XLA_FLAGS", ""):
        return ()
    for value in (YNNPACK_MATMULS, "") if ynnpack_matmuls else ("",):
        try:
            jax.jit(lambda x: x + 1, compiler_options={YNNPACK_FUSIONS: value})(np.float32(0))
        except jax.errors.JaxRuntimeError:  # an XLA without the option or the value
            continue
        return ((YNNPACK_FUSIONS, value),)
    return ()
