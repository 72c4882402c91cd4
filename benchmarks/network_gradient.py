"""The cost of one gradient of CMAT's and MAT's networks as the team grows: compile seconds,
milliseconds per gradient and XLA's temporary buffer size.

    python benchmarks/network_gradient.py [--agents 25 50 100] [--algos cmat mat] [--batch 200]

The gradient is what the PPO update repeats (epochs × minibatches), and CMAT's decoder is the
part that grows with m = n: it unrolls m iterations, each attending to the consensus vectors
before it. For each team size n and network: a jitted gradient of a scalar of the training
forward pass (CMAT: every agent's log-softmax and the value; MAT: the same from its
teacher-forced pass) on `--batch` teams of random observations (`--obs-dim` features per agent,
`--actions` discrete actions, the reference network config), compiled once (timed), run once to
warm up, then timed over `--repeats` calls. The temporary buffer size is XLA's own figure for
the compiled program (`memory_analysis().temp_size_in_bytes`), so it does not depend on the
machine's load; the times do, so compare lines of one run.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp

from cmat.algorithms.cmat.network import CMATNetwork
from cmat.algorithms.cmat.options import CMATOptions
from cmat.algorithms.mat.network import MATNetwork
from cmat.config import NetworkConfig


def gradient_cost(
    algo: str, agents: int, batch: int, obs_dim: int, actions: int, repeats: int
) -> tuple[float, float, float]:
    """(compile s, ms per gradient, temporary MiB) of one network's gradient."""
    config = NetworkConfig()
    obs = jax.random.normal(jax.random.PRNGKey(0), (batch, agents, obs_dim))
    mask = jnp.ones((batch, agents, actions), bool)
    if algo == "cmat":
        network = CMATNetwork(config, CMATOptions(), agents, actions, True)
        params = network.init(jax.random.PRNGKey(1), obs[0], mask[0])

        def team_loss(p: dict, o: jax.Array, m: jax.Array) -> jax.Array:
            out = network.apply(p, o, m)
            return jnp.sum(jax.nn.log_softmax(out.action_params)) + jnp.sum(out.value)
    else:
        network = MATNetwork(config, agents, actions, True)  # type: ignore[assignment]
        taken = jnp.zeros((agents,), jnp.int32)
        order = jnp.arange(agents)
        params = network.init(jax.random.PRNGKey(1), obs[0], mask[0], taken, order)

        def team_loss(p: dict, o: jax.Array, m: jax.Array) -> jax.Array:
            out = network.apply(p, o, m, taken, order)
            return jnp.sum(jax.nn.log_softmax(out.action_params)) + jnp.sum(out.agent_values)

    def loss(p: dict, o: jax.Array, m: jax.Array) -> jax.Array:
        return jnp.sum(jax.vmap(team_loss, in_axes=(None, 0, 0))(p, o, m))

    start = time.perf_counter()
    compiled = jax.jit(jax.grad(loss)).lower(params, obs, mask).compile()
    compile_seconds = time.perf_counter() - start
    temporary = compiled.memory_analysis().temp_size_in_bytes / 2**20
    jax.block_until_ready(compiled(params, obs, mask))
    start = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(compiled(params, obs, mask))
    return compile_seconds, (time.perf_counter() - start) / repeats * 1000, temporary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[25, 50, 100])
    parser.add_argument("--algos", nargs="+", choices=["cmat", "mat"], default=["cmat", "mat"])
    parser.add_argument("--batch", type=int, default=200, help="teams per gradient")
    parser.add_argument("--obs-dim", type=int, default=64)
    parser.add_argument("--actions", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"gradient of {args.batch} teams, reference network config, one process")
    print(f"{'algo':6} {'n':>4} {'compile s':>10} {'ms/grad':>9} {'temp MiB':>9}")
    for agents in args.agents:
        for algo in args.algos:
            compile_seconds, milliseconds, temporary = gradient_cost(
                algo, agents, args.batch, args.obs_dim, args.actions, args.repeats)
            print(f"{algo:6} {agents:>4} {compile_seconds:>10.1f} {milliseconds:>9.0f} "
                  f"{temporary:>9.0f}", flush=True)


if __name__ == "__main__":
    main()
