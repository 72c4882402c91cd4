"""Host environments that break the rules in ordinary ways: agents that join, leave and come
back, Box bounds far from 0, malformed or non-finite observations and rewards, simulators that
keep crashing. One small ParallelEnv per kind, referred to by id as
`pettingzoo:<this module>:<factory>` (worker processes import this module to build them).
"""

from __future__ import annotations

import logging
import multiprocessing
from pathlib import Path
from typing import Any, ClassVar

import gymnasium.spaces as spaces
import numpy as np
import pytest
from pettingzoo import ParallelEnv

from cmat.cli import main
from cmat.envs.host import make_host_env
from cmat.envs.host.pool import InProcessPool, WorkerPool, make_pool
from cmat.errors import CmatError, SuiteUnavailable
from cmat.render import draw_host
from cmat.resolve import load_config
from cmat.runners.host import HostTrainer

pytestmark = pytest.mark.quick_compiles

HERE = __name__


def error_line(stderr: str) -> str:
    """The one error line that ends stderr (a progress bar may come before it)."""
    assert "Traceback" not in stderr
    line = stderr.strip().splitlines()[-1]
    assert line.startswith("cmat: error: ") and stderr.count("cmat: error") == 1, stderr
    return line


class RosterGame(ParallelEnv):
    """"a" plays from reset; "b" joins at step 2, leaves after step 4 and comes back at step 6;
    10 steps. Each agent observes [1, t/10]. Records the agents each step's actions went to and
    fails if they are not exactly `env.agents`."""

    metadata: ClassVar[dict[str, Any]] = {"name": "roster_game"}
    LENGTH = 10

    def __init__(self) -> None:
        self.possible_agents = ["a", "b"]
        self.agents: list[str] = []
        self.sent: list[list[str]] = []

    def observation_space(self, agent: str) -> spaces.Space:
        return spaces.Box(0.0, 1.0, (2,), np.float32)

    def action_space(self, agent: str) -> spaces.Space:
        return spaces.Discrete(2)

    @staticmethod
    def roster(t: int) -> list[str]:
        return ["a", "b"] if 2 <= t <= 4 or t >= 6 else ["a"]

    def _observe(self) -> dict[str, np.ndarray]:
        return {agent: np.array([1.0, self._t / 10], np.float32) for agent in self.agents}

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        self._t = 0
        self.agents = self.roster(0)
        return self._observe(), {agent: {} for agent in self.agents}

    def step(self, actions: dict[str, int]) -> tuple[dict, dict, dict, dict, dict]:
        assert sorted(actions) == sorted(self.agents), (sorted(actions), self.agents)
        self.sent.append(sorted(actions))
        acting = list(self.agents)
        self._t += 1
        end = self._t >= self.LENGTH
        self.agents = [] if end else self.roster(self._t)
        rewards = {agent: float(actions[agent]) for agent in acting}
        ended = {agent: end or agent not in self.agents for agent in acting}
        return (self._observe(), rewards, ended, {agent: False for agent in acting},
                {agent: {} for agent in acting})


