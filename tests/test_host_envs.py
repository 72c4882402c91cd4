"""Host environments: the PettingZoo, MaMuJoCo and GRF adapters, worker pools and their faults,
and `HostTrainer` learning through them.

The toy PettingZoo envs below are referred to by id as `pettingzoo:<this module>:<factory>`, so
worker processes (spawned) import this module to build them.
"""

from __future__ import annotations

import csv
import ctypes.util
import importlib.util
import json
import logging
import os
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar

import gymnasium.spaces as spaces
import jax
import numpy as np
import pytest
from pettingzoo import ParallelEnv

from cmat.cli import main
from cmat.config import TrainConfig
from cmat.envs import make_env
from cmat.envs.host import make_host_env
from cmat.envs.host.pool import InProcessPool, WorkerPool
from cmat.errors import CmatError
from cmat.resolve import load_config
from cmat.runners.base import TrainerState
from cmat.runners.host import HostTrainer

pytestmark = pytest.mark.quick_compiles

HERE = __name__
HAS_MUJOCO = importlib.util.find_spec("gymnasium_robotics") is not None
HAS_GRF = importlib.util.find_spec("gfootball") is not None
needs_mujoco = pytest.mark.skipif(
    not HAS_MUJOCO, reason="MaMuJoCo needs the [mujoco] extra: pip install -e '.[mujoco]'"
)
needs_grf = pytest.mark.skipif(
    not HAS_GRF, reason="gfootball is not installed: build it with scripts/install_grf.sh"
)


class SignalGame(ParallelEnv):
    """A 2-agent coordination game whose optimum needs communication through the team policy.

    Each step a cue c ∈ {0, 1, 2} is drawn. The scout observes c (one-hot, 3 floats); the
    striker observes a constant (1 float: sizes differ, so padding is exercised). Both pick one of
    4 actions; action 3 is masked out for the striker (its mask comes in the info dict, the
    scout's in an observation dict). The team scores 1 when both pick c, else 0. Episodes last 5
    steps; an episode is won when all 5 steps scored. Optimal return: 5. The best a team can do
    without sharing the cue is 5/3 (the striker guesses).
    """

    metadata: ClassVar[dict[str, Any]] = {"name": "signal_game", "has_win_rate": True}
    LENGTH = 5

    def __init__(self, order: tuple[int, int] = (0, 1), fail_at: int | None = None) -> None:
        names = ["scout", "striker"]
        self.possible_agents = [names[i] for i in order]
        self.agents: list[str] = []
        self.fail_at = fail_at
        self.total_steps = 0
        self._rng = np.random.default_rng(0)

    def observation_space(self, agent: str) -> spaces.Space:
        if agent == "scout":
            return spaces.Dict({
                "observation": spaces.Box(0.0, 1.0, (3,), np.float32),
                "action_mask": spaces.MultiBinary(4),
            })
        return spaces.Box(0.0, 1.0, (1,), np.float32)

    def action_space(self, agent: str) -> spaces.Space:
        return spaces.Discrete(4)

    def _observe(self) -> tuple[dict[str, Any], dict[str, Any]]:
        cue = np.eye(3, dtype=np.float32)[self._cue]
        obs = {"scout": {"observation": cue, "action_mask": np.ones(4, np.int8)},
               "striker": np.ones(1, np.float32)}
        infos = {"scout": {}, "striker": {"action_mask": np.array([1, 1, 1, 0], np.int8)}}
        return obs, infos

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self.agents = list(self.possible_agents)
        self._t, self._score = 0, 0
        self._cue = int(self._rng.integers(3))
        return self._observe()

    def step(self, actions: dict[str, int]) -> tuple[dict, dict, dict, dict, dict]:
        self.total_steps += 1
        if self.fail_at is not None and self.total_steps == self.fail_at:
            raise RuntimeError("simulated simulator crash")
        assert actions["striker"] != 3, "a masked action was sent"
        hit = float(actions["scout"] == self._cue and actions["striker"] == self._cue)
        self._t += 1
        self._score += int(hit)
        end = self._t >= self.LENGTH
        self._cue = int(self._rng.integers(3))
        obs, infos = self._observe()
        if end:
            for info in infos.values():
                info["won"] = self._score == self.LENGTH
            self.agents = []
        rewards = {agent: hit for agent in self.possible_agents}
        terminations = {agent: end for agent in self.possible_agents}
        truncations = {agent: False for agent in self.possible_agents}
        return obs, rewards, terminations, truncations, infos


