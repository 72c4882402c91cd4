"""`ppo.minibatch_chunks`: a minibatch's gradient from sequential slices (accumulated where the
loss is a plain mean over samples, else the network pass recomputed slice by slice) is the
same loss and gradient with less activation memory, and configs that cannot use it are
refused."""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.flatten_util
import numpy as np
import pytest
from test_cmat_options import batch_for

from cmat.algorithms import algorithm_options, build_algorithm
from cmat.algorithms.cmat.options import CMATOptions
from cmat.algorithms.sgd import minibatch_gradient
from cmat.config import NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.errors import CmatError
from cmat.resolve import load_config

DISCRETE = EnvSpec("test", 4, 5, 3, True, 10, False)
CONTINUOUS = EnvSpec("test", 4, 5, 3, False, 10, False)

pytestmark = pytest.mark.quick_compiles


def own(algo: str, **fields: object):
    """`algo`'s section with those of `fields` it has (m = 2 for CMAT's tests)."""
    cls = algorithm_options(algo)
    names = set(cls.__dataclass_fields__)
    return cls(**{k: v for k, v in {"consensus_iterations": 2, **fields}.items() if k in names})


@pytest.mark.parametrize("algo, spec, network", [
    ("cmat", CONTINUOUS, {"consensus_policy": "categorical"}),
    ("pmat", CONTINUOUS, {}),
    pytest.param("cmat", DISCRETE, {}, marks=pytest.mark.slow),
    pytest.param("mat", DISCRETE, {}, marks=pytest.mark.slow),
    pytest.param("triple_bert", CONTINUOUS, {}, marks=pytest.mark.slow),
])
def test_chunked_minibatch_gives_the_same_loss_and_gradient(algo, spec, network) -> None:
    config = NetworkConfig(n_embd=8, init_gain=1.0)
    algorithm = build_algorithm(algo, config, spec, options=own(algo, **network))
    params, batch = batch_for(algorithm)

    def loss_and_grad(chunks: int):
        ppo = dataclasses.replace(PPOConfig(), minibatch_chunks=chunks)
        return jax.jit(jax.value_and_grad(lambda p: algorithm.loss(p, batch, ppo), has_aux=True))(
            params)

    (whole, whole_metrics), whole_grad = loss_and_grad(1)
    (chunked, chunked_metrics), chunked_grad = loss_and_grad(4)
    assert float(chunked) == pytest.approx(float(whole), rel=1e-5, abs=1e-7)
    for name in ("policy_loss", "value_loss", "entropy"):
        assert float(chunked_metrics[name]) == pytest.approx(
            float(whole_metrics[name]), rel=1e-5, abs=1e-7)
    flat_whole, _ = jax.flatten_util.ravel_pytree(whole_grad)
    flat_chunked, _ = jax.flatten_util.ravel_pytree(chunked_grad)
    scale = float(np.abs(flat_whole).max())
    assert scale > 0
    np.testing.assert_allclose(flat_chunked, flat_whole, rtol=1e-4, atol=1e-5 * scale)


@pytest.mark.optimised  # XLA's buffer assignment after its optimisations is what is measured
@pytest.mark.parametrize("active_masks", [True, False], ids=["recomputed", "accumulated"])
def test_chunks_shrink_the_compiled_gradients_working_memory(active_masks) -> None:
    algorithm = build_algorithm("cmat", NetworkConfig(n_embd=32), DISCRETE,
                                options=CMATOptions(consensus_iterations=1))
    params, batch = batch_for(algorithm)
    batch = jax.tree.map(lambda x: np.concatenate([x] * 16), batch)

    def working_memory(chunks: int) -> int:
        ppo = PPOConfig(active_masks=active_masks, minibatch_chunks=chunks)
        gradient = jax.jit(lambda p: minibatch_gradient(algorithm.loss, p, batch, ppo))
        return gradient.lower(params).compile().memory_analysis().temp_size_in_bytes

    assert working_memory(8) < 0.5 * working_memory(1)