class BoxGame(ParallelEnv):
    """One-step episodes; "left" acts in Box [2, 4], "right" in Box [-10, -6] × [0, 0.5]. The
    team reward is minus the squared distance of the actions to TARGETS (inside the boxes),
    so a policy that reaches them scores 0. `unbounded` makes "right" Box(-inf, inf) ×
    [0, inf)."""

    metadata: ClassVar[dict[str, Any]] = {"name": "box_game"}
    TARGETS: ClassVar[dict[str, np.ndarray]] = {
        "left": np.array([3.5]), "right": np.array([-7.0, 0.4])
    }

    def __init__(self, unbounded: bool = False) -> None:
        self.possible_agents = ["left", "right"]
        self.agents: list[str] = []
        self.received: list[dict[str, np.ndarray]] = []
        self._right = (spaces.Box(np.array([-np.inf, 0.0]), np.array([np.inf, np.inf]))
                       if unbounded else
                       spaces.Box(np.array([-10.0, 0.0]), np.array([-6.0, 0.5])))

    def observation_space(self, agent: str) -> spaces.Space:
        return spaces.Box(0.0, 1.0, (1,), np.float32)

    def action_space(self, agent: str) -> spaces.Space:
        return spaces.Box(2.0, 4.0, (1,), np.float32) if agent == "left" else self._right

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        self.agents = list(self.possible_agents)
        return {agent: np.ones(1, np.float32) for agent in self.agents}, {}

    def step(self, actions: dict[str, np.ndarray]) -> tuple[dict, dict, dict, dict, dict]:
        self.received.append({agent: np.array(a) for agent, a in actions.items()})
        error = sum(float(np.sum((actions[a] - self.TARGETS[a]) ** 2)) for a in actions)
        self.agents = []
        agents = self.possible_agents
        return ({a: np.ones(1, np.float32) for a in agents}, {a: -error for a in agents},
                {a: True for a in agents}, {a: False for a in agents}, {a: {} for a in agents})


MASK_FAULTS = {"dead_mask": np.zeros(2, np.int8), "short_mask": np.ones(1, np.int8),
               "long_mask": np.ones((1, 3), bool)}
"""FaultyGame's info action masks of "q" for two actions: none allowed, one entry, three."""


class FaultyGame(ParallelEnv):
    """Two agents, 5-step episodes, observations of shape (3,), rewards 1.0. `fault` breaks one
    thing at episode step `at` (0: at reset): "obs_shape" (a (4,) observation), "reward" (the
    reward as `reward_value`), "nan_obs", "nan_reward", "raise" (the simulator raises, every
    time from then on), "no_rewards" (an empty rewards dict), "missing_reward" (none for "q"),
    "gym4" (a Gym-style 4-tuple), "dead_mask", "short_mask", "long_mask" (an info action mask
    of "q" from MASK_FAULTS)."""

    metadata: ClassVar[dict[str, Any]] = {"name": "faulty_game"}

    def __init__(self, fault: str | None = None, at: int = 0, reward_value: Any = 1.0) -> None:
        self.possible_agents = ["p", "q"]
        self.agents: list[str] = []
        self.fault, self.at, self.reward_value = fault, at, reward_value

    def observation_space(self, agent: str) -> spaces.Space:
        return spaces.Box(-1.0, 1.0, (3,), np.float32)

    def action_space(self, agent: str) -> spaces.Space:
        return spaces.Discrete(2)

    def _observe(self) -> dict[str, np.ndarray]:
        obs = {agent: np.zeros(3, np.float32) for agent in self.agents}
        if self._t == self.at and self.fault == "obs_shape":
            obs["q"] = np.zeros(4, np.float32)
        if self._t == self.at and self.fault == "nan_obs":
            obs["q"][1] = np.nan
        return obs

    def reset(self, seed: int | None = None, options: Any = None) -> tuple[dict, dict]:
        self._t = 0
        if self.fault == "raise" and self.at == 0:
            raise RuntimeError("the simulator fell over at reset")
        self.agents = list(self.possible_agents)
        return self._observe(), self._infos()

    def _infos(self) -> dict[str, dict]:
        infos: dict[str, dict] = {agent: {} for agent in self.agents}
        if self._t == self.at and self.fault in MASK_FAULTS:
            infos["q"]["action_mask"] = MASK_FAULTS[self.fault]
        return infos

    def step(self, actions: dict[str, int]) -> tuple[dict, ...]:
        self._t += 1
        if self.fault == "raise" and self._t >= self.at:
            raise RuntimeError("the simulator fell over")
        reward = self.reward_value if self.fault == "reward" and self._t == self.at else 1.0
        if self.fault == "nan_reward" and self._t == self.at:
            reward = float("nan")
        end = self._t >= 5
        obs, infos = self._observe(), self._infos()
        agents = list(self.agents)
        if end:
            self.agents = []
        rewards = {a: reward for a in agents}
        if self._t == self.at and self.fault in ("no_rewards", "missing_reward"):
            rewards = {"p": reward} if self.fault == "missing_reward" else {}
        if self._t == self.at and self.fault == "gym4":
            return obs, rewards, {a: end for a in agents}, infos
        return obs, rewards, {a: end for a in agents}, {a: False for a in agents}, infos