class ReachGame(ParallelEnv):
    """A continuous 3-agent game: agent i's Box action has i+1 entries in [-0.2, 0.3] (different
    sizes: padding); the team reward is -mean squared distance of every entry to 0.1. Agents
    observe a private random vector of size 2 + i. Episodes last 10 steps. `order` permutes the
    agents; each agent's observation depends only on its identity, not on its position."""

    metadata: ClassVar[dict[str, Any]] = {"name": "reach_game"}
    LOW, HIGH, TARGET = -0.2, 0.3, 0.1

    def __init__(self, order: tuple[int, ...] = (0, 1, 2)) -> None:
        self.possible_agents = [f"arm_{i}" for i in order]
        self.agents: list[str] = []
        self.received: list[np.ndarray] = []
        self._rng = np.random.default_rng(0)

    def observation_space(self, agent: str) -> spaces.Space:
        return spaces.Box(-np.inf, np.inf, (2 + int(agent[-1]),), np.float32)

    def action_space(self, agent: str) -> spaces.Space:
        return spaces.Box(self.LOW, self.HIGH, (1 + int(agent[-1]),), np.float32)

    def _observe(self) -> dict[str, np.ndarray]:
        return {agent: self._vectors[agent] * (1 + self._t) for agent in self.possible_agents}

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self._vectors = {
            f"arm_{i}": self._rng.normal(size=2 + i).astype(np.float32) for i in range(3)
        }
        self.agents, self._t = list(self.possible_agents), 0
        return self._observe(), {agent: {} for agent in self.agents}

    def step(self, actions: dict[str, np.ndarray]) -> tuple[dict, dict, dict, dict, dict]:
        self.received.extend(actions.values())
        self._t += 1
        error = np.mean(np.concatenate([(a - self.TARGET) ** 2 for a in actions.values()]))
        end = self._t >= 10
        if end:
            self.agents = []
        agents = self.possible_agents
        return (self._observe(), {a: -float(error) for a in agents}, {a: end for a in agents},
                {a: False for a in agents}, {a: {} for a in agents})


class RelayGame(ParallelEnv):
    """Agent "b" terminates after the first step, "a" after the third; records what is sent."""

    metadata: ClassVar[dict[str, Any]] = {"name": "relay_game"}

    def __init__(self) -> None:
        self.possible_agents = ["a", "b"]
        self.agents: list[str] = []
        self.sent: list[dict[str, int]] = []

    def observation_space(self, agent: str) -> spaces.Space:
        return spaces.Discrete(3)  # flattened to a one-hot

    def action_space(self, agent: str) -> spaces.Space:
        return spaces.Discrete(2, start=1)

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        self.agents, self._t = ["a", "b"], 0
        return {"a": 0, "b": 0}, {"a": {}, "b": {}}

    def step(self, actions: dict[str, int]) -> tuple[dict, dict, dict, dict, dict]:
        self.sent.append(dict(actions))
        self._t += 1
        ended = {"a": self._t >= 3, "b": True}
        rewards = {agent: float(self._t) for agent in self.agents}
        obs = {agent: min(self._t, 2) for agent in self.agents}
        self.agents = [agent for agent in self.agents if not ended[agent]]
        return obs, rewards, ended, {"a": False, "b": False}, {"a": {}, "b": {}}


def relay_game() -> RelayGame:
    return RelayGame()


def signal_game(**kwargs: Any) -> SignalGame:
    return SignalGame(**kwargs)


def reach_game(**kwargs: Any) -> ReachGame:
    return ReachGame(**kwargs)


SIGNAL = f"pettingzoo:{HERE}:signal_game"
REACH = f"pettingzoo:{HERE}:reach_game"
SMALL = ["network.n_embd=16", "ppo.epochs=2", "eval_episodes=4", "log_interval=1"]


def config(env: str, *overrides: str) -> TrainConfig:
    return load_config(overrides=[f"env={env}", *SMALL, *overrides])


