"""The trainer: CMAT's loss on a fixed batch, the target critic, seeds, and tasks actually
learned."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cmat.algorithms.base import Batch
from cmat.algorithms.cmat.algorithm import CMAT
from cmat.config import NetworkConfig, PPOConfig, TrainConfig
from cmat.envs.protocol import EnvSpec
from cmat.experiments.matrix_games import train_and_count_optimum
from cmat.resolve import load_config
from cmat.runners import trainer as trainer_lib
from cmat.runners.trainer import JaxTrainer

pytestmark = pytest.mark.quick_compiles

TINY = ["num_envs=8", "rollout_length=10", "ppo.epochs=2", "network.n_embd=16", "eval_episodes=4"]


def fixed_batch(seed: int = 0, size: int = 12, agents: int = 3, actions: int = 4) -> Batch:
    rng = np.random.default_rng(seed)
    mask = rng.random((size, agents, actions)) < 0.6
    mask[..., 1] = True
    chosen = np.array([[rng.choice(np.flatnonzero(m)) for m in team] for team in mask])
    return Batch(
        obs=jnp.asarray(rng.normal(size=(size, agents, 5)), jnp.float32),
        action_mask=jnp.asarray(mask),
        actions=jnp.asarray(chosen),
        log_probs=jnp.asarray(np.log(rng.uniform(0.1, 0.9, (size, agents))), jnp.float32),
        values=jnp.asarray(rng.normal(size=size), jnp.float32),
        advantages=jnp.asarray(rng.normal(size=size), jnp.float32),
        targets=jnp.asarray(rng.normal(scale=20.0, size=size), jnp.float32),
    )


def numpy_cmat_loss(logits: np.ndarray, values: np.ndarray, batch: Batch, ppo: PPOConfig) -> dict:
    """The paper's objective written out in numpy from the network's raw outputs."""
    shifted = logits - logits.max(-1, keepdims=True)
    log_softmax = shifted - np.log(np.exp(shifted).sum(-1, keepdims=True))
    log_probs = np.take_along_axis(log_softmax, np.asarray(batch.actions)[..., None], -1)[..., 0]
    ratio = np.prod(np.exp(log_probs) / np.exp(np.asarray(batch.log_probs)), axis=-1)
    adv = np.asarray(batch.advantages)
    eps = ppo.clip_eps
    policy = -np.mean(np.minimum(ratio * adv, np.clip(ratio, 1 - eps, 1 + eps) * adv))
    probs = np.exp(log_softmax)
    entropy = np.mean(-np.sum(np.where(probs > 0, probs * log_softmax, 0.0), axis=-1))
    old, targets = np.asarray(batch.values), np.asarray(batch.targets)

    def huber(residual: np.ndarray) -> np.ndarray:
        delta = ppo.huber_delta
        return np.where(np.abs(residual) <= delta, 0.5 * residual**2,
                        delta * (np.abs(residual) - 0.5 * delta))

    clipped = old + np.clip(values - old, -eps, eps)
    value = np.mean(np.maximum(huber(targets - values), huber(targets - clipped)))
    total = policy - ppo.ent_coef * entropy + ppo.value_coef * value
    return {"policy_loss": policy, "entropy": entropy, "value_loss": value, "total": total}


def test_cmat_loss_matches_numpy_reference_on_a_fixed_batch() -> None:
    batch = fixed_batch()
    spec = EnvSpec("test", 3, 5, 4, True, 10, False)
    algorithm = CMAT.build(NetworkConfig(n_embd=16, n_head=2), spec)
    params = jax.jit(algorithm.init)(jax.random.PRNGKey(0), batch.obs[0], batch.action_mask[0])
    ppo = PPOConfig(clip_eps=0.2)
    total, metrics = jax.jit(algorithm.loss, static_argnums=2)(params, batch, ppo)
    output = jax.jit(algorithm.network.apply)(params, batch.obs, batch.action_mask)
    expected = numpy_cmat_loss(
        np.asarray(output.action_params, np.float64), np.asarray(output.value, np.float64), batch,
        ppo,
    )
    for key in ("policy_loss", "entropy", "value_loss"):
        assert float(metrics[key]) == pytest.approx(expected[key], rel=1e-4, abs=1e-5), key
    assert float(total) == pytest.approx(expected["total"], rel=1e-4, abs=1e-5)


def test_joint_ratio_is_one_at_the_collecting_parameters() -> None:
    batch = fixed_batch(seed=1)
    spec = EnvSpec("test", 3, 5, 4, True, 10, False)
    algorithm = CMAT.build(NetworkConfig(n_embd=16), spec)
    params = jax.jit(algorithm.init)(jax.random.PRNGKey(1), batch.obs[0], batch.action_mask[0])
    acted = jax.jit(jax.vmap(algorithm.act, in_axes=(None, 0, 0, 0)))(
        params, batch.obs, batch.action_mask, jax.random.split(jax.random.PRNGKey(2), 12)
    )
    batch = batch._replace(actions=acted.actions, log_probs=acted.log_probs)
    _, metrics = jax.jit(algorithm.loss, static_argnums=2)(params, batch, PPOConfig())
    expected = -float(jnp.mean(batch.advantages))
    assert float(metrics["policy_loss"]) == pytest.approx(expected, abs=1e-5)
    assert float(metrics["approx_kl"]) == pytest.approx(0.0, abs=1e-6)
    assert float(metrics["clip_frac"]) == 0.0


def test_seeds_in_one_program_match_separate_runs() -> None:
    overrides = ["env=matrix:fig1", "total_steps=160", "log_interval=2", *TINY]
    together = JaxTrainer(load_config(overrides=[*overrides, "seeds=2", "seed=3"]))
    alone = JaxTrainer(load_config(overrides=[*overrides, "seeds=1", "seed=4"]))
    state_together, metrics_together = together.train_chunk(together.init())
    state_alone, _metrics_alone = alone.train_chunk(alone.init())
    leaves_together = jax.tree.leaves(state_together.learner.params)
    for both, one in zip(leaves_together, jax.tree.leaves(state_alone.learner.params)):
        np.testing.assert_allclose(both[1], one[0], rtol=1e-4, atol=1e-5)
    assert any(not np.allclose(leaf[0], leaf[1]) for leaf in leaves_together)
    assert metrics_together["env_steps"].tolist() == [160, 160]


def test_make_train_is_one_pure_program() -> None:
    config = load_config(overrides=["env=matrix:fig1", "algo=mappo", "total_steps=240", *TINY])
    state, metrics = jax.jit(trainer_lib.make_train(config))(jax.random.PRNGKey(0))
    assert int(state.learner.update_step) == config.num_updates == 3
    assert metrics["policy_loss"].shape == (3,)
    assert np.all(np.isfinite(np.asarray(metrics["value_loss"])))


@pytest.mark.optimised
def test_fig1_cmat_reaches_the_optimum_in_at_least_9_of_10_seeds() -> None:
    """Paper Fig. 1: the greedy joint action must be (B, B), payoff 100, not the (A, A) trap, at
    the matrix suite's settings and budget (4,000 steps: 10 updates of 16 envs × 25 steps)."""
    config = load_config(overrides=["env=matrix:fig1", "seeds=10", "log_interval=10",
                                    "eval_episodes=2"])
    assert config.num_updates == 10
    at_optimum, joint = train_and_count_optimum(config)
    assert at_optimum >= 9, joint


