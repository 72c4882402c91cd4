"""A user's own JAX environment by id, `jax:<this module>:<factory>`: a cmat MarlEnv used as
it is, a JaxMARL MultiAgentEnv adapted (padding, masks, world state, wins, Box bounds), and
envs that break the protocol in ordinary ways, each a one-line error before anything runs.
"""

from __future__ import annotations

import csv
import textwrap
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxmarl.environments.multi_agent_env import MultiAgentEnv
from jaxmarl.environments.spaces import Box, Discrete, MultiDiscrete

from cmat.cli import main
from cmat.envs import EnvSpec, TimeStep, make_env
from cmat.errors import CmatError
from cmat.rundir import RunDir

pytestmark = pytest.mark.quick_compiles

HERE = __name__


class TargetState(NamedTuple):
    targets: jax.Array
    step: jax.Array
    total: jax.Array
    """Steps since the environment was first reset (kept across episodes)."""


class TargetGame:
    """Every agent sees a one-hot target and is paid for naming it: a cmat MarlEnv, written
    against the protocol. A random team earns 1/choices per step; a learned one 1."""

    def __init__(
        self, agents: int = 3, choices: int = 3, length: int = 5, nan_after: int = 0,
        closed_after: int = 0, never_ends: bool = False,
    ) -> None:
        """`nan_after` > 0: the reward is NaN from that many steps of an instance on;
        `closed_after` > 0: from that many steps on, agent 0 (alive) may take no action;
        `never_ends`: no step sets done, though the spec says episodes last `length` steps."""
        self.choices, self.length, self.nan_after = choices, length, nan_after
        self.closed_after, self.never_ends = closed_after, never_ends
        self.spec = EnvSpec(
            env_id="jax:target", num_agents=agents, obs_dim=choices, action_dim=choices,
            discrete=True, max_episode_steps=length, has_win_rate=False,
        )

    def _timestep(self, state: TargetState, reward: jax.Array, done: jax.Array) -> TimeStep:
        n = self.spec.num_agents
        mask = jnp.ones((n, self.choices), bool)
        if self.closed_after:
            mask = mask.at[0].set(state.total < self.closed_after)
        return TimeStep(
            jax.nn.one_hot(state.targets, self.choices), mask,
            reward, done, jnp.asarray(False), jnp.ones(n, bool), jnp.zeros(0, jnp.float32),
        )

    def reset(self, key: jax.Array) -> tuple[TargetState, TimeStep]:
        targets = jax.random.randint(key, (self.spec.num_agents,), 0, self.choices)
        state = TargetState(targets, jnp.int32(0), jnp.int32(0))
        return state, self._timestep(state, jnp.float32(0.0), jnp.asarray(False))

    def step(
        self, key: jax.Array, state: TargetState, actions: jax.Array
    ) -> tuple[TargetState, TimeStep]:
        reward = jnp.mean((actions == state.targets).astype(jnp.float32))
        if self.nan_after:
            reward = jnp.where(state.total >= self.nan_after, jnp.nan, reward)
        done = (state.step + 1 >= self.length) & (not self.never_ends)
        targets = jax.random.randint(key, (self.spec.num_agents,), 0, self.choices)
        next_state = TargetState(targets, jnp.where(done, 0, state.step + 1), state.total + 1)
        return next_state, self._timestep(next_state, reward, done)


def target_game(**kwargs: Any) -> TargetGame:
    return TargetGame(**kwargs)