class ShapedGame(FaultyGame):
    """FaultyGame with `agents` agents (2 or 3) observing `obs_size` values each."""

    built: ClassVar[int] = 0
    """Instances `shaped_game` has built (tests set it to 0)."""

    def __init__(self, agents: int = 2, obs_size: int = 3) -> None:
        super().__init__()
        self.possible_agents = ["p", "q", "r"][:agents]
        self.obs_size = obs_size

    def observation_space(self, agent: str) -> spaces.Space:
        return spaces.Box(-1.0, 1.0, (self.obs_size,), np.float32)

    def _observe(self) -> dict[str, np.ndarray]:
        return {agent: np.zeros(self.obs_size, np.float32) for agent in self.agents}


class SpacelessGame(FaultyGame):
    """FaultyGame whose observation_space is PettingZoo's default, which reads the
    `observation_spaces` it lacks, or (`none`) returns None."""

    def __init__(self, none: bool = False) -> None:
        super().__init__()
        self.none = none

    def observation_space(self, agent: str) -> Any:
        return None if self.none else ParallelEnv.observation_space(self, agent)


def roster_game() -> RosterGame:
    return RosterGame()


def box_game(**kwargs: Any) -> BoxGame:
    return BoxGame(**kwargs)


def faulty_game(**kwargs: Any) -> FaultyGame:
    return FaultyGame(**kwargs)


def shaped_game(differs: str, from_build: int = 1) -> ShapedGame:
    """A ShapedGame that from its `from_build`-th build on (counting from 0), or `differs`
    "obs_in_workers" in worker processes, has a third agent ("agents") or observations of 5
    values ("obs", "obs_in_workers")."""
    ShapedGame.built += 1
    other = (multiprocessing.parent_process() is not None if differs == "obs_in_workers"
             else ShapedGame.built > from_build)
    if not other:
        return ShapedGame()
    return ShapedGame(agents=3) if differs == "agents" else ShapedGame(obs_size=5)


def spaceless_game(**kwargs: Any) -> SpacelessGame:
    return SpacelessGame(**kwargs)


ROSTER = f"pettingzoo:{HERE}:roster_game"
BOX = f"pettingzoo:{HERE}:box_game"
FAULTY = f"pettingzoo:{HERE}:faulty_game"
SHAPED = f"pettingzoo:{HERE}:shaped_game"
SPACELESS = f"pettingzoo:{HERE}:spaceless_game"


# ---------------------------------------------------------------- agents that join and leave
def test_agents_that_join_leave_and_come_back_act_exactly_while_live() -> None:
    env = make_host_env(ROSTER)
    timestep = env.reset()
    alive = [timestep.alive.tolist()]
    for _ in range(RosterGame.LENGTH):
        timestep = env.step(np.ones(2, int))
        alive.append(timestep.alive.tolist())
    expected = [[True, "b" in RosterGame.roster(t)] for t in range(RosterGame.LENGTH)]
    assert alive[:-1] == expected  # the last step's observation is the next episode's reset
    assert env.env.sent == [sorted(RosterGame.roster(t)) for t in range(RosterGame.LENGTH)]
    assert bool(timestep.done)


def test_an_absent_agent_is_masked_as_a_dead_one() -> None:
    env = make_host_env(ROSTER)
    timestep = env.reset()
    assert timestep.alive.tolist() == [True, False]
    np.testing.assert_array_equal(timestep.obs[1], 0.0)
    assert timestep.action_mask[1].tolist() == [True, False]
    joined = env.step(np.zeros(2, int))
    joined = env.step(np.zeros(2, int))
    assert joined.alive.tolist() == [True, True]
    np.testing.assert_allclose(joined.obs[1], [1.0, 0.2])
    assert joined.action_mask[1].tolist() == [True, True]


