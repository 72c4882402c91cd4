"""Jumanji (RWARE, LBF) and MABrax adapters: specs against the arrays they return, automatic reset
against a fresh reset and against the wrapped environment itself, episode returns, the registry's
errors, the suites' settings and `cmat train` end to end."""

from __future__ import annotations

import csv
import importlib.util
import math
import re
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cmat.algorithms import algorithm_names
from cmat.cli import main
from cmat.envs import MarlEnv, TimeStep, make_env
from cmat.envs.jumanji_envs import LBF_SCENARIOS, RWARE_SCENARIOS, TASKS, JumanjiEnv
from cmat.envs.suites import MAVA_SETTINGS, SUITES
from cmat.errors import CmatError
from cmat.resolve import resolve_config
from cmat.rundir import RunDir
from cmat.runners.evaluation import tally_result, tally_start, tally_step

pytestmark = pytest.mark.quick_compiles

NUM_ENVS = 4
HAS_BRAX = importlib.util.find_spec("brax") is not None


class Record(NamedTuple):
    """One step of `NUM_ENVS` environments, [envs, ...] each."""

    timestep: TimeStep
    fresh: TimeStep
    """A reset with the key `step` draws the next episode with (`reset_key`)."""
    inner_done: jax.Array
    inner_reward: jax.Array
    """The wrapped environment's own episode end and team reward (summed over agents)."""
    inner_obs: jax.Array
    """The wrapped environment's own next observation, before any reset."""
    count_before: jax.Array
    count_after: jax.Array
    """Steps into the episode before and after `step` (0: a first state)."""


def step_count(state: Any) -> jax.Array:
    """Jumanji's `step_count`, or Brax's `EpisodeWrapper` step counter."""
    return state[".step_count"] if isinstance(state, dict) else state.info["steps"].astype(int)


def inner_step(env: MarlEnv, key: jax.Array, state: Any, actions: jax.Array) -> tuple[Any, ...]:
    """The wrapped environment's own step: (done, team reward, next obs [n_agents, obs_dim])."""
    if isinstance(env, JumanjiEnv):
        _, timestep = env.env.step(env.jumanji_state(state), actions)
        view = timestep.observation.agents_view
        return timestep.last(), jnp.sum(timestep.reward), view.reshape(view.shape[0], -1)
    _, timestep = env.step_in_episode(key, state, actions)
    return timestep.done, timestep.reward, timestep.obs


def reset_key(key: jax.Array) -> jax.Array:
    """The key `step` draws the next episode with (`JaxMarlEnv.step`'s convention)."""
    return jax.random.split(key)[1]


def random_actions(env: MarlEnv, key: jax.Array, mask: jax.Array) -> jax.Array:
    """Uniform legal discrete actions, or uniform continuous actions in the spec's bounds."""
    spec = env.spec
    if spec.discrete:
        return jax.random.categorical(key, jnp.where(mask, 0.0, -jnp.inf))
    return jax.random.uniform(key, mask.shape, minval=spec.action_low, maxval=spec.action_high)


def rollout(env: MarlEnv, key: jax.Array, steps: int) -> tuple[TimeStep, Any, Record]:
    """`steps` random steps of `NUM_ENVS` environments: first timestep, first state, [steps, ...]
    records."""
    step = jax.vmap(env.step)
    reset = jax.vmap(env.reset)
    inner = jax.vmap(lambda k, s, a: inner_step(env, k, s, a))

    def one_step(carry: tuple[Any, TimeStep], key: jax.Array) -> tuple[Any, Record]:
        state, timestep = carry
        action_key, step_key = jax.random.split(key)
        actions = random_actions(env, action_key, timestep.action_mask)
        keys = jax.random.split(step_key, NUM_ENVS)
        next_state, next_timestep = step(keys, state, actions)
        _, fresh = reset(jax.vmap(reset_key)(keys))
        inner_done, inner_reward, inner_obs = inner(keys, state, actions)
        record = Record(next_timestep, fresh, inner_done, inner_reward, inner_obs,
                        step_count(state), step_count(next_state))
        return (next_state, next_timestep), record

    first_key, scan_key = jax.random.split(key)
    state, first = reset(jax.random.split(first_key, NUM_ENVS))
    _, records = jax.lax.scan(one_step, (state, first), jax.random.split(scan_key, steps))
    return first, state, records


