"""MAT and PMAT: training through the shared trainer, teacher forcing, order (in)sensitivity."""

from __future__ import annotations

import dataclasses
import functools
import itertools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cmat.algorithms.base import Batch
from cmat.algorithms.cmat.algorithm import CMAT
from cmat.algorithms.mat.algorithm import MAT
from cmat.algorithms.pmat.algorithm import PMAT, order_log_prob, sample_order
from cmat.algorithms.pmat.options import PMATOptions
from cmat.config import NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.networks.heads import action_distribution
from cmat.networks.layers import SCAN_LENGTH
from cmat.resolve import load_config
from cmat.runners.trainer import JaxTrainer

pytestmark = pytest.mark.quick_compiles

TINY = [
    "num_envs=8", "rollout_length=10", "ppo.epochs=2", "network.n_embd=16",
    "total_steps=240", "log_interval=3",
]
SHARP = NetworkConfig(n_embd=16, n_head=2, init_gain=1.0)
"""Output layers with gain 1, so that initial policies and order scores are far from uniform."""
AGENTS, ACTIONS, OBS_DIM, TEAMS = 3, 5, 4, 256
ORDERS = np.array(list(itertools.permutations(range(AGENTS))))


@functools.cache
def jitted(function: Callable, static_argnums: tuple[int, ...] = ()) -> Callable:
    """One compiled program per (bound) function, shared by every test that calls it."""
    return jax.jit(function, static_argnums=static_argnums)


class Team(NamedTuple):
    """An algorithm, its parameters and a batch it acted on at them (random masks)."""

    algorithm: MAT | PMAT
    params: Any
    batch: Batch


def acted_team(
    algorithm: MAT | PMAT, discrete: bool = True, seed: int = 0, agents: int = AGENTS,
    teams: int = TEAMS,
) -> Team:
    obs_key, mask_key, init_key, act_key, adv_key = jax.random.split(jax.random.PRNGKey(seed), 5)
    obs = jax.random.normal(obs_key, (teams, agents, OBS_DIM))
    mask = jax.random.bernoulli(mask_key, 0.5 if discrete else 1.0, (teams, agents, ACTIONS))
    mask = mask.at[..., 0].set(True)
    params = jitted(algorithm.init)(init_key, obs[0], mask[0])
    acted = jax.vmap(jitted(algorithm.act), in_axes=(None, 0, 0, 0))(
        params, obs, mask, jax.random.split(act_key, teams)
    )
    batch = Batch(
        obs=obs, action_mask=mask, actions=acted.actions, log_probs=acted.log_probs,
        values=acted.value, advantages=jax.random.normal(adv_key, (teams,)),
        targets=acted.value, extras=acted.extras,
    )
    return Team(algorithm, params, batch)


def spec(discrete: bool = True, agents: int = AGENTS) -> EnvSpec:
    return EnvSpec("test", agents, OBS_DIM, ACTIONS, discrete, 10, False)


@pytest.fixture(scope="module")
def mat_team() -> Team:
    return acted_team(MAT.build(SHARP, spec()))


@pytest.fixture(scope="module")
def pmat_team() -> Team:
    return acted_team(PMAT.build(SHARP, spec()), seed=1)


@pytest.fixture(scope="module", params=[
    ("mat", "smax:3m"), ("pmat", "matrix:fig1"),
    pytest.param(("pmat", "smax:3m"), marks=pytest.mark.slow),  # MAT's network on SMAX: above
], ids=lambda p: f"{p[0]}-{p[1]}")
def trained(request: pytest.FixtureRequest) -> tuple[str, Any, Any, dict[str, np.ndarray]]:
    algo, env = request.param
    trainer = JaxTrainer(load_config(overrides=[f"algo={algo}", f"env={env}", *TINY]))
    before = trainer.init()
    initial = jax.tree.map(np.array, before.learner.params)
    after, metrics = trainer.train_chunk(before)
    return algo, initial, jax.tree.map(np.array, after.learner.params), metrics