# ------------------------------------------------------------------------------ the adapters
def test_pettingzoo_adapter_pads_masks_and_resets() -> None:
    env = make_host_env(SIGNAL)
    spec = env.spec
    assert (spec.num_agents, spec.obs_dim, spec.action_dim, spec.discrete) == (2, 3, 4, True)
    assert spec.has_win_rate and spec.max_episode_steps == 1000
    first = env.reset(seed=3)
    assert first.obs.shape == (2, 3) and first.obs.dtype == np.float32
    np.testing.assert_array_equal(first.obs[1], [1.0, 0.0, 0.0])  # the striker's 1 float, padded
    np.testing.assert_array_equal(first.action_mask, [[1, 1, 1, 1], [1, 1, 1, 0]])
    cue = int(np.argmax(first.obs[0]))
    timesteps = [env.step(np.array([cue, cue]))]
    for _ in range(4):
        cue = int(np.argmax(timesteps[-1].obs[0]))
        timesteps.append(env.step(np.array([cue, cue])))
    assert [t.reward for t in timesteps] == [1.0] * 5
    assert [t.done for t in timesteps] == [False] * 4 + [True]
    assert timesteps[-1].won
    # auto-reset: the done step already shows the next episode's first observation
    assert timesteps[-1].obs[0].sum() == 1.0 and not env.step(np.array([0, 0])).done


def test_an_agent_done_before_the_others_is_dead_until_the_episode_ends() -> None:
    env = make_host_env(f"pettingzoo:{HERE}:relay_game")
    assert (env.spec.obs_dim, env.spec.action_dim) == (3, 2)
    env.reset(seed=0)
    first, second, third = (env.step(np.array([1, 0])) for _ in range(3))
    np.testing.assert_array_equal(first.obs, [[0, 1, 0], [0, 0, 0]])  # b is dead: zeros
    np.testing.assert_array_equal(first.action_mask, [[1, 1], [1, 0]])  # and only action 0
    assert (first.reward, first.done) == (1.0, False)
    assert (second.reward, second.done, third.done) == (2.0, False, True)
    # actions go to live agents only, shifted by the space's start
    assert env.env.sent == [{"a": 2, "b": 1}, {"a": 2}, {"a": 2}]


def test_agent_ids_are_appended() -> None:
    env = make_host_env(SIGNAL, agent_id=True)
    timestep = env.reset(seed=0)
    assert env.spec.obs_dim == 5
    np.testing.assert_array_equal(timestep.obs[:, 3:], np.eye(2))


@pytest.mark.parametrize(
    "env_id, message",
    [
        ("pettingzoo:no_such_module_xyz:f", "cannot import 'no_such_module_xyz'"),
        (f"pettingzoo:{HERE}:no_factory", "has no 'no_factory'"),
        ("pettingzoo:signal_game", "must look like pettingzoo:package.module:factory"),
        ("mamujoco:Ant-9x1", "unknown MaMuJoCo factorization '9x1' for Ant; available: 2x4, "
                             "2x4d, 4x2, 8x1"),
        ("mamujoco:Dog-4x1", "unknown MaMuJoCo scenario 'Dog'"),
        ("mamujoco:HalfCheetah", "no factorization in 'mamujoco:HalfCheetah'"),
        ("mamujoco:ManySegmentAnt-x2", "expected NxM"),
        ("grf:11_vs_11_stochastic", "unknown GRF scenario '11_vs_11_stochastic'; available: "
                                    "academy_3_vs_1_with_keeper"),
    ],
)
def test_bad_ids_are_one_line_errors(env_id: str, message: str) -> None:
    with pytest.raises(CmatError, match=None) as raised:
        make_host_env(env_id)
    assert message in str(raised.value) and "\n" not in str(raised.value)