# ----------------------------------------------------------------------- Box bounds mapping
def test_the_policys_range_is_mapped_onto_each_box() -> None:
    env = make_host_env(BOX)
    assert (env.spec.action_low, env.spec.action_high) == (-1.0, 1.0)
    env.reset()
    for unit, left, right in [(-1.0, 2.0, [-10.0, 0.0]), (0.0, 3.0, [-8.0, 0.25]),
                              (1.0, 4.0, [-6.0, 0.5]), (7.0, 4.0, [-6.0, 0.5]),
                              (0.5, 3.5, [-7.0, 0.375])]:
        env.step(np.full((2, 2), unit, np.float32))
        sent = env.env.received[-1]
        np.testing.assert_allclose(sent["left"], [left], rtol=1e-6)
        np.testing.assert_allclose(sent["right"], right, rtol=1e-6)


def test_infinite_bounds_are_sent_unmapped() -> None:
    env = make_host_env(BOX, unbounded=True)
    assert (env.spec.action_low, env.spec.action_high) == (-np.inf, np.inf)
    env.reset()
    env.step(np.array([[0.5, 0.0], [-7.0, -0.3]], np.float32))
    sent = env.env.received[-1]
    np.testing.assert_allclose(sent["left"], [3.5])  # finite: mapped as before
    np.testing.assert_allclose(sent["right"], [-7.0, 0.0])  # as sampled, clipped to [0, inf)


@pytest.mark.slow
def test_a_policy_learns_to_hit_targets_inside_boxes_far_from_zero() -> None:
    """Measured: the greedy return goes from -1.24 (about the box midpoints) to -0.002 in 40
    updates of 64 one-step episodes (0 is optimal); actions stuck at a bound would score
    at most -(1.5² + ...) = -2.25."""
    trainer = HostTrainer(load_config(overrides=[
        f"env={BOX}", "num_envs=16", "rollout_length=4", "total_steps=2560", "log_interval=40",
        "network.n_embd=16", "ppo.epochs=10", "ppo.lr=0.005", "ppo.clip_eps=0.2",
        "eval_episodes=4", "host_workers=0",
    ]))
    try:
        start = trainer.init()
        before = trainer.evaluate(start, 4)["episode_return"]
        state, _ = trainer.train_chunk(start)
        after = trainer.evaluate(state, 4)["episode_return"]
    finally:
        trainer.close()
    assert float(before[0]) < -0.4  # the box midpoints score -((3 - 3.5)² + 1² + 0.15²)
    assert float(after[0]) > -0.1


# ------------------------------------------------------- malformed and non-finite returns
@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"fault": "obs_shape", "at": 0}, "observation of agent 'q' at step 0 of an episode has "
                                          "shape (4,), but its observation space declares (3,)"),
        ({"fault": "obs_shape", "at": 3}, "observation of agent 'q' at step 3 of an episode has "
                                          "shape (4,), but its observation space declares (3,)"),
        ({"fault": "reward", "at": 2, "reward_value": [1.0, 2.0]},
         "reward of agent 'p' at step 2 of an episode has shape (2,); expected a scalar"),
        ({"fault": "reward", "at": 2, "reward_value": "high"},
         "reward of agent 'p' at step 2 of an episode is not a number: 'high'"),
        ({"fault": "nan_obs", "at": 0}, "non-finite observation of agent 'q' at step 0 of an "
                                        "episode (nan)"),
        ({"fault": "nan_obs", "at": 4}, "non-finite observation of agent 'q' at step 4"),
        ({"fault": "nan_reward", "at": 1}, "non-finite reward of agent 'p' at step 1"),
        ({"fault": "no_rewards", "at": 1}, "rewards at step 1 of an episode has no reward for "
                                           "agent(s) 'p', 'q', which acted"),
        ({"fault": "missing_reward", "at": 3}, "rewards at step 3 of an episode has no reward "
                                               "for agent(s) 'q', which acted"),
        ({"fault": "gym4", "at": 2}, "step must return (observations, rewards, terminations, "
                                     "truncations, infos), got a tuple of 4 items; a Gym-style "
                                     "(obs, reward, done, info)?"),
        ({"fault": "dead_mask", "at": 0}, "the action mask of live agent 'q' at step 0 of an "
                                          "episode allows no action"),
        ({"fault": "dead_mask", "at": 4}, "the action mask of live agent 'q' at step 4 of an "
                                          "episode allows no action"),
        ({"fault": "short_mask", "at": 0}, "the action mask of agent 'q' at step 0 of an "
                                           "episode has 1 entries, but its action space has 2"),
        ({"fault": "long_mask", "at": 3}, "the action mask of agent 'q' at step 3 of an episode "
                                          "has 3 entries, but its action space has 2 actions"),
    ],
)
def test_malformed_returns_are_error_line(kwargs: dict, message: str) -> None:
    env = make_host_env(FAULTY, **kwargs)
    with pytest.raises(CmatError, match=r"^pettingzoo:.*faulty_game: ") as raised:
        env.reset()
        for _ in range(5):
            env.step(np.zeros(2, int))
    assert message in str(raised.value)


