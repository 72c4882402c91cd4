"""The Triple-BERT, MAPPO and HAPPO baselines: training through the shared trainer, their losses,
HAPPO's sequential update and compounding factor."""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from optax.tree_utils import tree_get
from test_training import TINY, fixed_batch, numpy_cmat_loss

from cmat.algorithms import build_algorithm
from cmat.algorithms.base import Batch
from cmat.algorithms.happo.algorithm import (
    HAPPO,
    agent_columns,
    agent_phase,
    compounding_factors,
    train_phase,
)
from cmat.algorithms.mappo.algorithm import MAPPO
from cmat.algorithms.mappo.network import MLPActor
from cmat.config import NetworkConfig, PPOConfig
from cmat.envs.protocol import EnvSpec
from cmat.resolve import load_config
from cmat.runners import trainer as trainer_lib
from cmat.runners.learner import LearnerSetup
from cmat.runners.trainer import JaxTrainer

pytestmark = pytest.mark.quick_compiles

SPEC = EnvSpec("test", 3, 5, 4, True, 10, False)
NETWORK = NetworkConfig(n_embd=16, n_head=2)
LOSS_METRICS = ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac", "loss")


def rows(tree: dict, agent: int) -> list[np.ndarray]:
    return [np.asarray(leaf[agent]) for leaf in jax.tree.leaves(tree["actor"])]


def differ(before: list, after: list) -> bool:
    return any(not np.array_equal(a, b) for a, b in zip(before, after))


@pytest.fixture(scope="module", params=["mappo", "happo", "triple_bert"])
def trained(request: pytest.FixtureRequest) -> tuple:
    """Params before and after two updates in one chunk on SMAX 3m (action masks, a world
    state, episodes of many steps: the matrix game's path is a subset), and the chunk's
    metrics."""
    trainer = JaxTrainer(load_config(overrides=[
        f"algo={request.param}", "env=smax:3m", "total_steps=160", "log_interval=2", *TINY,
    ]))
    state = trainer.init()
    before = jax.tree.map(np.asarray, state.learner.params)
    state, metrics = trainer.train_chunk(state)
    return before, state.learner.params, metrics


def test_baseline_trains_through_the_shared_trainer(trained: tuple) -> None:
    before, after, metrics = trained
    leaves = list(zip(jax.tree.leaves(before), jax.tree.leaves(after)))
    assert sum(differ([a], [b]) for a, b in leaves) > len(leaves) // 2
    for key in LOSS_METRICS:
        assert np.all(np.isfinite(metrics[key])), key
    assert metrics["approx_kl"][0] > 0.0
    assert metrics["env_steps"][0] == 160


def test_compounding_factor_matches_a_numpy_reference() -> None:
    rng = np.random.default_rng(0)
    new, old = rng.normal(size=(2, 6, 4)) * 0.3
    order = np.array([2, 0, 3, 1])
    factors = compounding_factors(jnp.asarray(new), jnp.asarray(old), jnp.asarray(order))
    expected = np.ones((6, 4))
    running = np.ones(6)
    for agent in order:
        expected[:, agent] = running
        running = running * np.exp(new[:, agent]) / np.exp(old[:, agent])
    np.testing.assert_allclose(factors, expected, rtol=1e-5)
    assert np.all(np.asarray(factors)[:, order[0]] == 1.0)


@pytest.fixture(scope="module")
def built() -> dict[str, tuple]:
    """Each baseline over SPEC's three agents, with its initial params (initialised once)."""
    batch = fixed_batch()
    cases = {}
    for algo in ("mappo", "happo", "triple_bert"):
        algorithm = build_algorithm(algo, NETWORK, SPEC)
        init = jax.jit(algorithm.init)
        cases[algo] = algorithm, init(jax.random.PRNGKey(0), batch.obs[0], batch.action_mask[0])
    return cases


@pytest.fixture(scope="module")
def happo_setup(built: dict[str, tuple]) -> tuple[LearnerSetup, HAPPO, dict, Batch]:
    """A trainer setup whose algorithm is HAPPO over SPEC, its params and a fixed batch."""
    setup = trainer_lib.build_setup(load_config(overrides=["algo=happo", *TINY])).learner
    algorithm, params = built["happo"]
    return dataclasses.replace(setup, algorithm=algorithm), algorithm, params, fixed_batch()


def happo_phase(setup: LearnerSetup, algorithm: HAPPO, batch: Batch) -> object:
    """An agent's phase as HAPPO's update runs it: on its actor's slice and its batch column."""
    @jax.jit
    def phase(agent: jax.Array, params: dict, state: object, key: jax.Array) -> tuple:
        return agent_phase(setup.optimizer, partial(algorithm.agent_loss, 0), agent, params,
                           state, agent_columns(batch, agent), key, setup.config.ppo)

    return phase