def test_trains_through_the_shared_trainer(trained: tuple) -> None:
    algo, initial, params, metrics = trained
    assert metrics["env_steps"].tolist() == [240]
    for key in ("loss", "policy_loss", "value_loss", "entropy", "approx_kl", "grad_norm"):
        assert np.all(np.isfinite(metrics[key])), key
    assert metrics["entropy"][0] > 0.0
    assert metrics["approx_kl"][0] > 0.0
    changed = jax.tree.map(lambda a, b: not np.allclose(a, b), initial, params)
    if algo == "mat":
        modules = changed["params"]
    else:
        modules = {**changed["mat"]["params"], "scorer": changed["scorer"]}
    assert {name for name, leaves in modules.items() if not any(jax.tree.leaves(leaves))} == set()
    if algo == "pmat":
        assert np.isfinite(metrics["order_loss"][0]) and metrics["order_approx_kl"][0] > 0.0


def teacher_forced_log_probs(team: Team, orders: jax.Array) -> jax.Array:
    mat: MAT = team.algorithm if isinstance(team.algorithm, MAT) else team.algorithm.mat
    params = team.params if isinstance(team.algorithm, MAT) else team.params["mat"]
    output = jitted(mat.teacher_forced)(params, team.batch, orders)
    distribution = action_distribution(output.action_params, output.log_std, mat.network.discrete)
    return distribution.log_prob(team.batch.actions)


def test_mat_teacher_forcing_equals_autoregressive_sampling(mat_team: Team) -> None:
    identity = jnp.broadcast_to(jnp.arange(AGENTS), (TEAMS, AGENTS))
    log_probs = teacher_forced_log_probs(mat_team, identity)
    np.testing.assert_allclose(log_probs, mat_team.batch.log_probs, rtol=1e-5, atol=1e-5)
    algorithm, params, batch = mat_team
    _, metrics = jitted(algorithm.loss, (2,))(params, batch, PPOConfig())
    assert float(metrics["approx_kl"]) == pytest.approx(0.0, abs=1e-7)
    assert float(metrics["clip_frac"]) == 0.0
    mean_advantage = float(jnp.mean(batch.advantages))
    assert float(metrics["policy_loss"]) == pytest.approx(-mean_advantage, abs=1e-5)


@pytest.mark.parametrize("algorithm_class", [MAT, PMAT], ids=["mat", "pmat"])
def test_scanned_decoding_of_a_large_team_equals_teacher_forcing(
    algorithm_class: type[MAT] | type[PMAT],
) -> None:
    """Above SCAN_LENGTH agents acting is one scanned position (a traced k attending to the
    whole cache, later positions masked): the log-probs of actions sampled along the decision
    order equal teacher forcing's, and greedy actions are teacher forcing's most likely ones."""
    agents = SCAN_LENGTH + 3
    team = acted_team(algorithm_class.build(SHARP, spec(agents=agents)), agents=agents, teams=16)
    identity = jnp.broadcast_to(jnp.arange(agents), (16, agents))
    orders = team.batch.extras.order if algorithm_class is PMAT else identity
    np.testing.assert_allclose(
        teacher_forced_log_probs(team, orders), team.batch.log_probs, rtol=1e-5, atol=1e-5
    )
    if algorithm_class is MAT:
        algorithm, params, batch = team
        greedy = jax.vmap(jitted(algorithm.greedy), in_axes=(None, 0, 0))(
            params, batch.obs, batch.action_mask
        )
        output = jitted(algorithm.teacher_forced)(params, batch._replace(actions=greedy), identity)
        np.testing.assert_array_equal(jnp.argmax(output.action_params, axis=-1), greedy)


def test_mat_teacher_forcing_equals_sampling_for_continuous_actions() -> None:
    team = acted_team(MAT.build(SHARP, spec(discrete=False)), discrete=False, seed=2)
    identity = jnp.broadcast_to(jnp.arange(AGENTS), (TEAMS, AGENTS))
    np.testing.assert_allclose(
        teacher_forced_log_probs(team, identity), team.batch.log_probs, rtol=1e-5, atol=1e-5
    )