@pytest.mark.parametrize("reward", [np.float32(0.5), np.array(0.5), np.array([0.5]),
                                    np.array([[0.5]], np.float64), 0.5, 1])
def test_numpy_scalars_and_size_one_rewards_are_accepted(reward: Any) -> None:
    env = make_host_env(FAULTY, fault="reward", at=1, reward_value=reward)
    env.reset()
    assert env.step(np.zeros(2, int)).reward == pytest.approx(float(np.asarray(reward).sum()))


def test_nonfinite_values_are_replaced_and_counted_when_asked() -> None:
    pool = InProcessPool(FAULTY, {"fault": "nan_obs", "at": 2}, [0, 1], nonfinite="warn")
    pool.reset()
    batches = [pool.step(np.zeros((2, 2), int)) for _ in range(2)]
    assert np.isfinite(batches[1].obs).all()
    assert pool.counters()["env_nonfinite"].tolist() == [1, 1]


@pytest.mark.parametrize("policy", ["warm", "", "ERROR"])
def test_an_unknown_nonfinite_policy_is_refused(policy: str) -> None:
    with pytest.raises(CmatError, match=f"nonfinite must be one of error, warn, got {policy!r}"):
        make_host_env(FAULTY, nonfinite=policy)


@pytest.mark.parametrize("fault", [{"fault": "obs_shape", "at": 0}, {"fault": "nan_obs", "at": 0},
                                   {"fault": "dead_mask", "at": 0}])
