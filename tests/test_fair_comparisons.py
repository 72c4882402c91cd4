"""Each baseline trains as its reference does, and no run blows up silently.

Reference behaviours (target critic τ, initialisation, active masks, MAT's per-agent GAE,
MAPPO's critic on the world state) are checked against plain numpy or hand-computed references;
numerical safety (clamped joint log-ratio, non-finite stop), exact budgets and range checks of
the config end to end.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from test_ppo import plain_gae

from cmat.algorithms import build_algorithm
from cmat.algorithms.base import Batch
from cmat.algorithms.ppo import (
    LOG_RATIO_BOUND,
    clipped_surrogate_loss,
    masked_mean,
    normalize,
    value_loss,
)
from cmat.cli import main
from cmat.config import PPOConfig
from cmat.envs import make_env
from cmat.envs.protocol import EnvSpec
from cmat.resolve import load_config
from cmat.rundir import RunDir
from cmat.runners import trainer as trainer_lib
from cmat.runners.collector import rollout_report
from cmat.runners.learner import ROLLOUT_FAULTS, make_batch, summarise_updates, update_fault_code
from cmat.runners.trainer import JaxTrainer, build_setup, init_state
from cmat.runners.types import Transition

pytestmark = pytest.mark.quick_compiles

REFERENCE = {
    "cmat": (1.0, False, False),
    "triple_bert": (0.1, False, False),
    "mat": (1.0, True, True),
    "pmat": (1.0, True, True),
    "mappo": (1.0, True, False),
    "happo": (1.0, True, False),
    "sable": (1.0, False, True),
    "ff_sable": (1.0, False, True),
}
"""algo -> (ppo.target_tau, ppo.active_masks, ALGO.per_agent_gae) of its reference (CMAT: its
default, the learning-speed study's setting; False where the algorithm has no per-agent
values)."""


def one_error_line(stderr: str) -> str:
    """The one `cmat: error:` line of a failed command (a progress bar may precede it)."""
    assert "Traceback" not in stderr
    lines = [line for line in stderr.strip().splitlines() if line.startswith("cmat:")]
    assert len(lines) == 1 and lines[0].startswith("cmat: error: "), stderr
    assert stderr.strip().splitlines()[-1] == lines[0]
    return lines[0]


def spec(n: int = 3, discrete: bool = True, state_dim: int = 0) -> EnvSpec:
    return EnvSpec("test", n, 6, 4, discrete, 10, False, state_dim=state_dim)


# ------------------------------------------------------------------------- reference defaults
@pytest.mark.parametrize("algo", sorted(REFERENCE))
def test_each_algorithm_gets_its_reference_defaults(algo: str) -> None:
    config = load_config(overrides=[f"algo={algo}"])
    per_agent_gae = getattr(config.options, "per_agent_gae", False)
    assert (config.ppo.target_tau, config.ppo.active_masks, per_agent_gae) == REFERENCE[algo]
    overridden = load_config(overrides=[f"algo={algo}", "ppo.target_tau=0.5"])
    assert overridden.ppo.target_tau == 0.5


@pytest.mark.parametrize("algo", ["mat", "pmat"])
def test_mat_regresses_dead_agents_values_as_its_smac_script(algo: str) -> None:
    """`train_smac.sh` passes `--use_value_active_masks`, a store_false flag: MAT's policy loss
    leaves dead agents out, its value loss does not."""
    config = load_config(overrides=[f"algo={algo}", "env=smax:3m"])
    assert config.ppo.active_masks and config.ppo.value_active_masks is False


def test_pmat_trains_as_its_smac_script() -> None:
    """NUDT-BI-MARL/PMAT `train_smac.sh` passes `--ranking_loss_coef 1e-4`, and its training
    pass decodes the stored actions in index order; the option is PMAT's alone."""
    from cmat.errors import CmatError

    config = load_config(overrides=["algo=pmat", "env=smax:3m"])
    assert (config.options.order_loss_coef, config.options.order_in_loss) == (1e-4, "index")
    with pytest.raises(CmatError, match=r"unknown key mat\.order_in_loss"):
        load_config(overrides=["algo=mat", "mat.order_in_loss=index"])
    with pytest.raises(CmatError, match=r"pmat\.order_in_loss must be one of sampled, index"):
        load_config(overrides=["algo=pmat", "pmat.order_in_loss=random"])


def test_a_run_that_masked_mats_value_loss_is_not_reused() -> None:
    """A config written before `ppo.value_active_masks` existed (read as None: as active_masks)
    is not the reference MAT's, so an experiment redoes its run."""
    from cmat.experiments.plan import config_difference

    expected = load_config(overrides=["algo=mat", "env=smax:3m"])
    old = dataclasses.replace(
        expected, ppo=dataclasses.replace(expected.ppo, value_active_masks=None)
    )
    assert config_difference(old, expected) == "ppo.value_active_masks: None, spec False"
    assert config_difference(expected, expected) is None