ROLLED = [
    ("jumanji:rware-tiny-2ag", {"time_limit": 60}),
    ("jumanji:lbf-10x10-3p-3f", {}),
    pytest.param(("mabrax:hopper_3x1", {"episode_length": 10}), marks=[
        pytest.mark.slow,
        pytest.mark.skipif(not HAS_BRAX, reason="brax is not installed"),
    ]),
]
"""Rolled out for 2 × their episode limit. MABrax is `slow` (run with -m slow): compiling Brax's
step takes ~45 s of this fixture's ~75 s on a busy 2-core machine."""


@pytest.fixture(scope="module", params=ROLLED, ids=["rware", "lbf", "mabrax"])
def rolled(request: pytest.FixtureRequest) -> tuple[MarlEnv, TimeStep, Any, Record]:
    env_id, options = request.param
    env = make_env(env_id, **options)
    steps = 2 * env.spec.max_episode_steps
    first, state, records = jax.jit(lambda key: rollout(env, key, steps))(jax.random.PRNGKey(0))
    return env, jax.tree.map(np.asarray, first), state, jax.tree.map(np.asarray, records)


def test_rollout_matches_the_spec(rolled: tuple[MarlEnv, TimeStep, Any, Record]) -> None:
    env, first, _, records = rolled
    spec, timesteps = env.spec, records.timestep
    steps = 2 * spec.max_episode_steps
    for leading, timestep in (((NUM_ENVS,), first), ((steps, NUM_ENVS), timesteps)):
        assert timestep.obs.shape == (*leading, spec.num_agents, spec.obs_dim)
        assert timestep.action_mask.shape == (*leading, spec.num_agents, spec.action_dim)
        assert timestep.alive.shape == (*leading, spec.num_agents)
        assert timestep.global_state.shape == (*leading, spec.state_dim)
        assert timestep.reward.shape == timestep.done.shape == timestep.won.shape == leading
        assert timestep.obs.dtype == timestep.reward.dtype == timestep.global_state.dtype
        assert timestep.obs.dtype == np.float32
        for flag in (timestep.action_mask, timestep.done, timestep.won, timestep.alive):
            assert flag.dtype == np.bool_
        assert timestep.action_mask.any(axis=-1).all()
        assert timestep.alive.all() and not timestep.won.any()
        assert np.isfinite(timestep.obs).all() and np.isfinite(timestep.reward).all()
    assert not first.done.any() and not first.reward.any()
    assert not spec.has_win_rate
    assert spec.discrete == env.spec.env_id.startswith("jumanji:")
    if not spec.discrete:
        assert timesteps.action_mask.all()


def test_done_exactly_at_episode_ends(rolled: tuple[MarlEnv, TimeStep, Any, Record]) -> None:
    """`done` is the wrapped environment's episode end; every episode that reaches the time
    limit ends there, and `done` starts a fresh episode while anything else continues one."""
    env, _, _, records = rolled
    done, limit = records.timestep.done, env.spec.max_episode_steps
    np.testing.assert_array_equal(done, records.inner_done)
    at_limit = records.count_before + 1 == limit
    assert (done[at_limit]).all() and at_limit.any()
    np.testing.assert_array_equal(records.count_after[done], 0)
    np.testing.assert_array_equal(records.count_after[~done], records.count_before[~done] + 1)
    for env_done in done.T:
        lengths = np.diff(np.flatnonzero(env_done), prepend=-1)
        assert lengths.size >= 2 and lengths.max() <= limit