def test_pmat_scores_actions_along_the_sampled_order(pmat_team: Team) -> None:
    algorithm, params, batch = pmat_team
    orders = np.asarray(batch.extras.order)
    assert np.all(np.sort(orders, axis=-1) == np.arange(AGENTS))
    assert np.mean(np.all(orders == np.arange(AGENTS), axis=-1)) < 0.5
    log_probs = teacher_forced_log_probs(pmat_team, batch.extras.order)
    np.testing.assert_allclose(log_probs, batch.log_probs, rtol=1e-5, atol=1e-5)
    _, metrics = jitted(algorithm.loss, (2,))(params, batch, PPOConfig())
    for key in ("approx_kl", "order_approx_kl"):
        assert float(metrics[key]) == pytest.approx(0.0, abs=1e-7), key
    assert float(metrics["clip_frac"]) == float(metrics["order_clip_frac"]) == 0.0
    mean_advantage = float(jnp.mean(batch.advantages))
    assert float(metrics["order_loss"]) == pytest.approx(-mean_advantage, abs=1e-5)
    identity = jnp.broadcast_to(jnp.arange(AGENTS), orders.shape)
    mismatched = teacher_forced_log_probs(pmat_team, identity)
    assert np.abs(np.asarray(mismatched - batch.log_probs)).max() > 1e-2
    greedy = np.asarray(jax.vmap(jitted(algorithm.greedy), in_axes=(None, 0, 0))(
        params, batch.obs, batch.action_mask
    ))
    assert np.take_along_axis(np.asarray(batch.action_mask), greedy[..., None], -1).all()


def test_pmat_index_order_loss_decodes_as_the_reference_training_pass(pmat_team: Team) -> None:
    """`pmat.order_in_loss=index` (PMAT's reference default) decodes the stored actions in index
    order, as the reference's `forward` does: at the collecting parameters its log-ratios are
    index-order teacher forcing against the log-probs acting had along the sampled order."""
    algorithm, params, batch = pmat_team
    identity = jnp.broadcast_to(jnp.arange(AGENTS), batch.extras.order.shape)
    log_ratio = teacher_forced_log_probs(pmat_team, identity) - batch.log_probs
    expected_kl = float(jnp.mean(jnp.expm1(log_ratio) - log_ratio))
    index_order = dataclasses.replace(algorithm, options=PMATOptions(order_in_loss="index"))
    _, metrics = jitted(index_order.loss, (2,))(params, batch, PPOConfig())
    assert expected_kl > 1e-3
    assert float(metrics["approx_kl"]) == pytest.approx(expected_kl, rel=1e-4)
    assert float(metrics["order_approx_kl"]) == pytest.approx(0.0, abs=1e-7)


def test_pmat_order_weights_are_the_references_bounded_weights(pmat_team: Team) -> None:
    """The reference's scoring block: LayerNorm, two GELU layers of 64 each followed by a
    LayerNorm, one output squashed to a weight in (1, 10)."""
    algorithm, params, batch = pmat_team
    _, _, log_weights = jax.vmap(jitted(algorithm.scores), in_axes=(None, 0))(params, batch.obs)
    weights = np.exp(np.asarray(log_weights))
    assert weights.min() > 1.0 and weights.max() < 10.0 and weights.std() > 0.1
    scorer = params["scorer"]["params"]
    kernels = sorted(layer["kernel"].shape for layer in scorer.values() if "kernel" in layer)
    assert kernels == [(16, 64), (64, 1), (64, 64)]
    assert sum("scale" in layer for layer in scorer.values()) == 3