def test_a_run_whose_env_fails_at_reset_leaves_no_run_directory(
    fault: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    args = [f"env_kwargs.{key}={value}" for key, value in fault.items()]
    assert main(["train", "--env", FAULTY, "--steps", "40", "--out", str(out), "--set",
                 "num_envs=2", "rollout_length=5", "network.n_embd=8", *args]) == 2
    assert "agent 'q' at step 0" in error_line(capsys.readouterr().err)
    assert not out.exists()


def test_a_malformed_return_mid_run_stops_it_from_a_worker_too(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    assert main(["train", "--env", FAULTY, "--steps", "40", "--out", str(out), "--set",
                 "num_envs=2", "rollout_length=5", "network.n_embd=8", "host_workers=1",
                 "env_kwargs.fault=obs_shape", "env_kwargs.at=3"]) == 2
    error = error_line(capsys.readouterr().err)
    assert "observation of agent 'q' at step 3 of an episode has shape (4,)" in error
    assert f"; the new run directory {out} was removed" in error
    assert not out.exists()  # a new run that failed in its first chunk leaves nothing


# -------------------------------------------------------------------------------- crashes
@pytest.mark.parametrize("pool_kind", ["in_process", "workers"])
def test_an_env_that_always_crashes_stops_after_the_limit(
    pool_kind: str, caplog: pytest.LogCaptureFixture
) -> None:
    kwargs = {"fault": "raise", "at": 0}  # every reset raises, so every restart fails too
    pool = (InProcessPool(FAULTY, kwargs, [0], crash_limit=3) if pool_kind == "in_process"
            else WorkerPool(FAULTY, kwargs, [0], workers=1, crash_limit=3))
    try:
        with (
            caplog.at_level(logging.WARNING, logger="cmat.host"),
            pytest.raises(CmatError, match=r"environment 0 crashed 3 times in a row \(last: "
                                           r".*RuntimeError: the simulator fell over at "
                                           r"reset\); stopped \(host_crash_limit=3\)"),
        ):
            pool.reset()
    finally:
        pool.close()
    if pool_kind == "in_process":
        assert caplog.text.count("crashed (") == 2


def test_crashes_that_recover_are_restarted_and_counted() -> None:
    pool = InProcessPool(FAULTY, {"fault": "raise", "at": 5}, [0], crash_limit=2)
    pool.reset()
    dones = [bool(pool.step(np.zeros((1, 2), int)).done[0]) for _ in range(12)]
    # every 5th step crashes (counted as a truncated episode) and the fresh env starts again
    assert dones == [False, False, False, False, True] * 2 + [False, False]
    assert pool.counters()["env_restarts"].tolist() == [2]


def test_cmats_own_errors_are_not_taken_for_crashes() -> None:
    pool = InProcessPool(FAULTY, {}, [0])
    pool.reset()
    with pytest.raises(IndexError):
        pool.step(np.zeros((0, 2), int))  # a bug on cmat's side: no restart, no retry
    assert pool.counters()["env_restarts"].tolist() == [0]


# ------------------------------------------------------------- factories whose instances differ
@pytest.mark.parametrize(
    ("differs", "message"),
    [
        ("agents", "environment 1 differs from the first one built (agents ['p', 'q'] vs "
                   "['p', 'q', 'r']; num_agents 2 vs 3; observation_space('r') (none) vs Box("),
        ("obs", "environment 1 differs from the first one built (observation_space('p') "
                "Box(-1.0, 1.0, (3,), float32) vs Box(-1.0, 1.0, (5,), float32); "),
    ],
)
def test_a_factory_whose_instances_differ_is_an_error_line(
    differs: str, message: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(ShapedGame, "built", 0)
    with pytest.raises(CmatError, match=r"^pettingzoo:.*shaped_game: ") as raised:
        InProcessPool(SHAPED, {"differs": differs}, [0, 1, 2])
    assert message in str(raised.value) and "\n" not in str(raised.value)
    assert str(raised.value).endswith("every instance the factory builds must have the same "
                                      "agents and spaces")


def test_a_restarted_environment_is_checked_too(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ShapedGame, "built", 0)
    pool = InProcessPool(SHAPED, {"differs": "obs", "from_build": 2}, [0, 1])
    try:
        with pytest.raises(CmatError, match=r"environment 1 differs from the first one built"):
            pool._restart(1, "a test crash")
    finally:
        pool.close()


def test_worker_environments_are_checked_against_the_first_one_built() -> None:
    probe = make_host_env(SHAPED, differs="obs_in_workers")
    with pytest.raises(CmatError, match=r"shaped_game: environment 0 differs from the first "
                                        r"one built \(observation_space\('p'\)"):
        make_pool(SHAPED, {"differs": "obs_in_workers"}, [0, 1], workers=1, envs=[probe])


def test_a_run_whose_factory_builds_unlike_instances_stops_before_its_directory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(ShapedGame, "built", 0)
    out = tmp_path / "run"
    assert main(["train", "--env", SHAPED, "--steps", "40", "--out", str(out), "--set",
                 "num_envs=2", "rollout_length=5", "network.n_embd=8",
                 "env_kwargs.differs=agents"]) == 2
    assert "environment 1 differs from the first one built (agents" in error_line(
        capsys.readouterr().err)
    assert not out.exists()


# ------------------------------------------------------------------- spaces, imports, render
@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({}, "the env has no observation_space(agent) method or observation_spaces dict"),
        ({"none": True}, "observation_space('p') returned None, expected a gymnasium Space"),
    ],
)
def test_missing_spaces_are_an_error_line_even_in_a_dry_run(
    kwargs: dict, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    sets = [f"env_kwargs.{key}={value}" for key, value in kwargs.items()]
    options = ["--set", *sets] if sets else []
    assert main(["train", "--env", SPACELESS, "--dry-run", *options]) == 2
    assert error_line(capsys.readouterr().err).endswith(message)


def test_an_unimportable_module_hints_at_pythonpath_or_names_the_missing_dependency(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "cmat_user_envs_a.py").write_text("import cmat_no_such_dependency\n")
    (tmp_path / "cmat_user_envs_b.py").write_text("raise RuntimeError('half written')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(CmatError) as own:
        make_host_env("pettingzoo:cmat_no_such_package.envs:make")
    assert not isinstance(own.value, SuiteUnavailable)
    assert ("cannot import 'cmat_no_such_package.envs' (No module named 'cmat_no_such_package'); "
            "it must be importable from the Python running cmat (") in str(own.value)
    assert str(own.value).endswith("put its directory on PYTHONPATH or pip-install its package")
    with pytest.raises(SuiteUnavailable) as dependency:
        make_host_env("pettingzoo:cmat_user_envs_a:make")
    assert str(dependency.value).endswith(
        "cannot import 'cmat_user_envs_a': it imports 'cmat_no_such_dependency', which is not "
        "installed (No module named 'cmat_no_such_dependency')")
    with pytest.raises(CmatError, match=r"importing 'cmat_user_envs_b' raised RuntimeError: "
                                        r"half written$"):
        make_host_env("pettingzoo:cmat_user_envs_b:make")


@pytest.mark.parametrize(
    ("picture", "got"),
    [
        (np.zeros((32, 48), np.uint8), "an array of shape (32, 48) and dtype uint8"),
        (np.zeros((32, 48, 2), np.float32), "an array of shape (32, 48, 2) and dtype float32"),
        (None, "None"),
        ([[0]], "a list"),
    ],
)
def test_a_render_that_is_no_rgb_array_says_what_it_got(picture: Any, got: str) -> None:
    class Simulator:
        def render(self) -> Any:
            return picture

    with pytest.raises(CmatError) as raised:
        draw_host(Simulator(), "pettingzoo:m:f")
    assert str(raised.value) == (f"pettingzoo:m:f: render() returned no RGB array (got {got}); "
                                 f"expected an (H, W, 3) uint8 array, as "
                                 f"render_mode='rgb_array' gives")


class TurnTaker:
    """Looks like an AEC env: agents act in turn (`agent_iter`)."""

    possible_agents: ClassVar[list[str]] = ["a", "b"]

    def reset(self) -> None: ...

    def step(self, action: int) -> None: ...

    def agent_iter(self) -> list[str]:
        return self.possible_agents


class JaxLike:
    """Looks like a cmat MarlEnv: a spec, reset and step, no possible_agents."""

    spec = None

    def reset(self, key: Any) -> None: ...

    def step(self, key: Any, state: Any, actions: Any) -> None: ...


@pytest.mark.parametrize(("built", "hint"), [
    (TurnTaker, " (an AEC env: convert it with pettingzoo.utils.aec_to_parallel)"),
    (JaxLike, " (a cmat MarlEnv or JaxMARL env: use jax:MODULE:FACTORY)"),
    (dict, ""),
])
def test_a_factory_that_builds_no_parallel_env_gets_the_hint_that_fits(
    built: type, hint: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(globals(), "built_env", built)
    with pytest.raises(CmatError) as raised:
        make_host_env(f"pettingzoo:{HERE}:built_env")
    assert str(raised.value) == (f"pettingzoo:{HERE}:built_env: the factory must return a "
                                 f"PettingZoo ParallelEnv, got {built.__name__}{hint}")