MAPPO_SCRIPTS = {
    "smax:5m_vs_6m": (10, 0.05, 1, 0.01),
    "smax:10m_vs_11m": (10, 0.2, 1, 0.01),
    "smax:MMM2": (5, 0.2, 2, 1.0),
    "smax:3s5z_vs_3s6z": (5, 0.2, 1, 0.01),
    "smax:2s3z": (5, 0.2, 1, 0.01),
}
"""env -> (ppo_epoch, clip_param, num_mini_batch, gain) of on-policy's
train_smac_scripts/train_smac_MAP.sh (2s3z has none: the shared values)."""


@pytest.mark.parametrize("env", sorted(MAPPO_SCRIPTS))
def test_mappo_takes_its_per_map_smac_script_values(env: str) -> None:
    config = load_config(overrides=["algo=mappo", f"env={env}"])
    got = (config.ppo.epochs, config.ppo.clip_eps, config.ppo.num_minibatches,
           config.network.init_gain)
    assert got == MAPPO_SCRIPTS[env]
    mine = load_config(overrides=["algo=mappo", f"env={env}", "ppo.epochs=3"])
    assert mine.ppo.epochs == 3


def test_happo_takes_harls_tuned_config_of_the_map() -> None:
    tuned = load_config(overrides=["algo=happo", "env=smax:3s5z_vs_3s6z"])
    assert (tuned.network.n_embd, tuned.options.mlp_layers, tuned.ppo.clip_eps,
            tuned.ppo.gamma, tuned.ppo.epochs, tuned.ppo.num_minibatches) == (
        64, 3, 0.1, 0.95, 5, 2)
    untuned = load_config(overrides=["algo=happo", "env=smax:2s3z"])
    assert (untuned.network.n_embd, untuned.options.mlp_layers, untuned.ppo.clip_eps,
            untuned.ppo.gamma) == (128, 2, 0.2, 0.99)
    other = load_config(overrides=["algo=mappo", "env=smax:3s5z_vs_3s6z"])
    assert (other.options.mlp_layers, other.ppo.gamma) == (2, 0.99)


def test_happo_builds_the_mlp_depth_it_is_given() -> None:
    config = load_config(overrides=["algo=happo", "env=smax:3s5z_vs_3s6z"])
    algorithm = build_algorithm("happo", config.network, spec(), config.ppo, config.options)
    params = algorithm.init(jax.random.PRNGKey(0), jnp.zeros((3, 6)), jnp.ones((3, 4), bool))
    hidden = [path for path in kernels(params["critic"]) if "MLPTrunk_0" in path]
    assert len(hidden) == 3


def test_mappo_appends_no_second_agent_id() -> None:
    """Where the environment's observations already end with the id (`env_kwargs.agent_id`),
    the shared actor reads them as they are."""
    config = load_config(overrides=["algo=mappo"])
    plain = build_algorithm("mappo", config.network, spec(), config.ppo, config.options)
    with_id = build_algorithm(
        "mappo", config.network, dataclasses.replace(spec(), agent_id=True), config.ppo
    )
    obs, mask = jnp.zeros((3, 6)), jnp.ones((3, 4), bool)
    for algorithm, width in ((plain, 9), (with_id, 6)):
        params = algorithm.init(jax.random.PRNGKey(0), obs, mask)
        assert params["actor"]["params"]["MLPTrunk_0"]["Dense_0"]["kernel"].shape[0] == width
    assert make_env("smax:3m", agent_id=True).spec.agent_id
    assert not make_env("smax:3m").spec.agent_id


@pytest.mark.parametrize("algo, tau", [("cmat", ["ppo.target_tau=0.1"]), ("mat", [])])
def test_target_critic_follows_tau(algo: str, tau: list[str]) -> None:
    """φ⁻ ← τφ + (1−τ)φ⁻ after an update, from a target moved away from the critic first:
    τ = 1 (MAT) copies the new critic, τ = 0.1 (the paper's CMAT) lags."""
    config = load_config(overrides=[
        "env=matrix:fig1", f"algo={algo}", "num_envs=4", "rollout_length=5", "ppo.epochs=2", *tau,
    ])
    setup = build_setup(config)
    state = jax.jit(lambda key: init_state(setup, key))(jax.random.PRNGKey(0))
    before = jax.tree.map(lambda x: x + 1.0, state.learner.target_params)
    state = state.replace(learner=state.learner.replace(target_params=before))
    after, _ = jax.jit(lambda s: trainer_lib.update_step(setup, s))(state)
    tau = config.ppo.target_tau
    expected = jax.tree.map(lambda new, old: tau * new + (1 - tau) * old, after.learner.params,
                            before)
    moved = jax.tree.map(lambda a, b: bool(np.any(np.asarray(a) != np.asarray(b))),
                         after.learner.params, state.learner.params)
    assert any(jax.tree.leaves(moved))
    for got, want in zip(jax.tree.leaves(after.learner.target_params), jax.tree.leaves(expected)):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    assert int(after.learner.update_step) == 1


# ----------------------------------------------------------------------------- initialisation
def kernels(params: dict, path: tuple[str, ...] = ()) -> dict[tuple[str, ...], np.ndarray]:
    found = {}
    for key, value in params.items():
        if isinstance(value, dict):
            found.update(kernels(value, (*path, key)))
        elif key == "kernel":
            found[path] = np.asarray(value)
    return found