def test_pmat_order_term_averages_every_agents_advantage(pmat_team: Team) -> None:
    """With per-agent advantages, the order term's advantage is their mean over every agent,
    dead ones too (reference `mat_trainer.py`: `adv_targ.view(-1, n).mean(dim=1)`), while the
    policy loss leaves the dead out."""
    algorithm, params, batch = pmat_team
    advantage_key, alive_key = jax.random.split(jax.random.PRNGKey(5))
    advantages = jax.random.normal(advantage_key, (TEAMS, AGENTS)) + 1.0
    alive = jax.random.bernoulli(alive_key, 0.6, (TEAMS, AGENTS)).at[:, 0].set(True)
    per_agent = batch._replace(advantages=advantages, alive=alive,
                               targets=jnp.broadcast_to(batch.targets[:, None], alive.shape))
    _, metrics = jitted(algorithm.loss, (2,))(params, per_agent, PPOConfig(active_masks=True))
    assert float(metrics["order_loss"]) == pytest.approx(-float(jnp.mean(advantages)), abs=1e-5)
    masked = float(jnp.sum(advantages * alive) / jnp.sum(alive))
    assert float(metrics["policy_loss"]) == pytest.approx(-masked, abs=1e-5)


def joint_distribution(log_probs: Callable[[jax.Array], jax.Array]) -> np.ndarray:
    """P(a_0, .., a_{n-1}) over all joint actions, from per-agent log-probs of joint actions."""
    joint = jnp.array(list(itertools.product(range(ACTIONS), repeat=AGENTS)))
    per_agent = np.asarray(log_probs(joint), np.float64)
    return np.exp(per_agent.sum(-1)).reshape((ACTIONS,) * AGENTS)


def mat_joint(team: Team, obs: jax.Array, order: np.ndarray) -> np.ndarray:
    def log_probs(joint: jax.Array) -> jax.Array:
        size = len(joint)
        batch = team.batch._replace(
            obs=jnp.broadcast_to(obs, (size, *obs.shape)),
            action_mask=jnp.ones((size, AGENTS, ACTIONS), bool), actions=joint,
        )
        orders = jnp.broadcast_to(jnp.asarray(order), (size, AGENTS))
        return teacher_forced_log_probs(team._replace(batch=batch), orders)

    return joint_distribution(log_probs)


def cmat_joint(algorithm: CMAT, params: Any, obs: jax.Array) -> np.ndarray:
    logits = jitted(algorithm.network.apply)(params, obs, jnp.ones((AGENTS, ACTIONS), bool))
    log_softmax = jax.nn.log_softmax(logits.action_params)
    return joint_distribution(
        lambda joint: jnp.take_along_axis(log_softmax[None], joint[..., None], -1)[..., 0]
    )


def test_mat_joint_policy_depends_on_the_order_while_cmat_is_permutation_equivariant(
    mat_team: Team,
) -> None:
    obs = mat_team.batch.obs[0]
    permutation = np.array([2, 0, 1])
    identity = mat_joint(mat_team, obs, np.arange(AGENTS))
    reordered = mat_joint(mat_team, obs, permutation)
    relabelled = mat_joint(mat_team, obs[permutation], np.arange(AGENTS))
    for joint in (identity, reordered, relabelled):
        assert joint.sum() == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(
        relabelled, reordered.transpose(permutation), atol=1e-6,
        err_msg="decoding along an order must equal decoding the agents listed in that order",
    )
    gaps = [np.abs(reordered - identity.transpose(axes)).max() for axes in ORDERS]
    assert min(gaps) > 1e-2, gaps
    assert np.abs(relabelled - identity.transpose(permutation)).max() > 1e-2

    cmat = CMAT.build(SHARP, spec())
    params = jitted(cmat.init)(jax.random.PRNGKey(3), obs, jnp.ones((AGENTS, ACTIONS), bool))
    original, permuted = cmat_joint(cmat, params, obs), cmat_joint(cmat, params, obs[permutation])
    assert original.sum() == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(permuted, original.transpose(permutation), atol=1e-6)
    assert np.abs(original - original.transpose(permutation)).max() > 1e-2


