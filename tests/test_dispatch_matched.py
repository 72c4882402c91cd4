"""Matched decoding of a learned dispatch policy (`cmat.envs.dispatch.matched`): the plan is the
conflict-free joint action of highest joint log-probability (against brute force), it is the
greedy joint action wherever that has no conflict, and only policies whose agents decide
independently have the per-agent log-probabilities it scores."""

from __future__ import annotations

import itertools

import jax
import numpy as np
import pytest

from cmat.algorithms import algorithm_names, build_algorithm
from cmat.algorithms.base import Factorised, is_recurrent
from cmat.config import NetworkConfig, PPOConfig
from cmat.envs import make_env
from cmat.envs.dispatch.matched import matched_plan
from cmat.errors import CmatError
from cmat.policy import Policy
from cmat.resolve import load_config

pytestmark = pytest.mark.unit

FACTORISED = {"cmat", "mappo", "happo", "triple_bert"}


def fleet(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A random fleet: log-probs [n, A] over stay, K takes and 2 repositions, a mask that
    always allows staying, and candidate order slots (distinct per vehicle, shared across)."""
    n, k, orders = rng.integers(1, 5), rng.integers(1, 4), rng.integers(1, 5)
    actions = 1 + k + 2
    logits = rng.normal(0, 2, (n, actions))
    mask = rng.random((n, actions)) < 0.7
    mask[:, 0] = True
    log_probs = logits - np.logaddexp.reduce(np.where(mask, logits, -np.inf), axis=1,
                                             keepdims=True)
    candidates = np.stack([rng.choice(orders + 2, k, replace=False) for _ in range(n)])
    return np.where(mask, log_probs, -np.inf), mask, candidates


def conflict_free(actions: tuple[int, ...], candidates: np.ndarray) -> bool:
    k = candidates.shape[1]
    claims = [candidates[i, a - 1] for i, a in enumerate(actions) if 1 <= a <= k]
    return len(claims) == len(set(claims))


def joint(actions: np.ndarray | tuple[int, ...], log_probs: np.ndarray) -> float:
    return float(sum(log_probs[i, a] for i, a in enumerate(actions)))


def test_the_plan_is_the_most_likely_conflict_free_joint_action() -> None:
    rng = np.random.default_rng(0)
    for _ in range(150):
        log_probs, mask, candidates = fleet(rng)
        plan = matched_plan(log_probs, mask, candidates)
        assert mask[np.arange(len(plan)), plan].all()
        assert conflict_free(tuple(plan), candidates)
        best = max(joint(a, log_probs) for a in itertools.product(
            *[np.flatnonzero(row) for row in mask]) if conflict_free(a, candidates))
        assert joint(plan, log_probs) == pytest.approx(best, abs=1e-9)


def test_without_conflicts_the_plan_is_the_greedy_joint_action() -> None:
    rng = np.random.default_rng(1)
    checked = 0
    for _ in range(300):
        log_probs, mask, candidates = fleet(rng)
        greedy = log_probs.argmax(axis=1)
        if conflict_free(tuple(greedy), candidates):
            np.testing.assert_array_equal(matched_plan(log_probs, mask, candidates), greedy)
            checked += 1
    assert checked > 50


def test_only_agents_that_decide_independently_have_log_probs() -> None:
    env = make_env("matrix:fig1")
    _, step = env.reset(jax.random.PRNGKey(0))
    for name in algorithm_names():
        algorithm = build_algorithm(name, NetworkConfig(n_embd=8), env.spec, PPOConfig())
        factorised = isinstance(algorithm, Factorised) and not is_recurrent(algorithm)
        assert factorised == (name in FACTORISED), name
        if not factorised:
            config = load_config(overrides=["env=matrix:fig1", f"algo={name}"])
            policy = Policy(env.spec, config, 0, 0, algorithm, None)
            with pytest.raises(CmatError, match="decodes its agents one after another"):
                policy.log_probs(step.obs, step.action_mask)
            continue
        if name not in ("cmat", "mappo"):  # the others share these two's acting code
            continue
        params = algorithm.init(jax.random.PRNGKey(1), step.obs, step.action_mask)
        policy = Policy(env.spec, load_config(overrides=["env=matrix:fig1", f"algo={name}"]),
                        0, 0, algorithm, params)
        mask = np.array([[True, False], [True, True]])
        log_probs = np.asarray(policy.log_probs(step.obs, mask))
        assert np.isneginf(log_probs[~mask]).all()
        np.testing.assert_allclose(np.exp(log_probs).sum(-1), 1.0, rtol=1e-5)
        np.testing.assert_array_equal(log_probs.argmax(-1), policy.greedy(step.obs, mask))
