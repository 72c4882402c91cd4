"""`cmat.load_policy`: a trained run's policy in a user's own loop acts exactly as `cmat eval`,
and the PettingZoo loop of docs/policies.md reaches the optimum of a game the run learned."""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_host_envs import SignalGame

import cmat
from cmat import rundir
from cmat.cli import build_trainer, main
from cmat.errors import CmatError
from cmat.policy import Policy, bundle_digest
from cmat.resolve import load_config
from cmat.rundir import RunDir
from cmat.runners.base import eval_keys
from cmat.runners.trainer import JaxTrainer

pytestmark = pytest.mark.quick_compiles

SMAX_RUN = ["train", "--env", "smax:3m", "--steps", "128", "--seeds", "2", "--set",
            "num_envs=4", "rollout_length=16", "ppo.epochs=1", "eval_episodes=4", "seed=5"]


@pytest.fixture(scope="module")
def smax_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("policy") / "smax"
    assert main([*SMAX_RUN, "--out", str(out)]) == 0
    return out


def test_a_users_greedy_loop_scores_what_cmat_eval_scores(smax_run: Path) -> None:
    """Episodes stepped by hand with `policy.greedy` (batch of teams), replaying the keys of
    the trainer's evaluation, end with the returns `cmat eval` reports for that seed."""
    policy = cmat.load_policy(smax_run, seed=6)
    assert (policy.seed, policy.env_steps, policy.complete) == (6, 128, True)
    config = RunDir.open(smax_run).config()
    trainer = build_trainer(config)
    state = trainer.from_bytes(RunDir.open(smax_run).load_checkpoint()[0])
    episodes = 4
    expected = trainer.evaluate(state, episodes)["episode_return"][1]

    env = policy.make_env()
    rng = eval_keys(config, 0)[1]
    reset_key, rng = jax.random.split(rng)
    env_state, step = jax.vmap(env.reset)(jax.random.split(reset_key, episodes))
    returns, finished = np.zeros(episodes), np.zeros(episodes, bool)
    step_teams = jax.jit(jax.vmap(env.step))
    for key in jax.random.split(rng, policy.spec.max_episode_steps):
        actions = policy.greedy(step.obs, step.action_mask)
        assert actions.shape == (episodes, 3)
        assert np.asarray(step.action_mask)[np.arange(episodes)[:, None], np.arange(3),
                                            np.asarray(actions)].all()
        env_state, step = step_teams(jax.random.split(key, episodes), env_state, actions)
        returns += np.where(finished, 0.0, np.asarray(step.reward))
        finished |= np.asarray(step.done)
    np.testing.assert_allclose(returns.mean(), expected, rtol=1e-5)


def test_one_team_or_a_batch_and_sampling(smax_run: Path) -> None:
    policy = cmat.load_policy(smax_run)
    assert policy.seed == 5
    env = policy.make_env()
    _, steps = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(1), 3))
    batch = np.asarray(policy.greedy(steps.obs, steps.action_mask))
    for index in range(3):
        team = policy.greedy(steps.obs[index], steps.action_mask[index])
        assert team.shape == (3,) and np.array_equal(team, batch[index])
    sampled = policy.act(steps.obs, steps.action_mask, jax.random.PRNGKey(2))
    again = policy.act(steps.obs, steps.action_mask, jax.random.PRNGKey(2))
    assert sampled.shape == (3, 3) and np.array_equal(sampled, again)
    mask = np.asarray(steps.action_mask)
    assert mask[np.arange(3)[:, None], np.arange(3), np.asarray(sampled)].all()
    only_stop = jnp.zeros_like(steps.action_mask).at[..., 1].set(True)
    assert np.all(np.asarray(policy.act(steps.obs, only_stop)) == 1)
    assert np.array_equal(policy.act(steps.obs, only_stop, jax.random.key(3)),
                          policy.act(steps.obs, only_stop, jax.random.PRNGKey(3)))
    for bad_key in (0, np.zeros(2, np.uint32), jnp.zeros(3, jnp.uint32)):
        with pytest.raises(CmatError, match="key must be a jax PRNG key"):
            policy.act(steps.obs, only_stop, bad_key)
    other_seed = cmat.load_policy(smax_run, seed=6)
    assert not all(np.array_equal(a, b) for a, b in zip(
        jax.tree.leaves(policy.params), jax.tree.leaves(other_seed.params), strict=True))