class Outpost(MultiAgentEnv):
    """A JaxMARL env with what the adapter has to handle: a scout (3 features, 3 actions, its
    last action never available) and a runner ([2, 2] features, 5 actions), a world state, a
    "won" info, per-agent rewards and a runner that is done (out) after its first step."""

    def __init__(self, max_steps: int = 4, closed_at: int = 0) -> None:
        """`closed_at` > 0: from that step of an episode on, the scout may take no action."""
        super().__init__(num_agents=2)
        self.agents = ["scout", "runner"]
        self.max_steps, self.closed_at = max_steps, closed_at
        self.observation_spaces = {"scout": Box(0, 1, (3,)), "runner": Box(0, 1, (2, 2))}
        self.action_spaces = {"scout": Discrete(3), "runner": Discrete(5)}

    def reset(self, key: jax.Array) -> tuple[dict[str, jax.Array], Any]:
        state = jnp.int32(0)
        return self.get_obs(state), state

    def get_obs(self, state: Any) -> dict[str, jax.Array]:
        level = state.astype(jnp.float32)
        return {"scout": jnp.full(3, level), "runner": jnp.full((2, 2), level + 10),
                "world_state": jnp.full(6, level)}

    def get_avail_actions(self, state: Any) -> dict[str, jax.Array]:
        scout = jnp.array([True, True, False])
        if self.closed_at:
            scout = scout & (state < self.closed_at)
        return {"scout": scout, "runner": jnp.ones(5, bool)}

    def step_env(self, key: jax.Array, state: Any, actions: dict[str, jax.Array]) -> Any:
        state = state + 1
        done = state >= self.max_steps
        rewards = {"scout": actions["scout"].astype(jnp.float32),
                   "runner": actions["runner"].astype(jnp.float32)}
        dones = {"scout": done, "runner": jnp.asarray(True), "__all__": done}
        infos = {"won": jnp.array([done, False])}
        return self.get_obs(state), state, rewards, dones, infos


def outpost(**kwargs: Any) -> Outpost:
    return Outpost(**kwargs)


class Crane(MultiAgentEnv):
    """Continuous JaxMARL env: two agents with Box actions in [2, 4] and [-10, -6] (sizes 2 and
    1); the state records the last actions sent."""

    def __init__(self, infinite: bool = False) -> None:
        super().__init__(num_agents=2)
        self.max_steps = 3
        self.observation_spaces = {a: Box(0, 1, (2,)) for a in self.agents}
        self.action_spaces = {"agent_0": Box(2.0, 4.0, (2,)),
                              "agent_1": Box(-10.0, jnp.inf if infinite else -6.0, (1,))}

    def reset(self, key: jax.Array) -> tuple[dict[str, jax.Array], Any]:
        return {a: jnp.zeros(2) for a in self.agents}, jnp.zeros(3)

    def step_env(self, key: jax.Array, state: Any, actions: dict[str, jax.Array]) -> Any:
        sent = jnp.concatenate([actions["agent_0"], actions["agent_1"]])
        rewards = {a: -jnp.sum((sent - 3.0) ** 2) for a in self.agents}
        dones = {a: jnp.asarray(False) for a in [*self.agents, "__all__"]}
        return {a: jnp.zeros(2) for a in self.agents}, sent, rewards, dones, {}


def crane(**kwargs: Any) -> Crane:
    return Crane(**kwargs)


@pytest.mark.slow
def test_a_marl_env_trains_by_id_and_is_learned(tmp_path: Path) -> None:
    """Slow suite (40 s on 2 cores; the fast suite trains user environments by id in the tests
    below). The CLI trains a user's protocol env in-graph; the policy learns it (the last rollouts'
    reward per step well above a random team's 1/3)."""
    out = tmp_path / "run"
    code = main([
        "train", "--env", f"jax:{HERE}:target_game", "--steps", "8000", "--out", str(out),
        "--set", "num_envs=16", "rollout_length=25", "ppo.epochs=5", "ppo.lr=0.005",
        "log_interval=5",
    ])
    assert code == 0
    rows = [row for row in csv.DictReader((out / "metrics.csv").open()) if row["kind"] == "eval"]
    returns = [float(row["episode_return"]) for row in rows]
    assert returns[-1] / 5 > 0.8, returns


def test_a_new_run_that_fails_before_its_first_chunk_leaves_no_directory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A NaN reward from the first update on: no chunk written, the new directory removed; from
    the third update on (chunks of two): the first chunk's rows and checkpoint kept."""
    common = ["--algo", "mappo", "--steps", "80", "--set", "num_envs=2", "rollout_length=5",
              "log_interval=2", "eval_episodes=1"]
    first, later = tmp_path / "first", tmp_path / "later"
    assert main(["train", "--env", f"jax:{HERE}:target_game", "--out", str(first), *common,
                 "env_kwargs.nan_after=2"]) == 2
    error = capsys.readouterr().err
    assert "non-finite environment reward at update 1 (seed 0)" in error, error
    assert f"; the new run directory {first} was removed" in error, error
    assert not first.exists()
    assert main(["train", "--env", f"jax:{HERE}:target_game", "--out", str(later), *common,
                 "env_kwargs.nan_after=12"]) == 2
    error = capsys.readouterr().err
    assert "non-finite environment reward at update 3" in error and "removed" not in error, error
    rows = list(csv.DictReader((later / "metrics.csv").open()))
    assert {int(row["env_steps"]) for row in rows} == {20}
    assert RunDir.open(later).checkpoint_steps() == (20, True)