def test_plackett_luce_order_probabilities_and_sampler() -> None:
    scores = jnp.array([1.2, -0.3, 0.4])
    probs = np.exp(np.asarray(order_log_prob(jnp.broadcast_to(scores, ORDERS.shape), ORDERS)))
    assert probs.sum() == pytest.approx(1.0, abs=1e-6)
    weights = np.exp(np.asarray(scores, np.float64))
    for order, prob in zip(ORDERS, probs):
        expected = np.prod([weights[order[k]] / weights[order[k:]].sum() for k in range(AGENTS)])
        assert prob == pytest.approx(expected, rel=1e-5)
    samples = np.asarray(jax.vmap(sample_order, in_axes=(None, 0))(
        scores, jax.random.split(jax.random.PRNGKey(4), 20000)
    ))
    frequencies = [np.mean(np.all(samples == order, axis=-1)) for order in ORDERS]
    np.testing.assert_allclose(frequencies, probs, atol=0.015)


def test_mat_never_samples_or_picks_masked_actions(mat_team: Team) -> None:
    algorithm, params, batch = mat_team
    mask, actions = np.asarray(batch.action_mask), np.asarray(batch.actions)
    assert mask.mean() < 0.7
    assert np.take_along_axis(mask, actions[..., None], -1).all()
    assert np.isfinite(np.asarray(batch.log_probs)).all()
    greedy = np.asarray(jax.vmap(jitted(algorithm.greedy), in_axes=(None, 0, 0))(
        params, batch.obs, batch.action_mask
    ))
    assert np.take_along_axis(mask, greedy[..., None], -1).all()
    assert len(np.unique(actions)) == ACTIONS


@pytest.mark.parametrize("value_active_masks", [False, True])
@pytest.mark.parametrize("team_name", ["mat_team", "pmat_team"])
def test_every_agent_value_regresses_on_the_team_target_with_its_own_clip(
    team_name: str, value_active_masks: bool, request: pytest.FixtureRequest
) -> None:
    """The reference MAT value loss: mean over samples and agents of
    max((R − V_i)², (R − clip(V_i, V_i,old ± ε))²)/2, with V_i,old stored at acting time; dead
    agents count in that mean unless `ppo.value_active_masks` (the reference SMAC script's)."""
    team: Team = request.getfixturevalue(team_name)
    is_mat = isinstance(team.algorithm, MAT)
    mat: MAT = team.algorithm if is_mat else team.algorithm.mat
    params = team.params if is_mat else team.params["mat"]
    old_values = np.asarray(team.batch.extras if is_mat else team.batch.extras.agent_values)
    np.testing.assert_allclose(old_values.mean(axis=1), team.batch.values, rtol=1e-6, atol=1e-6)

    targets = np.asarray(team.batch.targets) + np.linspace(-1.0, 1.0, TEAMS)
    alive = np.ones(team.batch.log_probs.shape, bool)
    alive[::2, 0] = False
    shifted = team.batch._replace(targets=jnp.asarray(targets), alive=jnp.asarray(alive))
    moved = jax.tree.map(lambda x: x * 1.5, params)
    ppo = PPOConfig(huber_loss=False, clipped_value_loss=True, clip_eps=0.05, active_masks=True,
                    value_active_masks=value_active_masks)
    orders = jnp.broadcast_to(mat.identity, team.batch.log_probs.shape)
    _, metrics, output = jitted(mat.loss_along, static_argnums=(4,))(
        moved, shifted, orders, jnp.asarray(old_values), ppo
    )
    values = np.asarray(output.agent_values, np.float64)
    clipped = old_values + np.clip(values - old_values, -0.05, 0.05)
    losses = np.maximum((targets[:, None] - values) ** 2, (targets[:, None] - clipped) ** 2) / 2
    expected = losses[alive].mean() if value_active_masks else losses.mean()
    assert not np.isclose(losses[alive].mean(), losses.mean(), rtol=1e-3)
    assert np.abs(values - old_values).max() > 0.05
    np.testing.assert_allclose(metrics["value_loss"], expected, rtol=1e-4)