@pytest.mark.parametrize("obs_shape, mask_shape, message", [
    ((3, 5), None, "obs must have shape (3, 75) or (batch, *(3, 75))"),
    ((2, 4, 75), None, "obs must have shape (3, 75)"),
    ((75,), None, "got (75,)"),
    ((3, 75), (3, 9), "action_mask must have shape (3, 8)"),
    ((2, 3, 75), (3, 8), "action_mask must have shape (2, 3, 8)"),
])
def test_inputs_of_the_wrong_shape_are_one_error(
    smax_run: Path, obs_shape: tuple, mask_shape: tuple | None, message: str
) -> None:
    policy = cmat.load_policy(smax_run)
    mask = None if mask_shape is None else np.ones(mask_shape, bool)
    with pytest.raises(CmatError, match=re.escape(message)):
        policy.greedy(np.zeros(obs_shape), mask)


def test_inputs_no_team_could_give_are_one_error(smax_run: Path) -> None:
    policy = cmat.load_policy(smax_run)
    obs, mask = np.zeros((2, 3, 75)), np.ones((2, 3, 8), bool)
    obs[1, 2, 40] = np.nan
    for act in (policy.greedy, policy.act):
        with pytest.raises(CmatError, match=re.escape("infinite value (team member (1, 2))")):
            act(obs, mask)
    obs[1, 2, 40] = 0.0
    mask[0, 1] = False
    for act in (policy.greedy, policy.act):
        with pytest.raises(CmatError, match=re.escape("allows no action for team member (0, 1)")):
            act(obs, mask)
    mask[0, 1, 0] = True
    assert np.asarray(policy.greedy(obs, mask))[0, 1] == 0


def test_runs_that_cannot_be_loaded_are_one_error(smax_run: Path, tmp_path: Path) -> None:
    with pytest.raises(CmatError, match=r"trained seeds 5..6; there is no seed 7"):
        cmat.load_policy(smax_run, seed=7)
    with pytest.raises(CmatError, match="holds no run"):
        cmat.load_policy(tmp_path)
    with pytest.raises(cmat.CmatError, match="is a file; give the run's directory"):
        cmat.load_policy(smax_run / "config.yaml")
    for bad_seed in ("5", 5.0, True):
        with pytest.raises(CmatError, match="seed must be an int"):
            cmat.load_policy(smax_run, seed=bad_seed)  # type: ignore[arg-type]
    with pytest.raises(CmatError, match="run_dir must be a path, got int"):
        cmat.load_policy(123)  # type: ignore[arg-type]
    partial = tmp_path / "partial"
    partial.mkdir()
    (partial / "config.yaml").write_bytes((smax_run / "config.yaml").read_bytes())
    with pytest.raises(CmatError, match="no checkpoint in"):
        cmat.load_policy(partial)
    newer = tmp_path / "newer"
    newer.mkdir()
    text = (smax_run / "config.yaml").read_text().splitlines()
    newer_text = ["# written by cmat 9.0.0", *text[1:], "world_model: true"]
    (newer / "config.yaml").write_text("\n".join(newer_text) + "\n")
    with pytest.raises(CmatError, match=r"world_model.*written by cmat 9\.0\.0; this is cmat"):
        cmat.load_policy(newer)
    other = tmp_path / "other"
    other.mkdir()
    (other / "config.yaml").write_text("\n".join(
        ["# written by cmat 0.0.1",
         *(line.replace("n_embd: 64", "n_embd: 32") for line in text[1:])]
    ) + "\n")
    (other / "checkpoints").mkdir()
    (other / "checkpoints" / "latest.ckpt").write_bytes(
        (smax_run / "checkpoints" / "latest.ckpt").read_bytes())
    with pytest.raises(CmatError, match=r"shapes differ.*written by cmat 0\.0\.1"):
        cmat.load_policy(other)