def test_auto_reset_gives_a_fresh_episodes_first_step(
    rolled: tuple[MarlEnv, TimeStep, Any, Record],
) -> None:
    """After `done`: the first observation, mask and global state of a reset with the step's
    `reset_key`; otherwise the wrapped environment's own next observation. Reward and `done`
    are always those of the transition taken."""
    _, _, _, records = rolled
    timestep, fresh, done = records.timestep, records.fresh, records.timestep.done
    for field in ("obs", "action_mask", "global_state"):
        np.testing.assert_array_equal(getattr(timestep, field)[done], getattr(fresh, field)[done])
    assert not fresh.done.any() and not fresh.reward.any()
    np.testing.assert_array_equal(timestep.obs[~done], records.inner_obs[~done])
    np.testing.assert_allclose(timestep.reward, records.inner_reward, rtol=1e-6)


def test_episode_returns_are_the_sums_of_rewards(
    rolled: tuple[MarlEnv, TimeStep, Any, Record],
) -> None:
    """cmat's episode tally (`cmat.runners.evaluation`), one slot per env counting its first
    episode, gives each env the sum of its team rewards up to its first `done`."""
    env, _, _, records = rolled
    reward, done, won = records.timestep.reward, records.timestep.done, records.timestep.won
    quota = np.ones((NUM_ENVS, 1), np.int32)
    tally = tally_start((NUM_ENVS, 1), env.spec)
    for t in range(reward.shape[0]):
        tally = tally_step(tally, reward[t, :, None], done[t, :, None], won[t, :, None], quota)
    returns = tally_result(tally, quota, 1, env.spec)["episode_return"]
    ends = done.argmax(axis=0)
    expected = [reward[: ends[i] + 1, i].sum() for i in range(NUM_ENVS)]
    np.testing.assert_allclose(returns, expected, rtol=1e-5, atol=1e-6)
    if env.spec.env_id.startswith(("jumanji:lbf", "mabrax:")):
        assert (reward != 0).any()


# Every task: the spec is what the scenario's name says, and what reset and step return.

TASK_AGENTS = re.compile(r"-(\d+)(?:ag|p)(?:-|$)")


@pytest.mark.parametrize("task", list(TASKS))
def test_every_task_builds_with_its_scenarios_sizes(task: str) -> None:
    env = make_env(f"jumanji:{task}")
    spec = env.spec
    match = TASK_AGENTS.search(task)
    assert match is not None
    assert spec.num_agents == int(match.group(1))
    if task.startswith("rware-"):
        params = RWARE_SCENARIOS[task.removeprefix("rware-")]
        assert (spec.obs_dim, spec.action_dim, spec.max_episode_steps) == (66, 5, 500)
    else:
        params = LBF_SCENARIOS[task.removeprefix("lbf-")]
        assert spec.obs_dim == 3 * (params["num_food"] + spec.num_agents)
        assert (spec.action_dim, spec.max_episode_steps) == (6, 100)
    assert params["num_agents"] == spec.num_agents
    assert spec.discrete and not spec.has_win_rate and spec.state_dim == 0
    key = jax.random.PRNGKey(0)
    state, first = jax.eval_shape(env.reset, key)
    _, after = jax.eval_shape(env.step, key, state, jnp.zeros(spec.num_agents, jnp.int32))
    for timestep in (first, after):
        assert timestep.obs.shape == (spec.num_agents, spec.obs_dim)
        assert timestep.action_mask.shape == (spec.num_agents, spec.action_dim)
        assert timestep.global_state.shape == (0,)


def test_options_reach_the_environment() -> None:
    lbf = make_env("jumanji:lbf-2s-8x8-2p-2f-coop", time_limit=7, penalty=0.5)
    assert isinstance(lbf, JumanjiEnv)
    assert lbf.spec.max_episode_steps == 7 and lbf.env.penalty == 0.5
    with_ids = make_env("jumanji:rware-tiny-4ag", agent_id=True)
    assert with_ids.spec.obs_dim == 66 + 4