@pytest.mark.parametrize("env_id", [f"jax:{HERE}:target_game", f"jax:{HERE}:outpost"])
def test_a_live_agent_with_no_available_action_stops_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], env_id: str
) -> None:
    """A mask closed on a live agent, from a MarlEnv's `action_mask` or a JaxMARL env's
    `get_avail_actions`, stops the run with one line naming the update; before it closes the
    run trains (a dead agent's closed mask is no fault: the outpost's runner is out after its
    first step and keeps its mask open, the target game never has a dead agent)."""
    common = ["--algo", "mappo", "--steps", "80", "--set", "num_envs=2", "rollout_length=5",
              "log_interval=2", "eval_episodes=1"]
    fault = "env_kwargs.closed_after=12" if "target" in env_id else "env_kwargs.closed_at=3"
    assert main(["train", "--env", env_id, "--out", str(tmp_path / "open"), *common]) == 0
    capsys.readouterr()
    assert main(["train", "--env", env_id, "--out", str(tmp_path / "closed"), *common,
                 fault]) == 2
    error = capsys.readouterr().err
    assert "an action mask that allows no action to a live agent" in error, error
    update = 3 if "target" in env_id else 1
    assert f"at update {update} (seed 0)" in error, error


def test_an_env_whose_episodes_never_end_is_warned_about_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Chunks of 10 steps per environment: no episode of 5 steps ends, so the first chunk warns
    (once in the run) and the train rows read nan; the same env ending its episodes does not."""
    common = ["--algo", "mappo", "--steps", "80", "--set", "num_envs=2", "rollout_length=5",
              "log_interval=2", "eval_episodes=1"]
    never = tmp_path / "never"
    assert main(["train", "--env", f"jax:{HERE}:target_game", "--out", str(never), *common,
                 "env_kwargs.never_ends=true"]) == 0
    error = capsys.readouterr().err
    assert error.count("warning") == 1, error
    assert ("no episode has ended in the last 10 steps of any environment, more than its "
            "max_episode_steps (5)") in error, error
    train = [row for row in csv.DictReader((never / "metrics.csv").open())
             if row["kind"] == "train"]
    assert len(train) == 4 and all(row["episode_return"] == "nan" for row in train)
    assert main(["train", "--env", f"jax:{HERE}:target_game", "--out", str(tmp_path / "ends"),
                 *common]) == 0
    assert "warning" not in capsys.readouterr().err


def test_jaxmarl_env_is_adapted() -> None:
    env = make_env(f"jax:{HERE}:outpost")
    spec = env.spec
    assert (spec.num_agents, spec.obs_dim, spec.action_dim, spec.discrete) == (2, 4, 5, True)
    assert (spec.state_dim, spec.has_win_rate, spec.max_episode_steps) == (6, True, 5)
    state, first = env.reset(jax.random.PRNGKey(0))
    np.testing.assert_array_equal(first.obs, [[0, 0, 0, 0], [10, 10, 10, 10]])
    np.testing.assert_array_equal(
        first.action_mask, [[True, True, False, False, False], [True] * 5]
    )
    state, after = env.step(jax.random.PRNGKey(1), state, jnp.array([1, 4]))
    assert float(after.reward) == 2.5
    np.testing.assert_array_equal(after.alive, [True, False])
    np.testing.assert_array_equal(after.global_state, np.full(6, 1.0))
    assert not bool(after.won)
    for _ in range(3):
        state, after = env.step(jax.random.PRNGKey(2), state, jnp.array([0, 0]))
    assert bool(after.done) and bool(after.won)
    np.testing.assert_array_equal(after.obs[0], [0, 0, 0, 0])
    np.testing.assert_array_equal(after.alive, [True, True])


def test_jaxmarl_env_trains_and_reports_its_win_rate(tmp_path: Path) -> None:
    out = tmp_path / "run"
    code = main([
        "train", "--env", f"jax:{HERE}:outpost", "--algo", "mappo", "--steps", "400",
        "--out", str(out),
        "--set", "num_envs=4", "rollout_length=50", "ppo.epochs=1", "env_kwargs.max_steps=3",
    ])
    assert code == 0
    rows = [row for row in csv.DictReader((out / "metrics.csv").open()) if row["kind"] == "eval"]
    assert rows and float(rows[-1]["win_rate"]) == 1.0


def test_box_actions_are_mapped_onto_each_bound() -> None:
    env = make_env(f"jax:{HERE}:crane")
    assert (env.spec.action_dim, env.spec.discrete) == (2, False)
    state, _ = env.reset(jax.random.PRNGKey(0))
    sent, _ = env.step(jax.random.PRNGKey(0), state, jnp.array([[-1.0, 1.0], [1.0, 0.3]]))
    np.testing.assert_allclose(sent, [2.0, 4.0, -6.0])
    sent, _ = env.step(jax.random.PRNGKey(0), state, jnp.array([[5.0, 0.0], [-3.0, 0.0]]))
    np.testing.assert_allclose(sent, [4.0, 3.0, -10.0])


class WrongObs(TargetGame):
    def reset(self, key: jax.Array) -> tuple[TargetState, TimeStep]:
        state, timestep = super().reset(key)
        return state, timestep._replace(obs=timestep.obs[:, :2])


class DriftingState(TargetGame):
    def step(self, key: jax.Array, state: TargetState, actions: jax.Array) -> Any:
        next_state, timestep = super().step(key, state, actions)
        return next_state._replace(step=next_state.step.astype(jnp.float32)), timestep


class RaisingReset(TargetGame):
    def reset(self, key: jax.Array) -> tuple[TargetState, TimeStep]:
        raise ValueError("no map loaded")


class IntegerReward(TargetGame):
    def step(self, key: jax.Array, state: TargetState, actions: jax.Array) -> Any:
        next_state, timestep = super().step(key, state, actions)
        return next_state, timestep._replace(reward=jnp.int32(1))


class Tuple3(TargetGame):
    def reset(self, key: jax.Array) -> Any:
        state, timestep = super().reset(key)
        return state, tuple(timestep)


class MultiDiscreteOutpost(Outpost):
    def __init__(self) -> None:
        super().__init__()
        self.action_spaces = {"scout": MultiDiscrete([2, 2]), "runner": Discrete(5)}


class RewardlessOutpost(Outpost):
    def step_env(self, key: jax.Array, state: Any, actions: dict[str, jax.Array]) -> Any:
        obs, state, rewards, dones, infos = super().step_env(key, state, actions)
        return obs, state, {"scout": rewards["scout"]}, dones, infos


class VectorRewardOutpost(Outpost):
    def step_env(self, key: jax.Array, state: Any, actions: dict[str, jax.Array]) -> Any:
        obs, state, rewards, dones, infos = super().step_env(key, state, actions)
        return obs, state, {**rewards, "runner": jnp.full(2, rewards["runner"])}, dones, infos


class GrowingOutpost(Outpost):
    def step_env(self, key: jax.Array, state: Any, actions: dict[str, jax.Array]) -> Any:
        obs, state, rewards, dones, infos = super().step_env(key, state, actions)
        return {**obs, "runner": jnp.zeros((2, 3))}, state, rewards, dones, infos


class StatelessStepOutpost(Outpost):
    def step_env(self, key: jax.Array, state: Any, actions: dict[str, jax.Array]) -> Any:
        obs, state, rewards, dones, infos = super().step_env(key, state, actions)
        return {"scout": obs["scout"], "runner": obs["runner"]}, state, rewards, dones, infos


class ShortMaskOutpost(Outpost):
    def get_avail_actions(self, state: Any) -> dict[str, jax.Array]:
        return {**super().get_avail_actions(state), "scout": jnp.ones(2, bool)}


@chex.dataclass
class ChexState:
    level: jax.Array


class ChexOutpost(Outpost):
    """Outpost with its state in a chex dataclass, which flax cannot serialise."""

    def reset(self, key: jax.Array) -> tuple[dict[str, jax.Array], Any]:
        return self.get_obs(jnp.int32(0)), ChexState(level=jnp.int32(0))

    def step_env(self, key: jax.Array, state: Any, actions: dict[str, jax.Array]) -> Any:
        obs, level, rewards, dones, infos = super().step_env(key, state.level, actions)
        return obs, ChexState(level=level), rewards, dones, infos

    def get_avail_actions(self, state: Any) -> dict[str, jax.Array]:
        return super().get_avail_actions(state.level)


@jax.tree_util.register_pytree_node_class
class Counter:
    """A pytree class of the user's own, unknown to flax serialisation."""

    def __init__(self, count: jax.Array) -> None:
        self.count = count

    def tree_flatten(self) -> tuple[tuple[jax.Array], None]:
        return (self.count,), None

    @classmethod
    def tree_unflatten(cls, aux: None, children: tuple[jax.Array]) -> Counter:
        return cls(*children)