def test_factory_errors_and_the_in_graph_registry(capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(CmatError, match="the factory raised TypeError"):
        make_host_env(SIGNAL, colour="red")
    with pytest.raises(CmatError, match="is a host environment"):
        make_env(SIGNAL)
    assert main(["train", "--env", "mamujoco:Ant-3x1", "--steps", "10"]) == 2
    assert capsys.readouterr().err.startswith("cmat: error: unknown MaMuJoCo factorization")


# ---------------------------------------------------------------------- pools and their faults
def test_worker_pool_matches_in_process_pool() -> None:
    seeds = [5, 6, 7]
    local, remote = InProcessPool(SIGNAL, {}, seeds), WorkerPool(SIGNAL, {}, seeds, workers=2)
    try:
        a, b = local.reset(), remote.reset()
        for step in range(12):
            for x, y in zip(a, b):
                np.testing.assert_array_equal(x, y)
            actions = np.stack([np.full(2, step % 3)] * 3)
            a, b = local.step(actions), remote.step(actions)
        assert len(set(remote.worker_pids())) == 2
    finally:
        local.close()
        remote.close()


def test_env_that_raises_is_restarted(caplog: pytest.LogCaptureFixture) -> None:
    pool = InProcessPool(SIGNAL, {"fail_at": 3}, [0, 1])
    pool.reset()
    with caplog.at_level(logging.WARNING, logger="cmat.host"):
        batches = [pool.step(np.zeros((2, 2), int)) for _ in range(4)]
    # both envs raise at their 3rd step: that step ends their episodes (truncated)
    assert [bool(b.done[0]) for b in batches] == [False, False, True, False]
    assert batches[2].reward.tolist() == [0.0, 0.0]
    assert pool.counters()["env_restarts"].tolist() == [1, 1]
    assert "restarted it, its episode counts as truncated" in caplog.text


# --------------------------------------------------------------------------- the host runner
# Every HostTrainer compiles its programs (about 15-50 s each on this 2-core machine), so the
# tests share a few trained ones.
@pytest.fixture(scope="module")
def signal_run() -> Iterator[tuple[HostTrainer, TrainerState, dict[str, np.ndarray]]]:
    """CMAT trained on the signal game, 2 seeds, environments in 2 worker processes."""
    trainer = HostTrainer(config(
        SIGNAL, "num_envs=16", "rollout_length=25", "total_steps=2400", "seeds=2",
        "ppo.epochs=8", "network.n_embd=32", "ppo.clip_eps=0.2", "eval_episodes=16",
        "log_interval=6", "host_workers=2",
    ))
    state, metrics = trainer.train_chunk(trainer.init())
    yield trainer, state, metrics
    trainer.close()


@pytest.mark.slow
def test_cmat_learns_the_signal_game_through_the_adapter(signal_run: Any) -> None:
    """Slow suite with the other test of `signal_run` (its two worker processes and 8-epoch
    updates take 80-110 s on 2 cores; the host runner's fast tests are the pool's, the sampled
    evaluation's and the permutation's). Measured: 6 updates of 16 envs x 25 steps (2,400 steps)
    reach the optimum greedy return of 5 (win rate 1) for seeds 0 and 1; without the cue shared,
    5/3 is the best."""
    trainer, state, metrics = signal_run
    result = trainer.evaluate(state, 16)
    np.testing.assert_allclose(result["episode_return"], [5.0, 5.0])
    np.testing.assert_allclose(result["win_rate"], [1.0, 1.0])
    assert metrics["env_steps"].tolist() == [2400, 2400]
    assert np.all(metrics["episode_return"] > 5 / 12)  # random play's mean, pooled over the chunk


@pytest.mark.slow
def test_killed_worker_and_a_restored_checkpoint_are_survived(
    signal_run: Any, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    trainer, state, _ = signal_run
    restored = trainer.from_bytes(trainer.to_bytes(state))  # host episodes restart
    pool, calls = trainer._pool, []

    def step_then_kill(actions: np.ndarray) -> Any:
        calls.append(1)
        if len(calls) == 10:  # mid-rollout: SIGKILL the first worker, then step
            os.kill(pool.worker_pids()[0], signal.SIGKILL)
        return WorkerPool.step(pool, actions)

    monkeypatch.setattr(pool, "step", step_then_kill)
    with caplog.at_level(logging.WARNING, logger="cmat.host"):
        after, metrics = trainer.train_chunk(restored)
    assert "worker process 0 died" in caplog.text
    assert trainer.env_counters()["env_restarts"].tolist() == [16, 0]  # worker 0: seed 0's envs
    assert trainer.env_steps(after) == 4800 and np.isfinite(metrics["episode_return"]).all()
    assert np.all(trainer.evaluate(after, 16)["episode_return"] >= 4.0)


@pytest.fixture(scope="module")
def reach_run() -> Iterator[tuple[HostTrainer, TrainerState]]:
    """CMAT trained for one update on the continuous reach game, in-process."""
    trainer = HostTrainer(config(REACH, "num_envs=2", "rollout_length=10", "host_workers=0"))
    state, _ = trainer.train_chunk(trainer.init())
    yield trainer, state
    trainer.close()


def test_continuous_actions_are_mapped_onto_each_agents_bounds(reach_run: Any) -> None:
    trainer, _ = reach_run
    spec = trainer.env_spec
    assert (spec.action_dim, spec.discrete, spec.action_low, spec.action_high) == (3, False, -1, 1)
    received = [a for env in trainer._pool.envs for a in env.env.received]
    assert len(received) == 2 * 10 * 3 and [a.shape for a in received[:3]] == [(1,), (2,), (3,)]
    values = np.concatenate(received)
    assert values.min() >= ReachGame.LOW and values.max() <= ReachGame.HIGH
    # the policy's N(0, 0.37) in [-1, 1] reaches most of [-0.2, 0.3] around its midpoint
    assert values.min() < -0.1 and values.max() > 0.2
    assert abs(np.median(values) - (ReachGame.LOW + ReachGame.HIGH) / 2) < 0.05


def test_permuting_agents_permutes_the_policy_through_the_host_runner(reach_run: Any) -> None:
    """CMAT on a continuous env whose agents come in another order: the per-agent Gaussians
    of the host runner's policy step permute with them; the team value and the greedy return
    do not change."""
    plain, state = reach_run
    order = [2, 0, 1]
    permuted = HostTrainer(config(REACH, "num_envs=2", "rollout_length=10", "host_workers=0",
                                  "env_kwargs.order=[2,0,1]"))
    try:
        obs, mask = plain._start_episodes()[:2]
        other_obs, other_mask = permuted._start_episodes()[:2]
        np.testing.assert_array_equal(other_obs, obs[:, order])
        network = plain.learner_setup.algorithm.network
        params = jax.tree.map(lambda x: x[0], state.learner.params)

        def means(obs: np.ndarray, mask: np.ndarray) -> jax.Array:
            return jax.vmap(lambda o, m: network.apply(params, o, m).action_params)(obs, mask)

        np.testing.assert_allclose(means(other_obs, other_mask), means(obs, mask)[:, order],
                                   atol=1e-5)
        learner = state.learner
        no_state = np.zeros((1, obs.shape[0], plain.env_spec.state_dim), np.float32)
        start = np.ones((1, obs.shape[0]), bool)
        _, acted, _, _ = plain._policy(learner.params, learner.rng, (), obs[None], mask[None],
                                       no_state, start)
        _, other_acted, _, _ = permuted._policy(learner.params, learner.rng, (), other_obs[None],
                                                other_mask[None], no_state, start)
        np.testing.assert_allclose(acted.value, other_acted.value, atol=1e-5)
        np.testing.assert_allclose(plain.evaluate(state, 4)["episode_return"],
                                   permuted.evaluate(state, 4)["episode_return"], rtol=1e-4)
    finally:
        permuted.close()


@pytest.mark.slow
@needs_mujoco
def test_halfcheetah_6x1_through_the_cli(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Slow suite (80 s on 2 cores): MuJoCo's continuous control through the CLI; the fast suite
    maps continuous actions through the host runner (`reach_run`)."""
    out = tmp_path / "cheetah"
    assert main(["train", "--env", "mamujoco:HalfCheetah-6x1", "--steps", "400", "--out",
                 str(out), "--set", "num_envs=4", "rollout_length=50", "network.n_embd=16",
                 "ppo.epochs=1", "eval_episodes=1", "log_interval=2",
                 "env_kwargs.max_episode_steps=100"]) == 0
    with (out / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert [(r["kind"], r["env_steps"]) for r in rows] == [("train", "400"), ("eval", "400"),
                                                            ("absolute", "400")]
    assert all(r["win_rate"] == "nan" for r in rows)
    assert (float(rows[0]["env_restarts"]), float(rows[0]["env_nonfinite"])) == (0, 0)
    assert np.isfinite(float(rows[1]["episode_return"]))
    capsys.readouterr()
    assert main(["eval", "--run", str(out), "--episodes", "1", "--seed", "400"]) == 0
    assert float(rows[1]["episode_return"]) == pytest.approx(
        json.loads(capsys.readouterr().out)["per_seed"][0]["episode_return"], rel=1e-5)
    assert not Path("MUJOCO_LOG.TXT").exists()
    if ctypes.util.find_library("OSMesa") is not None:  # headless MuJoCo drawing
        from PIL import Image

        gif = tmp_path / "cheetah.gif"
        assert main(["render", "--run", str(out), "--max-steps", "6", "--out", str(gif)]) == 0
        with Image.open(gif) as frames:
            assert frames.n_frames == 6
            frames.seek(5)
            picture = np.asarray(frames.convert("RGB"))
        assert picture.std() > 10  # a scene, not a blank frame


@needs_mujoco
@pytest.mark.parametrize("env_id, agents", [("mamujoco:Ant-8x1", 8), ("mamujoco:Walker2d-6x1", 6)])
def test_one_joint_per_agent_factorizations(env_id: str, agents: int) -> None:
    env = make_host_env(env_id)
    timestep = env.reset(seed=0)
    assert (env.spec.num_agents, env.spec.action_dim, env.spec.discrete) == (agents, 1, False)
    for _ in range(3):
        timestep = env.step(np.full((agents, 1), 2.0))  # out of bounds: clipped
    assert np.isfinite(timestep.obs).all() and np.isfinite(timestep.reward)
    env.close()


@pytest.mark.slow
@needs_grf
@pytest.mark.parametrize("scenario, agents", [
    ("academy_3_vs_1_with_keeper", 3), ("academy_counterattack_easy", 4),
    ("academy_pass_and_shoot_with_keeper", 2),
])
def test_grf_scenarios_step_and_score(scenario: str, agents: int) -> None:
    env = make_host_env(f"grf:{scenario}")
    timestep = env.reset(seed=0)
    assert timestep.obs.shape == (agents, 115) and env.spec.has_win_rate
    done = 0
    for _ in range(900):
        timestep = env.step(np.random.default_rng(0).integers(19, size=agents))
        done += timestep.done
    assert done >= 2
    env.close()


@pytest.mark.slow
@needs_grf
def test_grf_trains_in_workers() -> None:
    trainer = HostTrainer(config("grf:academy_3_vs_1_with_keeper", "num_envs=4",
                                 "rollout_length=50", "host_workers=2"))
    try:
        state, metrics = trainer.train_chunk(trainer.init())
        assert np.isfinite(metrics["policy_loss"]).all()
        assert 0.0 <= trainer.evaluate(state, 2)["win_rate"][0] <= 1.0
    finally:
        trainer.close()


def test_sampled_evaluation_through_the_host_runner() -> None:
    """A fresh policy is near uniform: sampled episodes of the signal game score 1/4 × 1/3 per
    step (the striker's action 3 is masked), 5/12 per episode (sd 0.62), where greedy play
    repeats one joint action and scores 5/3 or 0 on average; the same episode seed replays the
    same samples, another draws others."""
    trainer = HostTrainer(config(SIGNAL, "num_envs=16", "host_workers=0", "eval_actions=sample"))
    try:
        state = trainer.init()
        episodes = 256
        mean = float(trainer.evaluate(state, episodes)["episode_return"][0])
        assert abs(mean - 5 / 12) < 4 * 0.62 / np.sqrt(episodes), mean
        assert float(trainer.evaluate(state, episodes)["episode_return"][0]) == mean
        other = float(trainer.evaluate(state, episodes, episode_seed=1)["episode_return"][0])
        assert other != mean and abs(other - 5 / 12) < 4 * 0.62 / np.sqrt(episodes), other
    finally:
        trainer.close()


def test_an_evaluation_resets_each_simulator_once_per_episode(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Each slot is reset (seeded) at the start of an evaluation and between its episodes, and
    not again after its last one: the next evaluation's seeded reset would repeat that work."""
    seeds: list[int | None] = []
    reset = SignalGame.reset

    def counted(self: SignalGame, seed: int | None = None, options: Any = None) -> Any:
        seeds.append(seed)
        return reset(self, seed=seed, options=options)

    monkeypatch.setattr(SignalGame, "reset", counted)
    trainer = HostTrainer(config(SIGNAL, "num_envs=2", "seeds=2", "host_workers=0"))
    state = trainer.init()
    for episodes in (2, 5):  # per seed, on 2 slots: 1 + 1, then 3 + 2 episodes
        seeds.clear()
        result = trainer.evaluate(state, episodes, episode_seed=7)
        assert len(seeds) == 2 * episodes, seeds  # 2 seeds: one reset per episode
        assert seeds.count(None) == 2 * (episodes - 2)  # between a slot's episodes only
        assert result["episode_return"].shape == (2,)
    pool = trainer._eval_pool
    assert pool is not None
    batch = pool.step(np.zeros((4, 2), int), np.zeros(4, bool))  # resting: no simulator call
    seeds.clear()
    assert not batch.done.any() and not batch.reward.any() and seeds == []
