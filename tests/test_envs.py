"""Environment contract tests: matrix games, SMAX and MPE adapters, the registry and its errors."""

from __future__ import annotations

import re
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cmat.envs import MarlEnv, TimeStep, make_env
from cmat.envs.jaxmarl_envs import SMAX_SCENARIOS, SmaxEnv
from cmat.errors import CmatError

pytestmark = [pytest.mark.unit, pytest.mark.quick_compiles]

NUM_ENVS = 8
NUM_STEPS = 150


def random_legal_actions(key: jax.Array, action_mask: jax.Array) -> jax.Array:
    return jax.random.categorical(key, jnp.where(action_mask, 0.0, -jnp.inf))


def episode_step(state: Any) -> jax.Array:
    """The step counter of a JaxMARL state (SMAX nests its state under `.state`)."""
    return getattr(state, "state", state).step


def rollout(env: MarlEnv, key: jax.Array) -> tuple[TimeStep, TimeStep, jax.Array]:
    """Reset timestep, [steps, envs, ...] timesteps and episode step counters of a random policy."""

    def one_step(carry: tuple[Any, TimeStep], key: jax.Array) -> tuple[Any, Any]:
        state, timestep = carry
        action_key, step_key = jax.random.split(key)
        actions = random_legal_actions(action_key, timestep.action_mask)
        state, timestep = jax.vmap(env.step)(jax.random.split(step_key, NUM_ENVS), state, actions)
        return (state, timestep), (timestep, episode_step(state))

    reset_key, scan_key = jax.random.split(key)
    state, first = jax.vmap(env.reset)(jax.random.split(reset_key, NUM_ENVS))
    _, (timesteps, steps) = jax.lax.scan(
        one_step, (state, first), jax.random.split(scan_key, NUM_STEPS)
    )
    return first, timesteps, steps


@pytest.fixture(scope="module", params=["smax:3m", "mpe:simple_spread"])
def rolled(request: pytest.FixtureRequest) -> tuple[MarlEnv, TimeStep, TimeStep, np.ndarray]:
    env = make_env(request.param)
    first, timesteps, steps = jax.jit(lambda key: rollout(env, key))(jax.random.key(0))
    return env, first, jax.tree.map(np.asarray, timesteps), np.asarray(steps)


# Matrix games.


def test_fig1_pays_the_paper_payoff_and_ends_every_step() -> None:
    env = make_env("matrix:fig1")
    assert (env.spec.num_agents, env.spec.action_dim, env.spec.max_episode_steps) == (2, 2, 1)
    assert not env.spec.has_win_rate
    state, first = env.reset(jax.random.key(0))
    assert not first.done and first.reward == 0.0
    step = jax.jit(env.step)
    for (a1, a2), payoff in {(0, 0): 1.0, (1, 0): -100.0, (0, 1): 0.0, (1, 1): 100.0}.items():
        _, timestep = step(jax.random.key(1), state, jnp.array([a1, a2]))
        assert timestep.reward == payoff and timestep.reward.dtype == jnp.float32
        assert timestep.done and not timestep.won
        np.testing.assert_array_equal(timestep.obs, np.eye(2, dtype=np.float32))
        assert timestep.action_mask.dtype == jnp.bool_ and timestep.action_mask.all()
        assert timestep.action_mask.shape == (2, 2)


def test_custom_payoff_replaces_fig1() -> None:
    payoff = [[0, 1, 2], [3, 4, 5], [6, 7, 8]]
    env = make_env("matrix:fig1", payoff=payoff)
    assert env.spec.action_dim == 3
    state, _ = env.reset(jax.random.key(0))
    actions = jnp.array([[i, j] for i in range(3) for j in range(3)])
    _, timesteps = jax.vmap(env.step, in_axes=(None, None, 0))(jax.random.key(1), state, actions)
    np.testing.assert_array_equal(timesteps.reward, np.ravel(payoff))
    assert timesteps.action_mask.shape == (9, 2, 3)


@pytest.mark.parametrize("k", ["abc", None, float("inf"), float("nan"), True, [1.0]])
def test_a_penalty_that_is_not_a_finite_number_is_named(k: object) -> None:
    with pytest.raises(CmatError, match=f"matrix:penalty: k must be a finite number, got "
                                        f"{re.escape(repr(k))}$"):
        make_env("matrix:penalty", k=k)