def test_an_exported_policy_acts_as_the_runs_and_carries_one_seed(
    smax_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "shipped"
    assert main(["export", "--run", str(smax_run), "--seed", "6", "--checkpoint", "best",
                 "--out", str(out)]) == 0
    assert f"wrote {out}: cmat on smax:3m, seed 6" in capsys.readouterr().out
    original = cmat.load_policy(smax_run, seed=6, checkpoint="best")
    shipped = cmat.load_policy(out)
    assert (shipped.seed, shipped.env_steps, shipped.spec) == (
        original.seed, original.env_steps, original.spec)
    assert shipped.config == original.config
    obs = jax.random.normal(jax.random.PRNGKey(3), (8, 3, original.spec.obs_dim))
    mask = jax.random.bernoulli(jax.random.PRNGKey(4), 0.7, (8, 3, original.spec.action_dim))
    mask = mask.at[..., 0].set(True)
    key = jax.random.PRNGKey(9)
    np.testing.assert_array_equal(shipped.greedy(obs, mask), original.greedy(obs, mask))
    np.testing.assert_array_equal(shipped.act(obs, mask, key), original.act(obs, mask, key))
    np.testing.assert_array_equal(shipped.log_probs(obs, mask), original.log_probs(obs, mask))
    one_seed = (out / "policy.msgpack").stat().st_size
    checkpoint = (smax_run / "checkpoints" / "best.ckpt").stat().st_size
    assert one_seed < checkpoint / 4  # two seeds' parameters, Adam moments and target critic
    assert cmat.load_policy(out, seed=6).seed == 6
    assert main(["export", "--run", str(smax_run), "--out", str(out)]) == 2
    assert "already exists; a policy is saved to a new directory" in capsys.readouterr().err

    def evaluated(*args: str) -> dict:
        assert main(["eval", "--episodes", "4", "--seed", "2", *args]) == 0
        return json.loads(capsys.readouterr().out)

    run_rows = evaluated("--run", str(smax_run), "--checkpoint", "best")["per_seed"]
    shipped_eval = evaluated("--run", str(out))
    assert shipped_eval["checkpoint"] == "saved policy"
    assert shipped_eval["env_steps"] == original.env_steps
    assert shipped_eval["per_seed"] == [row for row in run_rows if row["seed"] == 6]
    assert main(["eval", "--run", str(out), "--checkpoint", "best"]) == 2
    assert "is a saved policy, one checkpoint" in capsys.readouterr().err
    assert main(["render", "--run", str(out), "--max-steps", "3",
                 "--out", str(tmp_path / "shipped.gif")]) == 0
    assert "(3 frames, seed 6)" in capsys.readouterr().out


def resign(path: Path) -> None:
    """Record the digest of `path`'s three files as they now are: a forgery, which the
    digest cannot catch, so the loader's own checks must."""
    header = json.loads((path / "policy.json").read_text())
    header["sha256"] = bundle_digest(header, (path / "config.yaml").read_bytes(),
                                     (path / "policy.msgpack").read_bytes())
    (path / "policy.json").write_text(json.dumps(header))


def test_a_saved_policy_that_cannot_be_loaded_is_one_error(
    smax_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    good = cmat.load_policy(smax_run, seed=5).save(tmp_path / "good")
    mask = os.umask(0)
    os.umask(mask)
    assert {file.stat().st_mode & 0o777 for file in good.iterdir()} == {0o666 & ~mask}

    def broken(edit: Callable[[Path], object], forged: bool = False) -> Path:
        copy = tmp_path / f"broken{len(list(tmp_path.iterdir()))}"
        shutil.copytree(good, copy)
        edit(copy)
        if forged:
            resign(copy)
        return copy

    def header_edit(**fields: object) -> Callable[[Path], object]:
        def edit(path: Path) -> None:
            header = json.loads((path / "policy.json").read_text())
            for name, value in fields.items():
                section, _, key = name.partition("__")
                if key:
                    if value is None:
                        del header[section][key]
                    else:
                        header[section][key] = value
                else:
                    header[name] = value
            (path / "policy.json").write_text(json.dumps(header))
        return edit

    def params_edit(change: Callable[[np.ndarray], np.ndarray]) -> Callable[[Path], object]:
        def edit(path: Path) -> None:
            restored = flax.serialization.msgpack_restore((path / "policy.msgpack").read_bytes())
            changed = jax.tree.map(lambda leaf: change(np.asarray(leaf)), restored)
            (path / "policy.msgpack").write_bytes(flax.serialization.msgpack_serialize(changed))
        return edit

    def flip_a_byte(path: Path) -> None:
        data = bytearray((path / "policy.msgpack").read_bytes())
        data[len(data) // 2] ^= 1
        (path / "policy.msgpack").write_bytes(bytes(data))

    def edit_config(old: str, new: str) -> Callable[[Path], object]:
        return lambda path: (path / "config.yaml").write_text(
            (path / "config.yaml").read_text().replace(old, new))

    not_saved_together = "are not the files saved together"
    cases: list[tuple[Path, str]] = [
        (broken(flip_a_byte), not_saved_together),
        (broken(edit_config("n_embd: 64", "n_embd: 32")), not_saved_together),
        (broken(header_edit(seed=6)), not_saved_together),
        (broken(lambda p: (p / "policy.json").write_text("{")), "corrupt saved policy header"),
        (broken(lambda p: (p / "policy.json").write_text("[1, 2]")),
         "corrupt saved policy header"),
        (broken(lambda p: ((p / "policy.json").unlink(), (p / "policy.json").mkdir())),
         "corrupt saved policy header"),
        (broken(header_edit(format="cmat-policy 0")),
         "format 'cmat-policy 0' is not 'cmat-policy 1'"),
        (broken(lambda p: (p / "policy.msgpack").unlink()), r"cannot read .*policy\.msgpack"),
        (broken(lambda p: (p / "config.yaml").unlink()), r"cannot read .*config\.yaml"),
        (broken(header_edit(seed="5"), forged=True), "seed must be an integer, got '5'"),
        (broken(header_edit(env_steps=-1), forged=True), "env_steps must be an integer >= 0"),
        (broken(header_edit(spec__obs_dim=None), forged=True),
         "spec must hold exactly the fields of an EnvSpec"),
        (broken(header_edit(spec__num_agents=0), forged=True),
         "spec.num_agents must be an integer >= 1, got 0"),
        (broken(header_edit(spec__num_agents=2.0), forged=True),
         "spec.num_agents must be an integer >= 1, got 2.0"),
        (broken(header_edit(spec__discrete="no"), forged=True),
         "spec.discrete must be bool, got 'no'"),
        (broken(header_edit(algo="mappo"), forged=True),
         "config.yaml is a cmat run on smax:3m, and .*policy.json a mappo policy on smax:3m"),
        (broken(lambda p: (p / "policy.msgpack").write_bytes(b"\x93\x01\x02\x03"),
                forged=True), r"policy\.msgpack does not fit the cmat network of"),
        (broken(params_edit(lambda leaf: leaf.astype(np.int32)), forged=True),
         r"policy\.msgpack does not fit the cmat network of"),
        (broken(params_edit(lambda leaf: leaf[..., :1]), forged=True),
         r"policy\.msgpack does not fit the cmat network of"),
        (broken(params_edit(lambda leaf: np.full_like(leaf, np.nan)), forged=True),
         "holds NaN or infinite parameters"),
    ]
    for path, message in cases:
        with pytest.raises(CmatError, match=message):
            cmat.load_policy(path)

    other_env = broken(lambda p: (header_edit(env="smax:2s3z")(p),
                                  edit_config("env: smax:3m", "env: smax:2s3z")(p)), forged=True)
    assert cmat.load_policy(other_env).spec.num_agents == 3
    assert main(["eval", "--run", str(other_env), "--episodes", "1"]) == 2
    assert ("config.yaml builds an environment with env_id 'smax:2s3z', and the saved "
            "parameters act on env_id 'smax:3m'") in capsys.readouterr().err

    with pytest.raises(CmatError, match="saved policy of seed 5; there is no seed 6"):
        cmat.load_policy(good, seed=6)
    with pytest.raises(CmatError, match="checkpoint 'best' is the run directory's choice"):
        cmat.load_policy(good, checkpoint="best")
    for checkpoint in (None, 400.0, True, [1], -3):
        with pytest.raises(CmatError, match="checkpoint must be 'latest', 'best' or the env"):
            cmat.load_policy(smax_run, checkpoint=checkpoint)  # type: ignore[arg-type]
    assert main(["eval", "--run", str(smax_run), "--checkpoint", "\u0664\u0660\u0660"]) == 2
    assert "--checkpoint must be latest, best or the env steps" in capsys.readouterr().err

    for argv in (["train", "--resume", str(good)], ["train", "--resume", str(good), "--dry-run"],
                 ["finetune", "--from", str(good), "--mode", "action"]):
        assert main(argv) == 2, argv
        assert "is a policy saved by cmat export (one seed's parameters, no checkpoint)" in (
            capsys.readouterr().err)

    policy = cmat.load_policy(good)
    with pytest.raises(CmatError, match="already exists; a policy is saved to a new directory"):
        policy.save(good)
    with pytest.raises(CmatError, match="path must be a path, got int"):
        policy.save(5)  # type: ignore[arg-type]

    def no_space(path: Path, data: bytes) -> None:
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(rundir, "atomic_write", no_space)
    with pytest.raises(CmatError, match=r"cannot write .*policy\.msgpack: No space left"):
        policy.save(tmp_path / "new" / "deeper" / "policy")
    assert not (tmp_path / "new").exists()


SIGNAL = "pettingzoo:test_host_envs:signal_game"


def readme_loop_scores(out: Path, episodes: int) -> list[float]:
    """The PettingZoo loop of docs/policies.md with the policy loaded from run `out`: one score per
    episode, each checked to end within the game's length with actions the masks allow."""
    policy = cmat.load_policy(out)
    env = policy.make_env()
    scores = []
    for episode in range(episodes):
        step, score = env.reset(seed=episode), 0.0
        for _ in range(SignalGame.LENGTH):
            actions = np.asarray(policy.greedy(step.obs, step.action_mask))
            assert np.asarray(step.action_mask)[np.arange(2), actions].all()
            step = env.step(actions)
            score += step.reward
            if step.done:
                break
        assert step.done
        scores.append(score)
    env.close()
    return scores


def test_the_documented_pettingzoo_loop_plays_a_loaded_policy(tmp_path: Path) -> None:
    """One update, then the loop of docs/policies.md: episodes of the host environment end,
    scored."""
    out = tmp_path / "signal"
    assert main(["train", "--env", SIGNAL, "--steps", "64", "--out", str(out), "--set",
                 "num_envs=16", "rollout_length=4", "ppo.epochs=1", "network.n_embd=16",
                 "eval_episodes=2"]) == 0
    assert all(0 <= score <= SignalGame.LENGTH for score in readme_loop_scores(out, 2))


@pytest.mark.slow
def test_the_documented_pettingzoo_loop_reaches_the_optimum(tmp_path: Path) -> None:
    """The signal game's settings measured in tests/test_host_envs.py (2,400 steps reach the
    optimum return 5); the loop of docs/policies.md with the loaded policy scores 5 in every
    episode."""
    out = tmp_path / "signal"
    assert main(["train", "--env", SIGNAL, "--steps", "2400", "--out", str(out), "--set",
                 "num_envs=16", "rollout_length=25", "ppo.epochs=8", "network.n_embd=32",
                 "ppo.clip_eps=0.2", "eval_episodes=16", "log_interval=6"]) == 0
    assert readme_loop_scores(out, 5) == [SignalGame.LENGTH] * 5


def test_render_draws_the_episode_the_policy_plays(smax_run: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """The GIF holds one frame per step of the greedy episode plus its first, and its
    pictures change as the units move."""
    from PIL import Image

    out = tmp_path / "episode.gif"
    assert main(["render", "--run", str(smax_run), "--seed", "6", "--out", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out

    policy = cmat.load_policy(smax_run, seed=6)
    env = policy.make_env()
    key = jax.random.PRNGKey(6)
    key, reset_key = jax.random.split(key)
    state, step = env.reset(reset_key)
    steps = 0
    while not bool(step.done):
        key, step_key = jax.random.split(key)
        state, step = env.step_in_episode(step_key, state, policy.greedy(step.obs,
                                                                         step.action_mask))
        steps += 1
    with Image.open(out) as gif:
        assert gif.n_frames == steps + 1
        pictures = []
        for index in (0, gif.n_frames - 1):
            gif.seek(index)
            pictures.append(np.asarray(gif.convert("RGB")))
    assert pictures[0].shape[2] == 3 and not np.array_equal(*pictures)


@pytest.mark.parametrize("env, args, message", [
    ("matrix:fig1", [], "matrix:fig1 has no renderer; cmat render draws smax, mpe"),
    ("smax:3m", ["--out", "x.avi"], "--out must end in .gif or .mp4, got 'x.avi'"),
    ("smax:3m", ["--episodes", "0"], "--episodes and --fps must be > 0"),
])
def test_render_requests_it_cannot_serve_are_one_error(
    smax_run: Path, tmp_path: Path, env: str, args: list[str], message: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(
        (smax_run / "config.yaml").read_text().replace("env: smax:3m", f"env: {env}"))
    out = [] if "--out" in args else ["--out", str(tmp_path / "a.gif")]
    assert main(["render", "--run", str(run), *out, *args]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and message in error[0], error
    assert not (tmp_path / "a.gif").exists()


def test_a_recurrent_policys_loop_with_memory_scores_what_evaluation_scores() -> None:
    """Recurrent Sable (untrained, so cheap) on MPE: a hand loop through `greedy_with_memory`, the
    state carried from step to step and reset where an episode starts, replays the trainer's
    greedy evaluation of seed 6 exactly; the stateless `greedy` and `act` refuse it."""
    config = load_config(overrides=[
        "env=mpe:simple_spread", "env_kwargs.max_steps=6", "algo=sable",
        "network.n_embd=16", "num_envs=4", "rollout_length=16",
        "seeds=2", "seed=5", "ppo.num_minibatches=2",
    ])
    trainer = JaxTrainer(config)
    state = trainer.init()
    episodes = 4
    expected = trainer.evaluate(state, episodes)["episode_return"][1]
    params = jax.tree.map(lambda x: x[1], state.learner.params)
    policy = Policy(trainer.env_spec, config, 6, 0, trainer.learner_setup.algorithm, params)
    assert policy.recurrent
    env = policy.make_env()
    rng = eval_keys(config, 0)[1]
    reset_key, rng = jax.random.split(rng)
    env_state, step = jax.vmap(env.reset)(jax.random.split(reset_key, episodes))
    for method in (policy.greedy, policy.act):
        with pytest.raises(CmatError, match=r"recurrent: .*greedy_with_memory"):
            method(step.obs, step.action_mask)
    memory = policy.initial_memory(episodes)
    returns, finished = np.zeros(episodes), np.zeros(episodes, bool)
    env_step = jax.jit(jax.vmap(env.step))
    for key in jax.random.split(rng, policy.spec.max_episode_steps):
        actions, memory = policy.greedy_with_memory(memory, step.obs, step.action_mask,
                                                    step.done)
        env_state, step = env_step(jax.random.split(key, episodes), env_state, actions)
        returns += np.where(finished, 0.0, np.asarray(step.reward))
        finished |= np.asarray(step.done)
    assert not np.allclose(jax.tree.leaves(memory)[0], 0.0)
    np.testing.assert_allclose(returns.mean(), expected, rtol=1e-5)