def orthogonal_gain(kernel: np.ndarray) -> float:
    """g of an orthogonally initialised kernel g·Q: every singular value equals g."""
    singular = np.linalg.svd(kernel, compute_uv=False)
    np.testing.assert_allclose(singular, singular[0], rtol=1e-4)
    return float(singular[0])


@pytest.mark.parametrize("algo", ["cmat", "mat", "triple_bert"])
def test_transformers_start_with_the_reference_mat_gains(algo: str) -> None:
    """Gain 0.01 for Q, K, V, the attention output, the second FFN layer and the value output;
    √2 for the layers followed by an activation (ma_transformer.py's init_). Flax names a
    feed-forward block's layers in call-expression order, so its output layer is Dense_0."""
    network = load_config(overrides=[f"algo={algo}"]).network
    algorithm = build_algorithm(algo, network, spec(discrete=False))
    obs, mask = jnp.ones((3, 6)), jnp.ones((3, 4), bool)
    params = jax.jit(algorithm.init)(jax.random.PRNGKey(0), obs, mask)["params"]
    found = kernels(params)
    def feed_forward(path: tuple[str, ...]) -> bool:
        return len(path) > 1 and (path[-2].startswith("FeedForward") or path[-2] == "feed_forward")

    small = {path: k for path, k in found.items()
             if path[-1] in ("query", "key", "value", "out")
             or (feed_forward(path) and path[-1] == "Dense_0")}
    attentions = {"cmat": 3, "mat": 3, "triple_bert": 1}[algo]
    feed_forwards = {"cmat": 2, "mat": 2, "triple_bert": 1}[algo]
    assert len(small) == 4 * attentions + feed_forwards
    for path, kernel in small.items():
        assert orthogonal_gain(kernel) == pytest.approx(0.01, rel=1e-4), path
    first_ffn = [k for path, k in found.items() if feed_forward(path) and path[-1] == "Dense_1"]
    assert first_ffn and all(orthogonal_gain(k) == pytest.approx(math.sqrt(2), rel=1e-4)
                             for k in first_ffn)
    value_outputs = [k for path, k in found.items()
                     if any(p.startswith(("critic_mlp", "value_head")) for p in path)
                     and k.shape[-1] == 1]
    assert len(value_outputs) == 1
    assert np.linalg.norm(value_outputs[0]) == pytest.approx(0.01, rel=1e-4)


@pytest.mark.parametrize("discrete", [True, False])
def test_mats_action_embedding_has_a_bias_for_continuous_actions_only(discrete: bool) -> None:
    """ma_transformer.py: `nn.Linear(action_dim + 1, n_embd, bias=False)` for discrete actions,
    `nn.Linear(action_dim, n_embd)` for continuous ones."""
    network = load_config(overrides=["algo=mat"]).network
    algorithm = build_algorithm("mat", network, spec(discrete=discrete))
    obs, mask = jnp.ones((3, 6)), jnp.ones((3, 4), bool)
    params = jax.jit(algorithm.init)(jax.random.PRNGKey(0), obs, mask)
    embedding = params["params"]["action_embedding"]
    assert set(embedding) == ({"kernel"} if discrete else {"kernel", "bias"})


@pytest.mark.parametrize("algo", ["cmat", "mat", "pmat", "triple_bert", "mappo", "happo"])
def test_continuous_policies_start_at_std_sigmoid_one_half(algo: str) -> None:
    network = load_config(overrides=[f"algo={algo}"]).network
    algorithm = build_algorithm(algo, network, spec(discrete=False))
    params = jax.jit(algorithm.init)(
        jax.random.PRNGKey(0), jnp.ones((3, 6)), jnp.ones((3, 4), bool)
    )
    log_stds = [np.asarray(leaf) for path, leaf in jax.tree_util.tree_leaves_with_path(params)
                if "log_std" in jax.tree_util.keystr(path)]
    assert log_stds
    for log_std in log_stds:
        std = 0.5 / (1 + np.exp(-log_std))
        np.testing.assert_allclose(std, 0.5 / (1 + math.exp(-1.0)), rtol=1e-6)
        assert std.flat[0] == pytest.approx(0.3655, abs=1e-4)


# ------------------------------------------------------------------------------- active masks
def test_masked_pieces_equal_numpy_references() -> None:
    rng = np.random.default_rng(0)
    log_ratio = rng.normal(0, 0.3, (7, 3)).astype(np.float32)
    advantages = rng.normal(size=(7, 3)).astype(np.float32)
    alive = rng.random((7, 3)) > 0.3
    eps = 0.2
    ratio = np.exp(log_ratio)
    objective = np.minimum(ratio * advantages, np.clip(ratio, 1 - eps, 1 + eps) * advantages)
    loss, _ = clipped_surrogate_loss(jnp.asarray(log_ratio), jnp.asarray(advantages), eps,
                                     jnp.asarray(alive))
    assert float(loss) == pytest.approx(-objective[alive].mean(), rel=1e-5)
    values, old, targets = (rng.normal(size=(7, 3)).astype(np.float32) for _ in range(3))
    clipped = old + np.clip(values - old, -eps, eps)
    squared = np.maximum(0.5 * (targets - values) ** 2, 0.5 * (targets - clipped) ** 2)
    value_config = PPOConfig(clip_eps=eps, huber_loss=False, clipped_value_loss=True)
    got = value_loss(*map(jnp.asarray, (values, old, targets)), value_config, jnp.asarray(alive))
    assert float(got) == pytest.approx(squared[alive].mean(), rel=1e-5)
    normalised = normalize(jnp.asarray(advantages), jnp.asarray(alive), eps=0.0)
    kept = advantages[alive]
    np.testing.assert_allclose(normalised, (advantages - kept.mean()) / kept.std(), rtol=1e-4,
                               atol=1e-5)
    assert float(masked_mean(jnp.ones(3), jnp.zeros(3, bool))) == 0.0