@pytest.mark.parametrize("overrides, named", [
    (["algo=mappo", "ppo.minibatch_chunks=2"], "ppo.minibatch_chunks=2 applies to"),
    (["num_envs=4", "rollout_length=10", "ppo.minibatch_chunks=3"],
     "minibatch size (40) must be divisible by ppo.minibatch_chunks (3)"),
    (["num_envs=4", "rollout_length=10", "ppo.num_minibatches=2", "ppo.minibatch_chunks=40"],
     "minibatch size (20) must be divisible by ppo.minibatch_chunks (40)"),
    (["ppo.minibatch_chunks=0"], "ppo.minibatch_chunks must be > 0"),
])
def test_configs_that_cannot_chunk_are_refused_in_one_line(overrides, named) -> None:
    with pytest.raises(CmatError, match=re.escape(named)) as error:
        load_config(overrides=overrides)
    assert "\n" not in str(error.value)


def gradient_with(algorithm, params, batch, ppo: PPOConfig):
    return jax.jit(lambda p: minibatch_gradient(algorithm.loss, p, batch, ppo))(params)


@pytest.mark.parametrize("algo, spec, network, options", [
    ("cmat", DISCRETE, {}, {}),
    ("cmat", CONTINUOUS, {"consensus_policy": "categorical"}, {"joint_clip": "per_agent"}),
    ("pmat", CONTINUOUS, {}, {}),
    pytest.param("mat", DISCRETE, {}, {"per_agent_gae": True}, marks=pytest.mark.slow),
    pytest.param("triple_bert", CONTINUOUS, {}, {}, marks=pytest.mark.slow),
])
def test_accumulated_slices_give_the_minibatchs_loss_and_gradient(
    algo, spec, network, options
) -> None:
    algorithm = build_algorithm(algo, NetworkConfig(n_embd=8, init_gain=1.0), spec,
                                options=own(algo, **network, **options))
    params, batch = batch_for(algorithm)
    ppo = PPOConfig(active_masks=False)
    (whole, whole_metrics), whole_grad = gradient_with(algorithm, params, batch, ppo)
    (sliced, sliced_metrics), sliced_grad = gradient_with(
        algorithm, params, batch, dataclasses.replace(ppo, minibatch_chunks=4))
    assert float(sliced) == pytest.approx(float(whole), rel=1e-5, abs=1e-7)
    for name in ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac"):
        assert float(sliced_metrics[name]) == pytest.approx(
            float(whole_metrics[name]), rel=1e-5, abs=1e-7), name
    flat_whole, _ = jax.flatten_util.ravel_pytree(whole_grad)
    flat_sliced, _ = jax.flatten_util.ravel_pytree(sliced_grad)
    scale = float(np.abs(flat_whole).max())
    assert scale > 0
    np.testing.assert_allclose(flat_sliced, flat_whole, rtol=1e-4, atol=1e-5 * scale)


@pytest.mark.parametrize("active_masks, calls", [
    (False, [(8, 1)]),
    (True, [(32, 4)]),
])
def test_slices_are_accumulated_only_where_the_loss_is_a_plain_mean(active_masks, calls) -> None:
    """Without active masks the loss sees each 8-sample slice whole (traced once, in the
    scan); with them, the whole 32-sample minibatch and the chunk count, to recompute."""
    algorithm = build_algorithm("cmat", NetworkConfig(n_embd=8), DISCRETE,
                                options=CMATOptions(consensus_iterations=1))
    params, batch = batch_for(algorithm)
    seen = []

    def loss(p, minibatch, ppo):
        seen.append((minibatch.advantages.shape[0], ppo.minibatch_chunks))
        return algorithm.loss(p, minibatch, ppo)

    ppo = PPOConfig(active_masks=active_masks, minibatch_chunks=4)
    jax.eval_shape(lambda p: minibatch_gradient(loss, p, batch, ppo), params)
    assert set(seen) == set(calls)