def greedy_return_gain(config: TrainConfig, episodes: int = 64) -> float:
    """Seed 0's greedy return over `episodes` after one chunk of `config` (its whole budget)
    minus the one before it; asserts the chunk trained the whole budget."""
    trainer = JaxTrainer(config)
    state = trainer.init()
    before = trainer.evaluate(state, episodes)
    state, metrics = trainer.train_chunk(state)
    after = trainer.evaluate(state, episodes)
    assert metrics["env_steps"][0] == config.budget_steps
    return float(after["episode_return"][0] - before["episode_return"][0])


@pytest.mark.slow
def test_smax_3m_improves_on_its_starting_return() -> None:
    """Measured: greedy return 0.2 at init, 1.1-1.5 after 32k-48k steps (win rate 0.3-0.6)."""
    config = load_config(overrides=[
        "env=smax:3m", "total_steps=32000", "log_interval=10", "eval_episodes=64",
    ])
    assert greedy_return_gain(config) >= 0.5


def test_initialisation_runs_lapack_on_one_thread() -> None:
    """The QR of the orthogonal initialisers runs in scipy's OpenBLAS: inside the trainers'
    initialisation context every BLAS/LAPACK pool of the process has one thread, and after it
    the pools have their earlier sizes again (two threads here, whatever the suite's default)."""
    import threadpoolctl

    from cmat.runners.base import single_threaded_lapack

    def blas_threads() -> list[int]:
        return [pool["num_threads"] for pool in threadpoolctl.threadpool_info()
                if pool["user_api"] == "blas"]

    jax.block_until_ready(jnp.linalg.qr(jnp.eye(4)))
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        assert blas_threads() and set(blas_threads()) == {2}
        with single_threaded_lapack():
            assert set(blas_threads()) == {1}
        assert set(blas_threads()) == {2}


def test_sampled_evaluation_draws_actions_from_the_policy() -> None:
    """In a coordination game paying 10 for (A, A) and (B, B) and 0 otherwise, a fresh policy
    is near uniform over A and B for each agent: sampled episodes pay 5 on average (sd 5),
    greedy ones all pay the payoff of the most likely joint action, 0 or 10. The same
    evaluation episode seed replays the same samples, another draws others."""
    episodes = 4096
    game = ["env=matrix:fig1", "env_kwargs.payoff=[[10,0],[0,10]]", *TINY]
    sampled = JaxTrainer(load_config(overrides=[*game, "eval_actions=sample"]))
    greedy = JaxTrainer(load_config(overrides=game))
    state = sampled.init()
    mean = float(sampled.evaluate(state, episodes)["episode_return"][0])
    assert abs(mean - 5.0) < 4 * 5 / np.sqrt(episodes), mean
    assert float(sampled.evaluate(state, episodes)["episode_return"][0]) == mean
    other = float(sampled.evaluate(state, episodes, episode_seed=7)["episode_return"][0])
    assert other != mean and abs(other - 5.0) < 4 * 5 / np.sqrt(episodes), other
    assert float(greedy.evaluate(state, episodes)["episode_return"][0]) in (0.0, 10.0)