@pytest.mark.parametrize(
    ("env_id", "kwargs", "bad"),
    [
        ("jumanji:rware-nope", {}, "rware-nope"),
        ("jumanji:", {}, ""),
        ("jumanji:lbf-8x8-2p-2f-coop", {"fov": 3}, "fov"),
        ("jumanji:rware-tiny-2ag", {"penalty": 1.0}, "penalty"),
        ("mabrax:nope", {}, "nope"),
        ("mabrax:hopper_3x1", {"homogenisation_method": "max"}, "homogenisation_method"),
    ],
)
def test_bad_ids_and_options_raise_one_line_errors(
    env_id: str, kwargs: dict[str, Any], bad: str
) -> None:
    if env_id.startswith("mabrax:") and not HAS_BRAX:
        pytest.skip("brax is not installed")
    with pytest.raises(CmatError) as error:
        make_env(env_id, **kwargs)
    message = str(error.value)
    assert f"'{bad}'" in message and "\n" not in message
    assert "available: " in message or "accepted: agent_id, " in message


def test_mabrax_without_brax_names_the_package(monkeypatch: pytest.MonkeyPatch) -> None:
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *args: None if name == "brax" else find_spec(name, *args))
    with pytest.raises(CmatError) as error:
        make_env("mabrax:ant_4x2")
    message = str(error.value)
    assert "brax" in message and "pip install 'brax>=0.14.2,<0.15'" in message
    assert "\n" not in message


# Suites and the CLI.


@pytest.mark.parametrize("env_id", ["jumanji:rware-small-4ag", "mabrax:walker2d_2x3"])
def test_suite_settings_are_mavas_with_their_source(env_id: str) -> None:
    config, sources = resolve_config(overrides=[f"env={env_id}"])
    suite = env_id.partition(":")[0]
    assert SUITES[suite].settings is MAVA_SETTINGS
    assert (config.ppo.lr, config.ppo.epochs, config.ppo.num_minibatches) == (2.5e-4, 4, 2)
    assert (config.num_envs, config.rollout_length, config.env_kwargs) == (
        32, 128, {"agent_id": True})
    assert config.total_steps == 1000 * 128 * 16 * 2
    assert config.total_steps % (config.num_envs * config.rollout_length) == 0
    for name in ("ppo.lr", "ppo.clip_eps", "num_envs", "total_steps", "env_kwargs"):
        assert sources[name] == f"suite {suite}", name


TINY = ["num_envs=4", "rollout_length=16", "log_interval=2", "ppo.epochs=1",
        "ppo.num_minibatches=1", "eval_episodes=2", "env_kwargs.time_limit=16"]


FAST_PAIRS = {("jumanji:rware-tiny-2ag", "mappo")}
"""Run by CI; every other (task, algorithm) pair is `slow` (about 50 s each, nearly all of it
compiling; Sable's update is checked in the fast suite by tests/test_sable.py)."""


@pytest.mark.parametrize(("env_id", "algo"), [
    pytest.param(env_id, algo, marks=[] if (env_id, algo) in FAST_PAIRS else pytest.mark.slow)
    for env_id in ("jumanji:rware-tiny-2ag", "jumanji:lbf-2s-8x8-2p-2f-coop")
    for algo in algorithm_names()
])
def test_cmat_train_end_to_end(env_id: str, algo: str, tmp_path: Path) -> None:
    """A few updates of every algorithm on each suite, through `cmat train`."""
    out = tmp_path / "run"
    argv = ["train", "--env", env_id, "--algo", algo, "--steps", "256", "--set", *TINY,
            "--out", str(out)]
    assert main(argv) == 0
    with (out / "metrics.csv").open(newline="") as file:
        rows = list(csv.DictReader(file))
    assert {r["kind"] for r in rows} == {"train", "eval", "absolute"}
    assert max(int(r["env_steps"]) for r in rows) == 256
    evals = [r for r in rows if r["kind"] == "eval"]
    assert all(math.isfinite(float(r["episode_return"])) and r["win_rate"] == "nan"
               for r in evals)
    assert all(math.isfinite(float(r["policy_loss"])) for r in rows if r["kind"] == "train")
    config, sources = RunDir.open(out).config(), RunDir.open(out).sources()
    assert (config.algo, config.env_kwargs) == (algo, {"agent_id": True, "time_limit": 16})
    assert sources["ppo.gae_lambda"] == "suite jumanji" and sources["env_kwargs"] == "command line"