def dead_agent_batch(algorithm, n: int, per_agent: bool, key: int = 0) -> Batch:
    """A batch of 5 samples in which agent 1 is dead in every sample."""
    keys = jax.random.split(jax.random.PRNGKey(key), 8)
    obs = jax.random.normal(keys[0], (5, n, 6))
    mask = jnp.ones((5, n, 4), bool)
    params = jax.jit(algorithm.init)(keys[1], obs[0], mask[0])
    acted = jax.jit(jax.vmap(algorithm.act, in_axes=(None, 0, 0, 0)))(
        params, obs, mask, jax.random.split(keys[2], 5)
    )
    shape = (5, n) if per_agent else (5,)
    return params, Batch(
        obs=obs, action_mask=mask, actions=acted.actions,
        log_probs=acted.log_probs + 0.1 * jax.random.normal(keys[3], (5, n)),
        values=acted.value + 0.1 * jax.random.normal(keys[4], shape),
        advantages=jax.random.normal(keys[5], shape),
        targets=jax.random.normal(keys[6], shape),
        alive=jnp.ones((5, n), bool).at[:, 1].set(False),
        global_state=jnp.zeros((5, 0)),
        extras=acted.extras,
    )


def perturb_dead_agent(batch: Batch, per_agent: bool) -> Batch:
    """What only concerns dead agent 1: its old log-prob, its action mask and, per agent, its
    advantage, target and old value."""
    changed = batch._replace(
        log_probs=batch.log_probs.at[:, 1].add(3.0),
        action_mask=batch.action_mask.at[:, 1, 1:].set(False),
    )
    if per_agent:
        changed = changed._replace(
            advantages=changed.advantages.at[:, 1].add(5.0),
            targets=changed.targets.at[:, 1].add(5.0),
            values=changed.values.at[:, 1].add(5.0),
        )
    return changed


@pytest.mark.parametrize("algo", ["mat", "pmat", "mappo"])
def test_active_masks_remove_a_dead_agent_from_every_mean(algo: str) -> None:
    """Policy loss and entropy leave a dead agent out; so does the value loss with
    `ppo.value_active_masks` (MAT's per-agent values; the reference SMAC script regresses dead
    agents' values too, tested below; MAPPO's team value has no agent to leave out). PMAT's
    order term averages every agent's advantage, as its reference does (tests/test_mat.py), so
    the comparison of totals leaves that term out."""
    config = load_config(overrides=[f"algo={algo}"])
    ppo, options = config.ppo, config.options
    assert ppo.active_masks
    ppo = dataclasses.replace(ppo, value_active_masks=True)
    per_agent_gae = getattr(options, "per_agent_gae", False)
    algorithm = build_algorithm(algo, config.network, spec(), ppo, options)
    params, batch = dead_agent_batch(algorithm, 3, per_agent_gae)
    loss = jax.jit(algorithm.loss, static_argnums=2)
    base, metrics = loss(params, batch, ppo)
    changed, changed_metrics = loss(params, perturb_dead_agent(batch, per_agent_gae), ppo)
    order_loss_coef = getattr(options, "order_loss_coef", 0.0)

    def without_order_term(total: jax.Array, metrics: dict[str, jax.Array]) -> float:
        return float(total) - order_loss_coef * float(metrics.get("order_loss", 0.0))

    assert without_order_term(changed, changed_metrics) == pytest.approx(
        without_order_term(base, metrics), rel=1e-5, abs=1e-6)
    for name in ("policy_loss", "entropy", "value_loss"):
        assert float(changed_metrics[name]) == pytest.approx(float(metrics[name]), abs=1e-6)
    if per_agent_gae:
        reference = dataclasses.replace(ppo, value_active_masks=False)
        _, kept = loss(params, batch, reference)
        _, kept_changed = loss(params, perturb_dead_agent(batch, True), reference)
        assert float(kept_changed["policy_loss"]) == pytest.approx(float(kept["policy_loss"]))
        assert abs(float(kept_changed["value_loss"]) - float(kept["value_loss"])) > 1e-3
    unmasked = dataclasses.replace(ppo, active_masks=False)
    off, _ = loss(params, batch, unmasked)
    off_changed, _ = loss(params, perturb_dead_agent(batch, per_agent_gae), unmasked)
    assert abs(float(off_changed) - float(off)) > 1e-3