def test_happo_phase_moves_only_its_agent_and_keeps_the_others_moments(happo_setup: tuple) -> None:
    setup, algorithm, params, batch = happo_setup
    state = setup.optimizer.init(params)
    phase = happo_phase(setup, algorithm, batch)

    after_1, state_1, _ = phase(1, params, state, jax.random.PRNGKey(1))
    after_0, state_0, _ = phase(0, after_1, state_1, jax.random.PRNGKey(2))
    for agent, before, after in [(1, params, after_1), (0, after_1, after_0)]:
        for other in {0, 1, 2} - {agent}:
            for a, b in zip(rows(before, other), rows(after, other)):
                np.testing.assert_array_equal(a, b)
        assert differ(rows(before, agent), rows(after, agent))
        for a, b in zip(jax.tree.leaves(before["critic"]), jax.tree.leaves(after["critic"])):
            np.testing.assert_array_equal(a, b)
    for moment in ("mu", "nu"):
        moments_1, moments_0 = tree_get(state_1, moment), tree_get(state_0, moment)
        for a, b in zip(rows(moments_1, 1), rows(moments_0, 1)):
            np.testing.assert_array_equal(a, b)
        assert all(np.all(np.asarray(leaf[2]) == 0) for leaf in jax.tree.leaves(moments_0["actor"]))


def test_happo_phase_on_its_actors_slice_equals_the_masked_whole_tree(happo_setup: tuple) -> None:
    """The phase cut to one actor and its column of the batch gives the numbers of training the
    whole tree on the whole batch with every other actor and the critic masked (their
    gradients zero, their moments kept)."""
    setup, algorithm, params, batch = happo_setup
    ppo = setup.config.ppo
    state = setup.optimizer.init(params)
    sliced = happo_phase(setup, algorithm, batch)

    @jax.jit
    def masked(agent: jax.Array, params: dict, state: object, key: jax.Array) -> tuple:
        def loss(whole: dict, minibatch: Batch, ppo: PPOConfig) -> tuple:
            own = {"actor": jax.tree.map(lambda x: x[agent], whole["actor"]),
                   "critic": whole["critic"]}
            return algorithm.agent_loss(agent, own, minibatch, ppo)

        is_agent = jnp.arange(SPEC.num_agents) == agent
        mask = {"actor": jax.tree.map(lambda x: is_agent.reshape(-1, *(1,) * (x.ndim - 1)),
                                      params["actor"]),
                "critic": jax.tree.map(lambda _: jnp.asarray(False), params["critic"])}
        return train_phase(setup.optimizer, loss, mask, params, state, batch, key, ppo)

    expected_params, expected_state = params, state
    got_params, got_state = params, state
    for agent, seed in ((2, 5), (0, 6)):
        expected_params, expected_state, expected_metrics = masked(
            agent, expected_params, expected_state, jax.random.PRNGKey(seed))
        got_params, got_state, got_metrics = sliced(
            agent, got_params, got_state, jax.random.PRNGKey(seed))
        for want, got in zip(jax.tree.leaves((expected_params, expected_state)),
                             jax.tree.leaves((got_params, got_state)), strict=True):
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-7)
        for key in ("policy_loss", "entropy", "grad_norm", "grad_norm_actor"):
            assert float(got_metrics[key]) == pytest.approx(float(expected_metrics[key]),
                                                            rel=1e-5), key
    assert differ(rows(params, 2), rows(got_params, 2))
    assert int(tree_get(got_state, "count")) == 2 * ppo.epochs * ppo.num_minibatches


def test_happo_update_trains_every_actor_then_the_critic_with_own_step_counts(
    happo_setup: tuple,
) -> None:
    setup, algorithm, params, batch = happo_setup
    state = setup.optimizer.init(params)
    optimise = jax.jit(
        lambda p, s, key: algorithm.update(setup.optimizer, p, s, batch, key, setup.config.ppo)
    )
    new_params, new_state, metrics = optimise(params, state, jax.random.PRNGKey(3))
    for agent in range(SPEC.num_agents):
        assert differ(rows(params, agent), rows(new_params, agent)), agent
    assert differ(jax.tree.leaves(params["critic"]), jax.tree.leaves(new_params["critic"]))
    ppo = setup.config.ppo
    assert int(tree_get(new_state, "count")) == ppo.epochs * ppo.num_minibatches
    assert all(np.isfinite(float(metrics[key])) for key in LOSS_METRICS)


