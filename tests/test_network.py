"""Properties of the CMAT network: order independence, masks, the decoder cache, ablations."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cmat.algorithms.cmat.algorithm import CMAT
from cmat.algorithms.cmat.network import ConsensusDecoder
from cmat.algorithms.cmat.options import CMATOptions
from cmat.config import NetworkConfig
from cmat.envs.protocol import EnvSpec
from cmat.networks.heads import SharedInputDense, action_distribution
from cmat.networks.layers import SCAN_LENGTH, DecoderBlock, MultiHeadAttention, dense

N_AGENTS, OBS_DIM, N_ACTIONS = 5, 7, 6


pytestmark = pytest.mark.quick_compiles

def build(discrete: bool, **options: object) -> tuple[CMAT, object, jax.Array, jax.Array]:
    spec = EnvSpec("test", N_AGENTS, OBS_DIM, N_ACTIONS, discrete, 10, False)
    algorithm = CMAT.build(NetworkConfig(n_embd=32, n_head=2), spec,
                           options=CMATOptions(**options))
    obs = jax.random.normal(jax.random.PRNGKey(1), (3, N_AGENTS, OBS_DIM))
    mask = jax.random.bernoulli(jax.random.PRNGKey(2), 0.6, (3, N_AGENTS, N_ACTIONS))
    mask = mask.at[..., 0].set(True)
    params = jax.jit(algorithm.init)(jax.random.PRNGKey(0), obs[0], mask[0])
    return algorithm, params, obs, mask


@pytest.mark.unit
@pytest.mark.parametrize("discrete", [True, False])
def test_permuting_agents_permutes_policies_and_keeps_value_and_consensus(discrete: bool) -> None:
    algorithm, params, obs, mask = build(discrete)
    permutation = np.array([3, 0, 4, 1, 2])

    def apply(o, m):
        return jax.jit(algorithm.network.apply)(params, o, m)

    original, permuted = apply(obs, mask), apply(obs[:, permutation], mask[:, permutation])
    np.testing.assert_allclose(permuted.value, original.value, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(permuted.consensus, original.consensus, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(
        permuted.action_params, original.action_params[:, permutation], rtol=1e-5, atol=1e-5
    )
    dist = action_distribution(original.action_params, original.log_std, discrete)
    dist_permuted = action_distribution(permuted.action_params, permuted.log_std, discrete)
    actions = dist.sample(seed=jax.random.PRNGKey(3))
    np.testing.assert_allclose(
        dist_permuted.log_prob(actions[:, permutation]),
        dist.log_prob(actions)[:, permutation], rtol=1e-5, atol=1e-5,
    )


@pytest.mark.unit
def test_different_observations_change_the_consensus() -> None:
    algorithm, params, obs, mask = build(True)
    out = jax.jit(algorithm.network.apply)(params, obs, mask)
    assert not np.allclose(out.consensus[0], out.consensus[1])


@pytest.mark.unit
def test_masked_actions_have_zero_probability_and_are_never_sampled() -> None:
    algorithm, params, obs, mask = build(True)
    keys = jax.random.split(jax.random.PRNGKey(4), 2000)
    act = jax.jit(jax.vmap(algorithm.act, in_axes=(None, None, None, 0)))
    acted = act(params, obs[0], mask[0], keys)
    chosen_available = jnp.take_along_axis(mask[0][None], acted.actions[..., None], axis=-1)
    assert bool(jnp.all(chosen_available))
    output = jax.jit(algorithm.network.apply)(params, obs, mask)
    probs = jax.nn.softmax(output.action_params, axis=-1)
    assert float(jnp.max(jnp.where(mask, 0.0, probs))) == 0.0
    distribution = action_distribution(output.action_params, output.log_std, True)
    assert np.isfinite(float(jnp.sum(distribution.entropy())))


@pytest.mark.unit
@pytest.mark.parametrize("causal", [False, True])
def test_attention_matches_flax_reference_attention(causal: bool) -> None:
    attention = MultiHeadAttention(n_embd=16, n_head=4)
    x = jax.random.normal(jax.random.PRNGKey(0), (2, 5, 16))
    memory = jax.random.normal(jax.random.PRNGKey(1), (2, 5, 16))
    params = attention.init(jax.random.PRNGKey(2), x, memory)["params"]
    params = jax.tree.map(
        lambda p: p + 0.1 * jax.random.normal(jax.random.PRNGKey(3), p.shape), params
    )

    def project(name: str, inputs: jax.Array) -> jax.Array:
        layer = params[name]
        return (inputs @ layer["kernel"] + layer["bias"]).reshape(2, 5, 4, 4)

    mask = nn.make_causal_mask(jnp.ones((2, 5))) if causal else None
    heads = nn.dot_product_attention(
        project("query", x), project("key", memory), project("value", memory), mask=mask
    )
    reference = heads.reshape(2, 5, 16) @ params["out"]["kernel"] + params["out"]["bias"]
    output = attention.apply({"params": params}, x, memory, causal=causal)
    np.testing.assert_allclose(output, reference, rtol=1e-5, atol=1e-5)


@pytest.mark.unit
@pytest.mark.parametrize("traced", [False, True], ids=["static", "traced"])
def test_decoder_cache_matches_full_causal_pass(traced: bool) -> None:
    """Iterating `step` over a cache equals the causal pass, whether the position is a static
    int (the prefix is read) or an array (the whole cache is read, later positions masked)."""
    block = DecoderBlock(n_embd=16, n_head=2)
    tokens = jax.random.normal(jax.random.PRNGKey(0), (2, 6, 16))
    memory = jax.random.normal(jax.random.PRNGKey(1), (2, 4, 16))
    params = block.init(jax.random.PRNGKey(2), tokens, memory)
    full = jax.jit(block.apply)(params, tokens, memory)

    def iterate(module: DecoderBlock) -> jax.Array:
        encoded, outputs = module.encode_memory(memory), []
        cache = module.empty_cache(tokens[:, 0], tokens.shape[1])
        for k in range(tokens.shape[1]):
            position = jnp.asarray(k) if traced else k
            y, cache = module.step(tokens[:, k : k + 1], cache, encoded, position)
            outputs.append(y[:, 0])
        return jnp.stack(outputs, axis=1)

    cached = jax.jit(lambda p: block.apply(p, method=iterate))(params)
    np.testing.assert_allclose(cached, full, rtol=1e-5, atol=1e-5)


@pytest.mark.unit
def test_shared_input_dense_equals_a_dense_layer_on_the_concatenation() -> None:
    tokens = jax.random.normal(jax.random.PRNGKey(3), (2, N_AGENTS, 6))
    shared = jax.random.normal(jax.random.PRNGKey(4), (2, 4))
    layer = SharedInputDense(8)
    params = layer.init(jax.random.PRNGKey(0), tokens, shared)
    params["params"]["bias"] = jax.random.normal(jax.random.PRNGKey(5), (8,))
    concatenated = jnp.concatenate(
        [tokens, jnp.broadcast_to(shared[:, None, :], (2, N_AGENTS, 4))], axis=-1
    )
    reference = dense(8).apply(params, concatenated)
    np.testing.assert_allclose(layer.apply(params, tokens, shared), reference, rtol=1e-5, atol=1e-5)
    assert params["params"]["kernel"].shape == (10, 8)


def test_iterations_and_consensus_source_change_the_output() -> None:
    _, _, obs, mask = build(True)
    outputs = {}
    for name, overrides in {
        "default": {},
        "m0": {"consensus_iterations": 0},
        "last": {"consensus_source": "last"},
    }.items():
        algorithm, params, _, _ = build(True, **overrides)
        outputs[name] = jax.jit(algorithm.network.apply)(params, obs, mask)
        assert np.all(np.isfinite(outputs[name].action_params))
    assert algorithm.network.iterations == N_AGENTS
    for other in ("m0", "last"):
        assert not np.allclose(outputs[other].action_params, outputs["default"].action_params)


@pytest.mark.unit
def test_m_zero_uses_e0_alone() -> None:
    algorithm, params, obs, mask = build(True, consensus_iterations=0)
    assert "decoder" not in params["params"]
    out = jax.jit(algorithm.network.apply)(params, obs, mask)
    assert out.consensus.shape == (3, 32)


@pytest.mark.parametrize("iterations", [1, 3])
def test_scanned_consensus_iterations_equal_unrolled_ones(iterations: int) -> None:
    """The decoder's scanned path (large m) has the unrolled path's parameters and gives its
    consensus sequence and gradients up to float rounding."""
    e0 = jax.random.normal(jax.random.PRNGKey(1), (3, 16))
    encoded = jax.random.normal(jax.random.PRNGKey(2), (3, N_AGENTS, 16))
    unrolled, scanned = (ConsensusDecoder(16, 2, 2, iterations, scan=scan)
                         for scan in (False, True))
    params = jax.jit(unrolled.init)(jax.random.PRNGKey(0), e0, encoded)
    assert (jax.tree.map(jnp.shape, jax.eval_shape(scanned.init, jax.random.PRNGKey(0), e0,
                                                   encoded))
            == jax.tree.map(jnp.shape, params))
    np.testing.assert_allclose(jax.jit(scanned.apply)(params, e0, encoded),
                               jax.jit(unrolled.apply)(params, e0, encoded),
                               rtol=1e-5, atol=1e-5)

    def gradient(decoder: ConsensusDecoder) -> list[jax.Array]:
        loss = lambda p: jnp.sum(jnp.sin(decoder.apply(p, e0, encoded)))  # noqa: E731
        return jax.tree.leaves(jax.jit(jax.grad(loss))(params))

    for scanned_grad, unrolled_grad in zip(gradient(scanned), gradient(unrolled)):
        np.testing.assert_allclose(scanned_grad, unrolled_grad, rtol=1e-4, atol=1e-5)


@pytest.mark.unit
@pytest.mark.parametrize("options", [{"consensus_iterations": SCAN_LENGTH + 3},
                                     {"inducing_points": 3}], ids=["scanned", "inducing"])
def test_large_team_settings_keep_order_independence(options: dict[str, int]) -> None:
    """m above SCAN_LENGTH (a scanned decoder), and agents attending through learned
    vectors: permuting the agents permutes the policies and keeps the value and the
    consensus."""
    algorithm, params, obs, mask = build(True, **options)
    permutation = np.array([3, 0, 4, 1, 2])
    apply = jax.jit(algorithm.network.apply)
    original, permuted = apply(params, obs, mask), apply(params, obs[:, permutation],
                                                         mask[:, permutation])
    np.testing.assert_allclose(permuted.value, original.value, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(permuted.consensus, original.consensus, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(permuted.action_params, original.action_params[:, permutation],
                               rtol=1e-5, atol=1e-5)


@pytest.mark.unit
def test_inducing_points_are_parameters_of_each_encoder_block() -> None:
    def inducing(params: object) -> list[tuple[int, ...]]:
        return [leaf.shape for path, leaf in jax.tree_util.tree_leaves_with_path(params)
                if "inducing" in jax.tree_util.keystr(path)]

    assert inducing(build(True, inducing_points=3)[1]) == [(3, 32)]
    assert inducing(build(True)[1]) == []


@pytest.mark.unit
@pytest.mark.parametrize("inducing", [0, 4])
def test_inducing_points_make_the_encoders_largest_array_linear_in_agents(inducing: int) -> None:
    """The largest intermediate of the encoder's forward and backward pass grows as n² with
    full attention and as n with k inducing points (traced, not run: shapes only)."""
    from cmat.networks.layers import ObservationEncoder

    def largest(agents: int) -> int:
        encoder = ObservationEncoder(16, 1, 1, inducing_points=inducing)
        obs = jnp.zeros((2, agents, 6))
        params = jax.eval_shape(encoder.init, jax.random.PRNGKey(0), obs)
        jaxpr = jax.make_jaxpr(jax.grad(lambda p: jnp.sum(encoder.apply(p, obs))))(params)
        return max(int(np.prod(var.aval.shape)) for equation in jaxpr.jaxpr.eqns
                   for var in equation.outvars)

    growth = largest(400) / largest(100)
    assert growth == pytest.approx(16 if inducing == 0 else 4, rel=0.05)


@pytest.mark.parametrize(("agents", "block"), [(7, 3), (8, 4), (5, 1)])
def test_blockwise_attention_is_full_attention_in_value_and_gradient(
    agents: int, block: int
) -> None:
    """`attention_block` changes the memory of the encoder, not its function: outputs and
    gradients equal full attention's (whole and partial blocks), and permuting the agents
    permutes the outputs."""
    from cmat.networks.layers import ObservationEncoder

    obs = jax.random.normal(jax.random.PRNGKey(0), (3, agents, 6))
    full, blocked = (ObservationEncoder(16, 2, 2, query_block=b) for b in (0, block))
    params = full.init(jax.random.PRNGKey(1), obs)

    def loss(p: object, module: ObservationEncoder) -> jax.Array:
        return jnp.sum(module.apply(p, obs) ** 2)

    np.testing.assert_allclose(blocked.apply(params, obs), full.apply(params, obs),
                               rtol=1e-5, atol=1e-5)
    for got, want in zip(jax.tree.leaves(jax.grad(loss)(params, blocked)),
                         jax.tree.leaves(jax.grad(loss)(params, full)), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    order = jax.random.permutation(jax.random.PRNGKey(2), agents)
    np.testing.assert_allclose(blocked.apply(params, obs[:, order]),
                               blocked.apply(params, obs)[:, order], rtol=1e-5, atol=1e-5)


@pytest.mark.unit
def test_blockwise_attention_masks_keys_as_full_attention_does() -> None:
    from cmat.networks.layers import blockwise_attention

    keys = jax.random.normal(jax.random.PRNGKey(0), (2, 9, 4))
    values = jax.random.normal(jax.random.PRNGKey(1), (2, 9, 4))
    queries = jax.random.normal(jax.random.PRNGKey(2), (2, 5, 4))
    visible = jnp.arange(9) % 3 != 0
    logits = jnp.where(visible, jnp.einsum("hqd,hkd->hqk", queries, keys), -jnp.inf)
    want = jnp.einsum("hqk,hkd->hqd", jax.nn.softmax(logits, axis=-1), values)
    np.testing.assert_allclose(blockwise_attention(queries, keys, values, 2, visible), want,
                               rtol=1e-5, atol=1e-6)