def test_happo_agent_loss_masks_samples_where_the_agent_is_dead() -> None:
    config = load_config(overrides=["algo=happo"])
    algorithm = build_algorithm("happo", config.network, spec(), config.ppo, config.options)
    params, batch = dead_agent_batch(algorithm, 3, per_agent=False)
    alive = batch.alive.at[:, 1].set(jnp.array([True, False, True, False, False]))
    batch = batch._replace(alive=alive)
    actor = jax.tree.map(lambda x: x[1], params["actor"])
    own = {"actor": actor, "critic": params["critic"]}
    _loss, metrics = algorithm.agent_loss(jnp.asarray(1), own, batch, config.ppo)
    distribution = algorithm.agent_distribution(actor, jnp.asarray(1), batch)
    log_ratio = np.asarray(distribution.log_prob(batch.actions[:, 1]) - batch.log_probs[:, 1])
    ratio, adv, eps = np.exp(log_ratio), np.asarray(batch.advantages), config.ppo.clip_eps
    objective = np.minimum(ratio * adv, np.clip(ratio, 1 - eps, 1 + eps) * adv)
    keep = np.asarray(alive[:, 1])
    assert float(metrics["policy_loss"]) == pytest.approx(-objective[keep].mean(), rel=1e-5)
    entropy = np.asarray(distribution.entropy())
    assert float(metrics["entropy"]) == pytest.approx(entropy[keep].mean(), rel=1e-5)


def test_smax_alive_follows_unit_deaths() -> None:
    env = make_env("smax:3m")
    state, timestep = env.reset(jax.random.PRNGKey(0))
    assert timestep.alive.tolist() == [True, True, True]
    killed = state.replace(state=state.state.replace(
        unit_health=state.state.unit_health.at[1].set(0.0),
        unit_alive=state.state.unit_alive.at[1].set(False),
    ))
    _, after = env.step(jax.random.PRNGKey(1), killed, jnp.zeros(3, jnp.int32))
    assert after.alive.tolist() == [True, False, True]


# ----------------------------------------------------------------------------- per-agent GAE
@pytest.mark.parametrize("per_agent", [True, False])
def test_mat_gae_runs_per_agent_on_each_agents_value(per_agent: bool) -> None:
    config = load_config(overrides=[
        "env=mpe:simple_spread", "algo=mat", "num_envs=2", "rollout_length=6",
        "ppo.normalize_advantages=false", "ppo.value_norm=false",
        f"mat.per_agent_gae={str(per_agent).lower()}",
    ])
    setup = build_setup(config)
    state = jax.jit(lambda key: init_state(setup, key))(jax.random.PRNGKey(0))
    learner = state.learner
    _, rollout = jax.jit(setup.collector.collect)(learner.params, state.envs, learner.rng)
    rng = np.random.default_rng(1)
    rollout = rollout._replace(steps=rollout.steps._replace(
        reward=jnp.asarray(rng.normal(size=(6, 2)), jnp.float32),
        done=jnp.asarray(rng.random((6, 2)) < 0.3),
    ))
    _, batch = jax.jit(lambda s, r: make_batch(setup.learner, s, r))(learner, rollout)
    network = setup.learner.algorithm.network
    obs = np.concatenate([np.asarray(rollout.steps.obs), np.asarray(rollout.next_obs)[None]])
    agent_values = np.asarray(jax.jit(jax.vmap(jax.vmap(
        lambda o: network.apply(learner.target_params, o, method=type(network).encode)[1]
    )))(jnp.asarray(obs)))
    values = agent_values if per_agent else agent_values.mean(-1)
    extra = (None,) if per_agent else ()
    rewards = np.asarray(rollout.steps.reward)[(..., *extra)]
    dones = np.asarray(rollout.steps.done, np.float32)[(..., *extra)]
    shape = values[:-1].shape
    expected, _ = plain_gae(np.broadcast_to(rewards, shape).copy(), values[:-1],
                            np.broadcast_to(dones, shape), values[-1], 0.99, 0.95)
    assert batch.advantages.shape == ((12, 3) if per_agent else (12,))
    np.testing.assert_allclose(batch.advantages, expected.reshape(batch.advantages.shape),
                               rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(batch.targets, (expected + values[:-1]).reshape(
        batch.targets.shape), rtol=1e-4, atol=1e-5)


# ---------------------------------------------------------------------- MAPPO's critic input
def test_mappo_critic_reads_the_smax_world_state() -> None:
    env = make_env("smax:3m")
    state, timestep = env.reset(jax.random.PRNGKey(0))
    np.testing.assert_array_equal(timestep.global_state, env.env.get_world_state(state))
    assert env.spec.state_dim == timestep.global_state.shape[0] > 0
    config = load_config(overrides=["env=smax:3m", "algo=mappo"])
    algorithm = build_algorithm("mappo", config.network, env.spec, config.ppo, config.options)
    params = jax.jit(algorithm.init)(jax.random.PRNGKey(1), timestep.obs, timestep.action_mask)
    first = params["critic"]["params"]["MLPTrunk_0"]["Dense_0"]["kernel"]
    assert first.shape[0] == env.spec.state_dim
    value = algorithm.value(params, timestep.obs, timestep.global_state)
    assert float(algorithm.value(params, timestep.obs + 1.0, timestep.global_state)) == float(value)
    moved = timestep.global_state.at[1].add(1.0)
    assert float(algorithm.value(params, timestep.obs, moved)) != float(value)
    acted = algorithm.act(params, timestep.obs, timestep.action_mask, jax.random.PRNGKey(2),
                          timestep.global_state)
    assert float(acted.value) == float(value)
    with pytest.raises(ValueError, match="global state"):
        algorithm.value(params, timestep.obs)


def test_without_a_global_state_the_critic_reads_all_observations() -> None:
    algorithm = build_algorithm("mappo", load_config().network, spec())
    obs = jax.random.normal(jax.random.PRNGKey(0), (3, 6))
    params = jax.jit(algorithm.init)(jax.random.PRNGKey(1), obs, jnp.ones((3, 4), bool))
    assert params["critic"]["params"]["MLPTrunk_0"]["Dense_0"]["kernel"].shape[0] == 18
    assert float(algorithm.value(params, obs.at[2, 0].add(1.0))) != float(
        algorithm.value(params, obs))


# ------------------------------------------------------------------------- numerical safety
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_a_joint_log_ratio_of_100_over_27_agents_stays_finite(sign: float) -> None:
    config = load_config(overrides=["network.n_embd=16", "cmat.consensus_iterations=1"])
    algorithm = build_algorithm("cmat", config.network, spec(n=27), options=config.options)
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    obs = jax.random.normal(keys[0], (4, 27, 6))
    mask = jnp.ones((4, 27, 4), bool)
    params = jax.jit(algorithm.init)(keys[1], obs[0], mask[0])
    acted = jax.jit(jax.vmap(algorithm.act, in_axes=(None, 0, 0, 0)))(
        params, obs, mask, jax.random.split(keys[2], 4))
    batch = Batch(obs, mask, acted.actions, acted.log_probs - 100.0 / 27, acted.value,
                  jnp.full(4, sign), jnp.zeros(4), alive=jnp.ones((4, 27), bool))
    log_ratio, _, _ = jax.jit(algorithm.log_ratio)(params, batch)
    np.testing.assert_allclose(log_ratio, 100.0, rtol=1e-4)
    (loss, _), grads = jax.jit(jax.value_and_grad(algorithm.loss, has_aux=True),
                               static_argnums=2)(params, batch, config.ppo)
    assert np.isfinite(float(loss))
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grads))