class CounterStateGame(TargetGame):
    def reset(self, key: jax.Array) -> Any:
        return Counter(jnp.int32(0)), super().reset(key)[1]

    def step(self, key: jax.Array, state: Any, actions: jax.Array) -> Any:
        inner, timestep = super().step(key, TargetState(jnp.zeros(3, jnp.int32), state.count,
                                                        state.count), actions)
        return Counter(inner.step), timestep


class NumberedOutpost(Outpost):
    def __init__(self) -> None:
        super().__init__()
        self.agents = [0, 1]


class ArrayRewardOutpost(Outpost):
    def step_env(self, key: jax.Array, state: Any, actions: dict[str, jax.Array]) -> Any:
        obs, state, rewards, dones, infos = super().step_env(key, state, actions)
        return obs, state, jnp.stack([rewards["scout"], rewards["runner"]]), dones, infos


class ArrayDoneOutpost(Outpost):
    def step_env(self, key: jax.Array, state: Any, actions: dict[str, jax.Array]) -> Any:
        obs, state, rewards, dones, infos = super().step_env(key, state, actions)
        return obs, state, rewards, jnp.stack([dones["scout"], dones["runner"]]), infos


def zero_agents() -> TargetGame:
    game = TargetGame()
    game.spec = replace(game.spec, num_agents=0)
    return game