@pytest.mark.parametrize("n, d", [(3, 5), (40, 2)])
def test_the_actors_agent_ids_in_closed_form_equal_the_explicit_one_hot(n: int, d: int) -> None:
    """MAPPO's actor on o_i with `agent_ids` gives the outputs of the same parameters on the
    explicit [o_i; one-hot(i)], and initialises exactly those parameters."""
    implicit = MLPActor(16, 4, True, 0.01, agent_ids=n)
    explicit = MLPActor(16, 4, True, 0.01)
    keys = jax.random.split(jax.random.PRNGKey(n), 3)
    obs = 3.0 * jax.random.normal(keys[0], (2, n, d)) + 1.0
    mask = jnp.ones((2, n, 4), bool)
    with_ids = jnp.concatenate([obs, jnp.broadcast_to(jnp.eye(n), (2, n, n))], axis=-1)
    params = implicit.init(keys[1], obs, mask)
    assert jax.tree.structure(params) == jax.tree.structure(explicit.init(keys[1], with_ids, mask))
    for got, want in zip(jax.tree.leaves(params),
                         jax.tree.leaves(explicit.init(keys[1], with_ids, mask))):
        np.testing.assert_array_equal(got, want)
    leaves = jax.tree.leaves(params)
    noise = jax.random.split(keys[2], len(leaves))
    params = jax.tree.unflatten(jax.tree.structure(params), [
        leaf + 0.5 * jax.random.normal(key, leaf.shape) for leaf, key in zip(leaves, noise)])
    got = np.asarray(implicit.apply(params, obs, mask)[0])
    want = np.asarray(explicit.apply(params, with_ids, mask)[0])
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * np.abs(want).max())


def test_triple_bert_permutes_distributions_with_agents_and_keeps_the_value(built: dict) -> None:
    algorithm, params = built["triple_bert"]
    batch = fixed_batch(seed=2)
    permutation = np.array([2, 0, 1])
    apply = jax.jit(lambda o, m: algorithm.network.apply(params, o, m))
    original = apply(batch.obs, batch.action_mask)
    permuted = apply(batch.obs[:, permutation], batch.action_mask[:, permutation])
    np.testing.assert_allclose(permuted.value, original.value, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(
        permuted.action_params, original.action_params[:, permutation], rtol=1e-5, atol=1e-5
    )
    value = jax.jit(jax.vmap(algorithm.value, in_axes=(None, 0)))(params, batch.obs)
    np.testing.assert_allclose(value, original.value, rtol=1e-5, atol=1e-6)


def test_triple_bert_loss_is_the_joint_ratio_objective_on_a_fixed_batch(built: dict) -> None:
    algorithm, params = built["triple_bert"]
    batch = fixed_batch()
    ppo = PPOConfig(clip_eps=0.2)
    total, metrics = jax.jit(algorithm.loss, static_argnums=2)(params, batch, ppo)
    output = jax.jit(algorithm.network.apply)(params, batch.obs, batch.action_mask)
    logits, values = (np.asarray(x, np.float64) for x in (output.action_params, output.value))
    expected = numpy_cmat_loss(logits, values, batch, ppo)
    for key in ("policy_loss", "entropy", "value_loss"):
        assert float(metrics[key]) == pytest.approx(expected[key], rel=1e-4, abs=1e-5), key
    assert float(total) == pytest.approx(expected["total"], rel=1e-4, abs=1e-5)


@pytest.mark.parametrize("algo", ["mappo", "happo", "triple_bert"])
def test_masked_actions_are_never_sampled(algo: str, built: dict) -> None:
    algorithm, params = built[algo]
    batch = fixed_batch(seed=3, size=64)
    mask = np.asarray(batch.action_mask)
    act = jax.jit(jax.vmap(algorithm.act, in_axes=(None, 0, 0, 0)))
    acted = act(params, batch.obs, batch.action_mask, jax.random.split(jax.random.PRNGKey(1), 64))
    assert np.take_along_axis(mask, np.asarray(acted.actions)[..., None], -1).all()
    assert np.all(np.isfinite(np.asarray(acted.log_probs)))
    greedy = jax.jit(jax.vmap(algorithm.greedy, in_axes=(None, 0, 0)))
    chosen = greedy(params, batch.obs, batch.action_mask)
    assert np.take_along_axis(mask, np.asarray(chosen)[..., None], -1).all()


@pytest.mark.parametrize("algo", ["mappo", "happo"])
def test_identical_observations_give_each_agent_its_own_distribution(
    algo: str, built: dict
) -> None:
    """MAPPO's shared actor tells agents apart by the one-hot id; HAPPO's actors are separate."""
    algorithm, params = built[algo]
    assert isinstance(algorithm, MAPPO)
    obs = jnp.broadcast_to(jnp.arange(5.0), (3, 5))
    logits = np.asarray(jax.jit(algorithm.policy)(params, obs, jnp.ones((3, 4), bool))[0])
    for i, j in [(0, 1), (0, 2), (1, 2)]:
        assert np.abs(logits[i] - logits[j]).max() > 1e-6