def test_the_log_ratio_clamp_changes_nothing_inside_its_bound() -> None:
    log_ratio = jnp.linspace(-LOG_RATIO_BOUND + 0.5, LOG_RATIO_BOUND - 0.5, 41)
    for sign in (1.0, -1.0):
        advantages = jnp.full(41, sign)

        def reference(x, advantages=advantages):
            ratio = jnp.exp(x)
            return -jnp.mean(jnp.minimum(ratio * advantages,
                                         jnp.clip(ratio, 0.8, 1.2) * advantages))

        def surrogate(x, advantages=advantages):
            return clipped_surrogate_loss(x, advantages, 0.2)[0]

        got = jax.grad(surrogate)(log_ratio)
        np.testing.assert_allclose(got, jax.grad(reference)(log_ratio), rtol=1e-6)


def fault_code(metrics: dict[str, jax.Array], params: Any, steps: Transition) -> jax.Array:
    """The `fault_code` of one update with these metrics and parameters on this rollout: the
    collector's report and the learner's check, combined as a run's chunk combines them."""
    per_update = {**rollout_report(steps), "update_fault": update_fault_code(metrics, params)}
    spec = make_env("matrix:fig1").spec
    return summarise_updates(spec, {key: value[None] for key, value in per_update.items()})[
        "fault_code"]


def test_fault_code_names_the_first_failed_check() -> None:
    good = {"loss": jnp.float32(1.0), "grad_norm": jnp.float32(1.0)}
    params = {"w": jnp.ones(3)}
    steps = Transition(**{name: jnp.zeros((4, 2)) for name in Transition._fields})
    steps = steps._replace(alive=jnp.ones((4, 2), bool), action_mask=jnp.ones((4, 2, 3), bool),
                           done=jnp.zeros((4, 2), bool), won=jnp.zeros((4, 2), bool))
    nan = jnp.zeros((4, 2)).at[3, 1].set(jnp.nan)
    closed = steps.action_mask.at[2, 1].set(False)
    assert int(fault_code(good, params, steps)) == 0
    assert int(fault_code(good, params, steps._replace(global_state=jnp.zeros((4, 0))))) == 0
    dead_and_closed = steps._replace(action_mask=closed, alive=steps.alive.at[2, 1].set(False))
    assert int(fault_code(good, params, dead_and_closed)) == 0
    names = [ROLLOUT_FAULTS[int(code) - 1].split(" (")[0] for code in (
        fault_code(good, params, steps._replace(reward=nan, obs=nan)),
        fault_code({**good, "loss": jnp.float32(jnp.nan)}, params, steps._replace(obs=nan)),
        fault_code({**good, "loss": jnp.float32(jnp.nan)}, params,
                   steps._replace(global_state=jnp.full((4, 2), jnp.inf))),
        fault_code({**good, "loss": jnp.float32(jnp.nan)}, params,
                   steps._replace(action_mask=closed)),
        fault_code({**good, "loss": jnp.float32(jnp.nan)}, params, steps),
        fault_code({**good, "grad_norm": jnp.float32(jnp.inf)}, params, steps),
        fault_code(good, {"w": jnp.array([1.0, jnp.nan, 0.0])}, steps),
    )]
    assert names == ["non-finite environment reward", "non-finite environment observation",
                     "non-finite environment global state",
                     "an action mask that allows no action to a live agent",
                     "non-finite loss", "non-finite gradient norm", "non-finite parameters"]