def spec_with(**changes: Any) -> Any:
    """A factory of TargetGame whose spec has `changes` (of any type: a user's mistakes)."""
    def factory() -> TargetGame:
        game = TargetGame()
        game.spec = replace(game.spec, **changes)
        return game
    return factory


BROKEN = {
    "wrong_obs": (WrongObs, "reset's TimeStep.obs is (3, 2) float32, but the spec needs "
                            "shape (3, 3)"),
    "drifting_state": (DriftingState, "step returns a state unlike reset's"),
    "raising_reset": (RaisingReset, "reset(key) raised ValueError: no map loaded"),
    "integer_reward": (IntegerReward, "step's TimeStep.reward is () int32"),
    "tuple_timestep": (Tuple3, "reset must return (state, cmat.envs.TimeStep), got tuple as "
                                "the second item"),
    "multidiscrete": (MultiDiscreteOutpost, "action spaces must be all Discrete or all Box, "
                                            "got Discrete, MultiDiscrete"),
    "rewardless": (RewardlessOutpost, "'runner' is missing from"),
    "vector_reward": (VectorRewardOutpost, "step_env's reward of agent 'runner' has shape (2,); "
                                           "expected one number per agent"),
    "growing_obs": (GrowingOutpost, "step_env's observation 'runner' has shape (2, 3), but "
                                    "reset's has shape (2, 2); each must keep its size"),
    "stateless_step": (StatelessStepOutpost, "step_env must return observations of every agent "
                                             "and the world_state as reset does"),
    "short_mask": (ShortMaskOutpost, "get_avail_actions gives agent 'scout' 2 entries, but its "
                                     "action space has 3 actions"),
    "chex_state": (ChexOutpost, "the env's state (ChexState) cannot be saved in a checkpoint "
                                "(TypeError: can not serialize"),
    "pytree_state": (CounterStateGame, "the env's state (Counter) cannot be saved in a "
                                       "checkpoint"),
    "numbered_agents": (NumberedOutpost, "env.agents must be names (str), as JaxMARL's envs use "
                                         "them to key observations, actions, rewards and dones; "
                                         "got 0 (int)"),
    "array_rewards": (ArrayRewardOutpost, "step_env's rewards must be a dict keyed by agent "
                                          "name, got an array of shape (2,) (float32)"),
    "array_dones": (ArrayDoneOutpost, "step_env's dones must be a dict keyed by agent name (and "
                                      "__all__), got an array of shape (2,) (bool)"),
    "infinite_box": (lambda: Crane(infinite=True), "agent 'agent_1''s Box has an infinite bound"),
    "zero_agents": (zero_agents, "must all be >= 1"),
    "text_agents": (spec_with(num_agents="3"), "the spec's num_agents must be a whole number, "
                                               "got '3'"),
    "bool_obs_dim": (spec_with(obs_dim=True), "the spec's obs_dim must be a whole number, got "
                                              "True"),
    "numeric_discrete": (spec_with(discrete=1), "the spec's discrete must be True or False, "
                                                "got 1"),
    "text_bound": (spec_with(action_low="-1"), "the spec's action_low must be a number, got "
                                               "'-1'"),
    "not_an_env": (lambda: object(), "must return a cmat MarlEnv (spec, reset, step) or a "
                                     "JaxMARL MultiAgentEnv, got object"),
    "raising_factory": (lambda: 1 / 0, "the factory raised ZeroDivisionError"),
}