@pytest.mark.parametrize("k", [-100.0, -5.0, -7])
def test_penalty_game(k: float) -> None:
    env = make_env("matrix:penalty", k=k)
    state, _ = env.reset(jax.random.key(0))
    expected = [[10, 0, k], [0, 2, 0], [k, 0, 10]]
    for a1 in range(3):
        for a2 in range(3):
            _, timestep = env.step(jax.random.key(0), state, jnp.array([a1, a2]))
            assert timestep.reward == expected[a1][a2]


@pytest.mark.parametrize(
    "payoff", [[[1, 2], [3]], [[1.0]], [[1, 2, 3], [4, 5, 6]], "ab", [[1, float("nan")], [0, 1]]]
)
def test_malformed_payoff_is_rejected(payoff: Any) -> None:
    with pytest.raises(CmatError, match="malformed payoff"):
        make_env("matrix:fig1", payoff=payoff)


# JaxMARL adapters under jit + vmap + scan with random legal actions.


def test_rollout_shapes_and_dtypes(rolled: tuple[MarlEnv, TimeStep, TimeStep, np.ndarray]) -> None:
    env, first, timesteps, _ = rolled
    n, spec = NUM_ENVS, env.spec
    assert first.obs.shape == (n, spec.num_agents, spec.obs_dim)
    leading = (NUM_STEPS, n)
    assert timesteps.obs.shape == (*leading, spec.num_agents, spec.obs_dim)
    assert timesteps.action_mask.shape == (*leading, spec.num_agents, spec.action_dim)
    assert timesteps.reward.shape == timesteps.done.shape == timesteps.won.shape == leading
    assert timesteps.obs.dtype == np.float32 and timesteps.reward.dtype == np.float32
    assert timesteps.action_mask.dtype == timesteps.done.dtype == timesteps.won.dtype == np.bool_
    assert np.isfinite(timesteps.obs).all() and np.isfinite(timesteps.reward).all()
    assert timesteps.action_mask.any(axis=-1).all()
    assert not (timesteps.won & ~timesteps.done).any()


def test_episodes_end_within_max_episode_steps(
    rolled: tuple[MarlEnv, TimeStep, TimeStep, np.ndarray],
) -> None:
    env, _, timesteps, steps = rolled
    for done in timesteps.done.T:
        ends = np.flatnonzero(done) + 1
        assert ends.size > 0
        assert np.diff(ends, prepend=0).max() <= env.spec.max_episode_steps
    np.testing.assert_array_equal(steps == 0, timesteps.done)
    if not env.spec.has_win_rate:
        assert not timesteps.won.any()


def test_auto_reset_returns_the_new_episodes_mask(
    rolled: tuple[MarlEnv, TimeStep, TimeStep, np.ndarray],
) -> None:
    env, first, timesteps, _ = rolled
    reset_mask = np.asarray(first.action_mask[0])
    assert (timesteps.action_mask[timesteps.done] == reset_mask).all()
    if isinstance(env, SmaxEnv):
        assert not reset_mask[:, env.env.num_movement_actions:].any()


# SMAX win condition on constructed terminal states (random play on 3m wins ~never: 0 of 1,775
# episodes), each at the time limit so that only `won` tells them apart.


@pytest.fixture(scope="module")
def smax_3m() -> tuple[SmaxEnv, Any]:
    env = make_env("smax:3m")
    assert isinstance(env, SmaxEnv)
    return env, jax.jit(env.step)


@pytest.mark.parametrize(
    ("allies_alive", "enemies_alive", "won"),
    [(True, False, True), (False, False, False), (False, True, False), (True, True, False)],
)
def test_smax_won_on_constructed_terminal_state(
    smax_3m: tuple[SmaxEnv, Any], allies_alive: bool, enemies_alive: bool, won: bool
) -> None:
    env, step = smax_3m
    state, _ = env.reset(jax.random.key(0))
    n_allies = env.env.num_allies
    alive = jnp.arange(state.state.unit_health.shape[0]) < n_allies
    alive = jnp.where(alive, allies_alive, enemies_alive)
    state = state.replace(state=state.state.replace(
        unit_health=jnp.where(alive, state.state.unit_health, 0.0), step=env.env.max_steps
    ))
    stop = jnp.full((n_allies,), env.env.num_movement_actions - 1)
    new_state, timestep = step(jax.random.key(1), state, stop)
    assert timestep.done and timestep.won == won
    assert timestep.reward >= (1.0 if won else 0.0)
    assert new_state.state.step == 0 and new_state.state.unit_alive.all()
    np.testing.assert_array_equal(
        timestep.obs, jnp.stack(list(env.env.get_obs(new_state).values()))
    )
    np.testing.assert_array_equal(
        timestep.action_mask, jnp.stack(list(env.env.get_avail_actions(new_state).values()))
    )