TINY = ["num_envs=4", "rollout_length=25", "log_interval=2", "ppo.epochs=2", "eval_episodes=4"]


def test_a_nonfinite_loss_stops_the_run_and_keeps_the_last_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    args = ["train", "--env", "matrix:fig1", "--algo", "mappo", "--steps", "200", "--set", *TINY]
    assert main([*args, "--out", str(out)]) == 0
    checkpoint = (out / "checkpoints" / "latest.ckpt").read_bytes()
    metrics = (out / "metrics.csv").read_bytes()
    capsys.readouterr()

    from cmat.algorithms.mappo import algorithm as mappo

    def poisoned(log_ratio, advantages, clip_eps, mask=None):
        loss, diagnostics = clipped_surrogate_loss(log_ratio, advantages, clip_eps, mask)
        return loss * jnp.nan, diagnostics

    monkeypatch.setattr(mappo, "clipped_surrogate_loss", poisoned)
    assert main(["train", "--resume", str(out), "--steps", "400"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "non-finite loss at update 3 (seed 0)" in line
    assert (out / "checkpoints" / "latest.ckpt").read_bytes() == checkpoint
    assert (out / "metrics.csv").read_bytes() == metrics
    monkeypatch.undo()
    assert main(["train", "--resume", str(out), "--steps", "400"]) == 0
    assert RunDir(out).load_checkpoint()[1] == 400


def test_nan_metrics_are_written_as_nan(tmp_path: Path) -> None:
    run = RunDir.create(tmp_path / "run", load_config())
    run.append_metrics([{"kind": "eval", "seed": 0, "env_steps": 10, "episode_return": 1.0,
                         "win_rate": float("nan")}])
    assert run.metrics_path.read_text().splitlines()[1].split(",")[:5] == [
        "eval", "0", "10", "1.0", "nan"]


# ----------------------------------------------------------------------------------- budgets
def test_a_budget_log_interval_does_not_divide_is_trained_exactly(tmp_path: Path) -> None:
    """1,050 steps at 100 per update: 11 whole updates (1,100 steps), in chunks 4, 4, 3."""
    out = tmp_path / "run"
    args = ["train", "--env", "matrix:fig1", "--algo", "mappo", "--steps", "1050", "--set",
            "num_envs=4", "rollout_length=25", "log_interval=4", "ppo.epochs=1",
            "eval_episodes=2"]
    assert main([*args, "--out", str(out)]) == 0
    run = RunDir(out)
    assert run.load_checkpoint()[1] == 1100 == run.config().budget_steps
    evals = [int(r["env_steps"]) for r in run.read_metrics() if r["kind"] == "eval"]
    assert evals == [400, 800, 1100]
    assert main(["train", "--resume", str(out), "--steps", "1250"]) == 0
    assert run.load_checkpoint()[1] == 1300
    assert [int(r["env_steps"]) for r in run.read_metrics() if r["kind"] == "eval"] == [
        400, 800, 1100, 1300]


def test_the_experiment_runner_reports_such_a_run_complete(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = {
        "name": "budget", "steps": 1050, "seeds": 1,
        "set": {"num_envs": 4, "rollout_length": 25, "log_interval": 4, "eval_episodes": 2,
                "ppo": {"epochs": 1}},
        "envs": [{"id": "matrix:fig1"}], "algos": ["mappo"],
    }
    path = tmp_path / "budget.yaml"
    path.write_text(yaml.safe_dump(spec))
    out = tmp_path / "out"
    assert main(["experiment", str(path), "--out", str(out)]) == 0
    run = RunDir(out / "runs" / "matrix_fig1" / "default" / "mappo-s0")
    assert run.load_checkpoint()[1] == 1100
    capsys.readouterr()
    assert main(["experiment", str(path), "--out", str(out), "--dry-run"]) == 0
    assert "1 complete" in capsys.readouterr().out


def test_eval_reports_the_budget(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    args = ["train", "--env", "matrix:fig1", "--algo", "mappo", "--steps", "150", "--set", *TINY]
    assert main([*args, "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["eval", "--run", str(out), "--episodes", "2"]) == 0
    result = yaml.safe_load(capsys.readouterr().out)
    assert (result["env_steps"], result["budget_steps"], result["complete"]) == (200, 200, True)


# ----------------------------------------------------------------------------- range checks
@pytest.mark.parametrize("override", [
    "ppo.max_grad_norm=0", "ppo.max_grad_norm=-1", "ppo.clip_eps=0", "ppo.adam_eps=-1",
    "ppo.huber_delta=0", "ppo.clip_eps=1.5", "ppo.ent_coef=-0.1", "ppo.value_coef=-1",
    "ppo.lr=nan", "ppo.gamma=inf", "network.init_gain=0", "cmat.consensus_ent_coef=-1",
    "ppo.clip_eps=1.0", "cmat.latent_head_gain=0", "cmat.attention_block=-1",
])
def test_out_of_range_numbers_are_one_error_line(
    override: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    code = main(["train", "--env", "matrix:fig1", "--set", override, "--out", str(out)])
    assert code == 2
    line = one_error_line(capsys.readouterr().err)
    assert override.split("=")[0] in line
    assert not out.exists()


@pytest.mark.parametrize("algo", ["cmat", "mappo", "sable"])
def test_one_sample_per_update_is_an_error_not_a_run_that_never_learns(
    algo: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Advantages normalised over one sample are all 0: such a run would never move."""
    out = tmp_path / "run"
    assert main(["train", "--env", "matrix:fig1", "--algo", algo, "--set", "num_envs=1",
                 "rollout_length=1", "ppo.num_minibatches=1", "--out", str(out)]) == 2
    assert "num_envs * rollout_length must be at least 2, got 1" in one_error_line(
        capsys.readouterr().err)
    assert not out.exists()


def test_per_agent_gae_is_for_per_agent_values_only() -> None:
    from cmat.errors import CmatError

    with pytest.raises(CmatError, match=r"unknown key cmat\.per_agent_gae"):
        load_config(overrides=["algo=cmat", "cmat.per_agent_gae=true"])
    with pytest.raises(CmatError, match=r"unknown key ppo\.per_agent_gae"):
        load_config(overrides=["algo=mat", "ppo.per_agent_gae=true"])


def test_a_checkpoint_missing_a_state_field_names_it() -> None:
    """A checkpoint without one of the environments' fields (here `timestep/alive`) is refused
    with one line naming the field, not restored with a guessed value."""
    import flax.serialization

    config = load_config(overrides=["env=smax:3m", "algo=mappo", "num_envs=2", *TINY[1:]])
    trainer = JaxTrainer(config)
    state = trainer.init()
    assert state.envs is not None
    raw = {**flax.serialization.to_state_dict(state.learner),
           **flax.serialization.to_state_dict(state.envs)}  # the checkpoint format
    assert trainer.from_bytes(flax.serialization.msgpack_serialize(raw)) is not None
    del raw["timestep"]["alive"]
    from cmat.errors import CmatError

    with pytest.raises(CmatError, match=r"state/timestep/alive is not in the checkpoint"):
        trainer.from_bytes(flax.serialization.msgpack_serialize(raw))


def test_ppo_config_defaults_are_the_papers() -> None:
    ppo = PPOConfig()
    assert (ppo.target_tau, ppo.active_masks) == (0.1, False)


# --------------------------------------------------------------------------- host environments
class StatefulRelay:
    """A ParallelEnv whose "b" leaves after the first step and whose `state()` is [t, 10 + t]."""

    metadata: ClassVar[dict[str, Any]] = {"name": "stateful_relay"}

    def __init__(self) -> None:
        self.possible_agents = ["a", "b"]
        self.agents: list[str] = []
        self._t = 0

    def observation_space(self, agent: str):
        import gymnasium.spaces as spaces

        return spaces.Box(-1.0, 1.0, (2,), np.float32)

    def action_space(self, agent: str):
        import gymnasium.spaces as spaces

        return spaces.Discrete(2)

    def state(self) -> np.ndarray:
        return np.array([self._t, 10 + self._t], np.float32)

    def reset(self, seed=None, options=None):
        self.agents, self._t = ["a", "b"], 0
        return {agent: np.zeros(2, np.float32) for agent in self.agents}, {}

    def step(self, actions):
        self._t += 1
        ended = {"a": self._t >= 3, "b": True}
        obs = {agent: np.full(2, 0.1 * self._t, np.float32) for agent in self.agents}
        rewards = {agent: 1.0 for agent in self.agents}
        self.agents = [agent for agent in self.agents if not ended[agent]]
        return obs, rewards, ended, {"a": False, "b": False}, {}


def stateful_relay() -> StatefulRelay:
    return StatefulRelay()


def test_host_envs_report_active_agents_and_their_global_state() -> None:
    from cmat.envs.host import make_host_env

    env = make_host_env(f"pettingzoo:{__name__}:stateful_relay")
    assert env.spec.state_dim == 2
    first = env.reset(seed=0)
    np.testing.assert_array_equal(first.global_state, [0, 10])
    assert first.alive.tolist() == [True, True]
    steps = [env.step(np.array([0, 0])) for _ in range(3)]
    assert [s.alive.tolist() for s in steps] == [[True, False], [True, False], [True, True]]
    np.testing.assert_array_equal(steps[0].global_state, [1, 11])
    np.testing.assert_array_equal(steps[2].global_state, [0, 10])  # the next episode's first
    algorithm = build_algorithm("mappo", load_config().network, env.spec)
    params = jax.jit(algorithm.init)(jax.random.PRNGKey(0), jnp.asarray(first.obs),
                            jnp.asarray(first.action_mask))
    assert params["critic"]["params"]["MLPTrunk_0"]["Dense_0"]["kernel"].shape[0] == 2
