"""The stochastic consensus (paper eq. joint-stochastic): log-probabilities, the joint ratio,
expressiveness beyond a single product, order independence, and the penalty game."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from cmat.algorithms.base import Batch
from cmat.algorithms.cmat.algorithm import CMAT
from cmat.algorithms.cmat.blocks import FROZEN, TRAIN, finetune_labels
from cmat.algorithms.cmat.options import CMATOptions
from cmat.config import NetworkConfig
from cmat.envs.protocol import EnvSpec
from cmat.experiments.matrix_games import train_and_count_optimum
from cmat.resolve import load_config

pytestmark = pytest.mark.quick_compiles

AGENTS, ACTIONS, OBS_DIM, TEAMS = 4, 5, 6, 64
POLICIES = ("categorical", "gaussian")


def build(policy: str, agents: int = AGENTS, actions: int = ACTIONS, **network: object) -> CMAT:
    config = NetworkConfig(n_embd=16, n_head=2)
    spec = EnvSpec("test", agents, OBS_DIM, actions, True, 10, False)
    options = CMATOptions(consensus_policy=policy, consensus_codes=4)
    return CMAT.build(dataclasses.replace(config, **network), spec, options=options)


def acted(policy: str) -> tuple[CMAT, object, Batch]:
    algorithm = build(policy)
    obs_key, mask_key, init_key, act_key = jax.random.split(jax.random.PRNGKey(0), 4)
    obs = jax.random.normal(obs_key, (TEAMS, AGENTS, OBS_DIM))
    mask = jax.random.bernoulli(mask_key, 0.6, (TEAMS, AGENTS, ACTIONS)).at[..., 0].set(True)
    params = jax.jit(algorithm.init)(init_key, obs[0], mask[0])
    result = jax.jit(jax.vmap(algorithm.act, in_axes=(None, 0, 0, 0)))(
        params, obs, mask, jax.random.split(act_key, TEAMS)
    )
    batch = Batch(
        obs=obs, action_mask=mask, actions=result.actions, log_probs=result.log_probs,
        values=result.value, advantages=jnp.zeros(TEAMS), targets=result.value,
        extras=result.extras,
    )
    return algorithm, params, batch


def log_softmax(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64)
    return x - np.log(np.sum(np.exp(x - x.max(-1, keepdims=True)), -1, keepdims=True)) - x.max(
        -1, keepdims=True
    )


@pytest.mark.unit
@pytest.mark.parametrize("policy", POLICIES)
def test_log_prob_of_a_sampled_latent_and_joint_action_is_the_sum_of_its_parts(policy: str) -> None:
    algorithm, params, batch = acted(policy)
    apply = jax.jit(lambda latent: algorithm.network.apply(
        params, batch.obs, batch.action_mask, latent=latent
    ))
    output = apply(batch.extras.latent)
    per_agent = np.take_along_axis(
        log_softmax(output.action_params), np.asarray(batch.actions)[..., None], -1
    )[..., 0]
    if policy == "categorical":
        every_code = np.stack(
            [apply(jnp.full(TEAMS, code)).latent_log_prob for code in range(4)], axis=-1
        )
        np.testing.assert_allclose(np.exp(every_code).sum(-1), 1.0, rtol=1e-5)
        latent_part = every_code[np.arange(TEAMS), np.asarray(batch.extras.latent)]
        assert len(np.unique(np.asarray(batch.extras.latent))) > 1
    else:
        scale = np.exp(np.asarray(params["params"]["latent_consensus"]["log_scale"], np.float64))
        z = (np.asarray(batch.extras.latent, np.float64) - np.asarray(output.consensus)) / scale
        latent_part = (-0.5 * np.sum(z**2, -1) - np.sum(np.log(scale))
                       - 0.5 * z.shape[-1] * np.log(2 * np.pi))
    np.testing.assert_allclose(batch.extras.log_prob, latent_part, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(batch.log_probs, per_agent, rtol=1e-4, atol=1e-4)
    joint = np.asarray(batch.extras.log_prob) + np.asarray(batch.log_probs).sum(-1)
    np.testing.assert_allclose(joint, latent_part + per_agent.sum(-1), rtol=1e-4, atol=1e-4)


@pytest.mark.unit
@pytest.mark.parametrize("policy", POLICIES)
def test_joint_ratio_is_one_at_the_collecting_parameters_and_moves_with_the_latent(
    policy: str,
) -> None:
    algorithm, params, batch = acted(policy)
    log_ratio_fn = jax.jit(algorithm.log_ratio)
    log_ratio, _, _ = log_ratio_fn(params, batch)
    np.testing.assert_allclose(log_ratio, 0.0, atol=1e-5)
    shifted = jax.tree.map(lambda x: x + 0.05, params["params"]["latent_consensus"])
    moved = {"params": {**params["params"], "latent_consensus": shifted}}
    moved_ratio, output, _ = log_ratio_fn(moved, batch)
    expected = np.asarray(output.latent_log_prob) - np.asarray(batch.extras.log_prob)
    if policy == "gaussian":
        np.testing.assert_allclose(moved_ratio, expected, rtol=1e-4, atol=1e-4)
    assert np.abs(np.asarray(moved_ratio)).max() > 1e-3


def joint_distribution(
    algorithm: CMAT, params: object, obs: jax.Array, mask: jax.Array
) -> jax.Array:
    """P(a1, a2) = Σ_z π_c(z | O) π_1(a1 | O, z) π_2(a2 | O, z) (a deterministic consensus: the
    single product)."""
    def given(latent: jax.Array | None) -> jax.Array:
        output = algorithm.network.apply(params, obs, mask, latent=latent)
        p = jax.nn.softmax(output.action_params, axis=-1)
        weight = jnp.exp(output.latent_log_prob) if algorithm.stochastic else 1.0
        return weight * jnp.outer(p[0], p[1])

    if not algorithm.stochastic:
        return given(None)
    return jax.vmap(given)(jnp.arange(algorithm.network.options.consensus_codes)).sum(axis=0)


@pytest.mark.parametrize("policy", ["categorical", "deterministic"])
def test_categorical_consensus_represents_a_correlated_joint_policy_no_product_can(
    policy: str,
) -> None:
    """Target ½(0,0) + ½(2,2). Every product has P00·P22 = P02·P20 (both are
    p1(0)p1(2)p2(0)p2(2)); the fitted K-code mixture breaks that identity, the deterministic
    consensus keeps it exactly."""
    algorithm = build(policy, agents=2, actions=3, init_gain=1.0)
    obs, mask = jnp.eye(2, OBS_DIM), jnp.ones((2, 3), bool)
    target = jnp.zeros((3, 3)).at[0, 0].set(0.5).at[2, 2].set(0.5)
    params = jax.jit(algorithm.init)(jax.random.PRNGKey(0), obs, mask)
    optimizer = optax.adam(0.02)

    @jax.jit
    def fit_step(params: object, opt_state: object) -> tuple[object, object]:
        grads = jax.grad(
            lambda p: -jnp.sum(target * jnp.log(joint_distribution(algorithm, p, obs, mask) + 1e-9))
        )(params)
        updates, opt_state = optimizer.update(grads, opt_state)
        return optax.apply_updates(params, updates), opt_state

    opt_state = optimizer.init(params)
    for _ in range(300):
        params, opt_state = fit_step(params, opt_state)
    joint = np.asarray(jax.jit(lambda p: joint_distribution(algorithm, p, obs, mask))(params),
                       np.float64)
    np.testing.assert_allclose(joint.sum(), 1.0, rtol=1e-5)
    gap = joint[0, 0] * joint[2, 2] - joint[0, 2] * joint[2, 0]
    if policy == "categorical":
        assert joint[0, 0] > 0.4 and joint[2, 2] > 0.4, joint
        assert gap > 0.15, joint
    else:
        assert abs(gap) < 1e-6, joint
        assert joint[0, 0] + joint[2, 2] < 0.75, joint


@pytest.mark.unit
@pytest.mark.parametrize("policy", POLICIES)
def test_permuting_agents_permutes_policies_given_the_latent_and_keeps_the_consensus_policy(
    policy: str,
) -> None:
    algorithm, params, batch = acted(policy)
    permutation = np.array([2, 0, 3, 1])
    apply = jax.jit(lambda obs, mask: algorithm.network.apply(
        params, obs, mask, latent=batch.extras.latent
    ))
    original = apply(batch.obs, batch.action_mask)
    permuted = apply(batch.obs[:, permutation], batch.action_mask[:, permutation])
    for field in ("value", "consensus", "latent_log_prob", "latent_entropy"):
        np.testing.assert_allclose(
            getattr(permuted, field), getattr(original, field), rtol=1e-4, atol=1e-4
        )
    np.testing.assert_allclose(
        permuted.action_params, original.action_params[:, permutation], rtol=1e-4, atol=1e-4
    )
    greedy_fn = jax.jit(algorithm.greedy)
    greedy = greedy_fn(params, batch.obs[0], batch.action_mask[0])
    greedy_permuted = greedy_fn(
        params, batch.obs[0][permutation], batch.action_mask[0][permutation]
    )
    np.testing.assert_array_equal(greedy_permuted, np.asarray(greedy)[permutation])


@pytest.mark.slow
def test_categorical_consensus_reaches_an_optimum_of_the_penalty_game() -> None:
    config = load_config(overrides=[
        "env=matrix:penalty", "cmat.consensus_policy=categorical", *PENALTY_RUN,
    ])
    at_optimum, joint = train_and_count_optimum(config)
    assert at_optimum >= 8, joint.tolist()


PENALTY_RUN = (
    "seeds=10", "num_envs=16", "rollout_length=25", "ppo.epochs=5", "total_steps=40000",
    "ppo.lr=1e-3",
)
"""The budget benchmarks/matrix_optimum.py compares every method at on matrix:penalty."""


@pytest.mark.unit
@pytest.mark.parametrize("mode, trains_latent", [("consensus", True), ("action", False)])
def test_fine_tuning_trains_the_consensus_policy_with_the_consensus_only(
    mode: str, trains_latent: bool
) -> None:
    _algorithm, params, _ = acted("categorical")
    labels = finetune_labels(params, mode)["params"]
    assert set(jax.tree.leaves(labels["latent_consensus"])) == {TRAIN if trains_latent else FROZEN}
    assert set(jax.tree.leaves(labels["actor_mlp"])) == {FROZEN if trains_latent else TRAIN}