def test_smax_not_won_before_the_end(smax_3m: tuple[SmaxEnv, Any]) -> None:
    env, step = smax_3m
    state, _ = env.reset(jax.random.key(0))
    _, timestep = step(jax.random.key(1), state, jnp.full((3,), 4))
    assert not timestep.done and not timestep.won


@pytest.mark.parametrize("scenario", SMAX_SCENARIOS)
def test_every_smax_scenario_builds(scenario: str) -> None:
    env = make_env(f"smax:{scenario}")
    spec = env.spec
    assert spec.env_id == f"smax:{scenario}" and spec.has_win_rate and spec.discrete
    _state, timestep = jax.eval_shape(env.reset, jax.random.key(0))
    assert timestep.obs.shape == (spec.num_agents, spec.obs_dim)
    assert timestep.action_mask.shape == (spec.num_agents, spec.action_dim)


@pytest.mark.parametrize("n", [3, 8, 40])
def test_marine_teams_of_any_size_are_smaxs_own_construction(n: int) -> None:
    """`smax:Nm` is N marines a side; for 3m and 8m it is exactly SMAX's own map."""
    env = make_env(f"smax:{n}m")
    assert env.spec.num_agents == n and env.spec.action_dim == 5 + n
    state, timestep = env.reset(jax.random.key(0))
    assert timestep.obs.shape == (n, env.spec.obs_dim)
    _, after = env.step(jax.random.key(1), state, jnp.zeros((n,), jnp.int32))
    assert after.obs.shape == timestep.obs.shape
    if n in (3, 8):
        from jaxmarl.environments.smax import map_name_to_scenario

        from cmat.envs.jaxmarl_envs import marine_team

        own, built = map_name_to_scenario(f"{n}m"), marine_team(n)
        np.testing.assert_array_equal(built.unit_types, own.unit_types)
        assert (built.num_allies, built.num_enemies, built.smacv2_position_generation,
                built.smacv2_unit_type_generation) == (own.num_allies, own.num_enemies,
                                                       own.smacv2_position_generation,
                                                       own.smacv2_unit_type_generation)


def test_smax_3m_spec() -> None:
    spec = make_env("smax:3m").spec
    shape = (spec.num_agents, spec.obs_dim, spec.action_dim, spec.max_episode_steps)
    assert shape == (3, 75, 8, 101)


# Registry: agent ids and errors.


@pytest.mark.parametrize("env_id", ["matrix:fig1", "mpe:simple_spread"])
def test_agent_id_appends_identity(env_id: str) -> None:
    plain, tagged = make_env(env_id), make_env(env_id, agent_id=True)
    n = plain.spec.num_agents
    assert tagged.spec.obs_dim == plain.spec.obs_dim + n
    key = jax.random.key(3)
    state, plain_first = plain.reset(key)
    tagged_state, tagged_first = tagged.reset(key)
    np.testing.assert_array_equal(tagged_first.obs[:, -n:], np.eye(n))
    np.testing.assert_array_equal(tagged_first.obs[:, :-n], plain_first.obs)
    actions = jnp.zeros((n,), dtype=jnp.int32)
    _, tagged_next = tagged.step(key, tagged_state, actions)
    _, plain_next = plain.step(key, state, actions)
    np.testing.assert_array_equal(tagged_next.obs[:, -n:], np.eye(n))
    np.testing.assert_array_equal(tagged_next.obs[:, :-n], plain_next.obs)


@pytest.mark.parametrize(
    ("env_id", "kwargs", "bad"),
    [
        ("foo:bar", {}, "foo"),
        ("3m", {}, "3m"),
        ("smax:foo", {}, "foo"),
        ("smax:0m", {}, "0m"),
        ("smax:1000m", {}, "1000m"),
        ("mpe:simple_tag", {}, "simple_tag"),
        ("matrix:nope", {}, "nope"),
        ("smax:3m", {"bogus": 1}, "bogus"),
        ("smax:3m", {"action_type": "continuous"}, "action_type"),
        ("matrix:fig1", {"k": 1.0}, "k"),
        ("matrix:penalty", {"payoff": [[1, 0], [0, 1]]}, "payoff"),
        ("mpe:simple_spread", {"colour": None}, "colour"),
    ],
)
def test_bad_ids_and_options_raise_one_line_errors(
    env_id: str, kwargs: dict[str, Any], bad: str
) -> None:
    with pytest.raises(CmatError) as error:
        make_env(env_id, **kwargs)
    message = str(error.value)
    assert f"'{bad}'" in message and "\n" not in message
    assert "available" in message or "accepted" in message