for _name, (_factory, _) in BROKEN.items():
    globals()[f"broken_{_name}"] = _factory


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_broken_env_is_one_error_line_before_anything_runs(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    message = BROKEN[name][1]
    out = tmp_path / "run"
    code = main(["train", "--env", f"jax:{HERE}:broken_{name}", "--steps", "100",
                 "--out", str(out)])
    error = capsys.readouterr().err.strip()
    assert code == 2
    assert len(error.splitlines()) == 1 and message in error, error
    assert f"jax:{HERE}:broken_{name}" in error
    assert not out.exists()


@pytest.mark.parametrize(("env_id", "message"), [
    ("jax:", "'jax:' must look like jax:package.module:factory"),
    ("jax:no_such_module_here:make", "cannot import 'no_such_module_here'"),
    (f"jax:{HERE}:missing_factory", f"module {HERE!r} has no 'missing_factory'"),
])
def test_bad_ids_are_one_error_line(
    env_id: str, message: str, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    assert main(["train", "--env", env_id, "--steps", "100", "--out", str(tmp_path / "r")]) == 2
    assert message in capsys.readouterr().err


def test_a_module_that_turns_on_64_bit_jax_is_one_error_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Training would crash with a traceback deep in the update (float64 against float32
    branches), even for an environment that returns float32."""
    (tmp_path / "x64_env.py").write_text(
        "import jax\n"
        "jax.config.update('jax_enable_x64', True)\n"
        f"from {HERE} import target_game as make_env\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "run"
    try:
        assert main(["train", "--env", "jax:x64_env:make_env", "--steps", "100",
                     "--out", str(out)]) == 2
    finally:
        jax.config.update("jax_enable_x64", False)
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1, error
    assert "64-bit JAX is on (jax_enable_x64" in error
    assert not out.exists()


@pytest.mark.parametrize(("agents", "choices"), [(3, 3), (2, 5)])
def test_the_documented_example_env_honours_its_options(
    agents: int, choices: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """docs/own-environment.md's smallest protocol env, copied from the page: its targets cover
    every choice it is given, and its episodes last `max_episode_steps`."""
    readme = (Path(__file__).resolve().parents[1] / "docs" / "own-environment.md").read_text()
    block = readme.split("The smallest one", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    (tmp_path / "readme_target.py").write_text(textwrap.dedent(block))
    monkeypatch.syspath_prepend(str(tmp_path))
    env = make_env("jax:readme_target:make_env", agents=agents, choices=choices)
    state, first = env.reset(jax.random.PRNGKey(0))

    def step(state: Any, key: jax.Array) -> tuple[Any, tuple[jax.Array, jax.Array]]:
        state, timestep = env.step(key, state, jnp.zeros(agents, jnp.int32))
        return state, (jnp.argmax(timestep.obs[0]), timestep.done)

    _, (targets, dones) = jax.lax.scan(step, state, jax.random.split(jax.random.PRNGKey(1), 200))
    assert first.obs.shape == (agents, choices)
    assert set(np.asarray(targets).tolist()) == set(range(choices))
    assert np.flatnonzero(np.asarray(dones)).tolist() == list(range(4, 200, 5))


def test_factory_options_come_from_env_kwargs() -> None:
    env = make_env(f"jax:{HERE}:target_game", agents=5, choices=4)
    assert (env.spec.num_agents, env.spec.action_dim) == (5, 4)
    with pytest.raises(CmatError, match="the factory raised TypeError"):
        make_env(f"jax:{HERE}:target_game", colour="red")
