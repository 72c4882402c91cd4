"""The machine a benchmark ran on, in one line, so that every printed figure carries it.

    python benchmarks/machine.py             # CPU, cores, memory, JAX and a large matmul's FLOP/s

The kind of machine this project runs on has changed CPU generation between sessions (docs/speed.md,
"The machine": a 2048² fp32 matmul at about 170 GFLOP/s on one, 530 on the next), so steps/s from
different days compare only through the line each benchmark prints with them.
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path


def cpu_model() -> str:
    """'MODEL NAME (family F, model M)' from /proc/cpuinfo, or the platform's processor name
    where there is no /proc/cpuinfo."""
    fields: dict[str, str] = {}
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or platform.machine()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    name = fields.get("model name", platform.machine())
    if "cpu family" in fields:
        return f"{name} (family {fields['cpu family']}, model {fields.get('model', '?')})"
    return name


def memory_gib() -> float | None:
    """Total memory in GiB, or None where the platform does not say."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        return None


def matmul_gflops(size: int = 2048, repeats: int = 5) -> float:
    """The fastest of `repeats` jitted float32 [size, size] matmuls on JAX's default device,
    in GFLOP/s."""
    import jax

    a = jax.random.normal(jax.random.PRNGKey(0), (size, size))
    product = jax.jit(lambda x: x @ x)
    jax.block_until_ready(product(a))
    fastest = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(product(a))
        fastest = min(fastest, time.perf_counter() - start)
    return 2 * size**3 / fastest / 1e9


def describe(with_matmul: bool = True) -> str:
    """One line: CPU model, logical CPUs, memory, and unless `with_matmul` is False the JAX
    version and device and a large matmul's GFLOP/s. A process that only starts others passes
    False: it then never imports JAX, which on a GPU would claim most of the GPU's memory."""
    memory = memory_gib()
    parts = [cpu_model(), f"{os.cpu_count()} CPUs"]
    if memory is not None:
        parts.append(f"{memory:.1f} GiB")
    if with_matmul:
        import jax

        device = jax.devices()[0]
        parts.append(f"jax {jax.__version__} on {device.platform} ({device.device_kind})")
        parts.append(f"2048² fp32 matmul {matmul_gflops():.0f} GFLOP/s")
    return "machine: " + "; ".join(parts)


if __name__ == "__main__":
    print(describe())
