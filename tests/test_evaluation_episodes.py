"""Every evaluation of a run plays its own episodes: the evaluation at env step t plays the
episodes of `episode_seed = t` (`cmat.runners.loop`), `cmat eval --seed S` plays those of S, the
same seed replays them exactly and another draws others."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from types import SimpleNamespace
from typing import cast

import jax
import numpy as np
import pytest

import cmat
from cmat.cli import main
from cmat.envs.dispatch.env import METRICS as DISPATCH_METRICS
from cmat.envs.dispatch.matched import matched_plan
from cmat.experiments.markdown import old_protocol_text
from cmat.experiments.plan import Run
from cmat.experiments.report import eval_protocol
from cmat.rundir import EVAL_PROTOCOL, RunDir
from cmat.runners import build_trainer

pytestmark = pytest.mark.quick_compiles

METRICS = ("episode_return", "service_rate", "revenue", "expired", "conflicts_per_step")


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A dispatch run (orders arrive at random: two sets of episodes differ in revenue almost
    surely) with three evaluations."""
    out = tmp_path_factory.mktemp("fresh") / "run"
    assert main(["train", "--env", "dispatch:grid-8-high", "--algo", "mappo", "--steps", "360",
                 "--set", "env_kwargs.grid_size=3", "env_kwargs.episode_minutes=20",
                 "num_envs=2", "rollout_length=30", "log_interval=2", "eval_episodes=3",
                 "--out", str(out)]) == 0
    return out


def eval_rows(run: Path) -> list[dict[str, str]]:
    return [r for r in csv.DictReader((run / "metrics.csv").open()) if r["kind"] == "eval"]


def test_each_training_evaluation_plays_the_episodes_of_its_step(run: Path) -> None:
    rows = eval_rows(run)
    assert [int(r["env_steps"]) for r in rows] == [120, 240, 360]
    config = RunDir.open(run).config()
    trainer = build_trainer(config)
    state = trainer.from_bytes(RunDir.open(run).load_checkpoint()[0])
    last = trainer.evaluate(state, 3, episode_seed=360)
    for name in METRICS:
        assert float(rows[-1][name]) == pytest.approx(float(last[name][0]), rel=1e-6), name
    again = trainer.evaluate(state, 3, episode_seed=360)
    other = trainer.evaluate(state, 3, episode_seed=240)
    assert all(np.array_equal(last[name], again[name]) for name in METRICS)
    assert not np.array_equal(last["revenue"], other["revenue"])


def test_cmat_eval_seed_picks_the_episodes(run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def evaluated(*argv: str) -> dict[str, float]:
        capsys.readouterr()
        assert main(["eval", "--run", str(run), *argv]) == 0
        result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        return dict(result["per_seed"][0], episode_seed=result["episode_seed"])

    last = eval_rows(run)[-1]
    replayed = evaluated("--seed", "360")
    assert replayed["episode_seed"] == 360
    assert replayed["revenue"] == pytest.approx(float(last["revenue"]), rel=1e-6)
    fresh = evaluated()
    assert fresh["episode_seed"] == 0 and fresh["revenue"] != replayed["revenue"]
    assert main(["eval", "--run", str(run), "--seed", "-1"]) == 2
    assert "--seed must be in [0," in capsys.readouterr().err.splitlines()[-1]


def test_matched_decoding_never_conflicts_and_replays_its_episodes(
        run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def evaluated(*argv: str) -> dict[str, object]:
        capsys.readouterr()
        assert main(["eval", "--run", str(run), "--actions", "matched", *argv]) == 0
        return cast(dict[str, object], json.loads(capsys.readouterr().out.splitlines()[-1]))

    first = evaluated("--seed", "5", "--episodes", "2")
    assert first["actions"] == "matched" and first["episode_seed"] == 5
    row = cast(list[dict[str, float]], first["per_seed"])[0]
    assert row["conflicts_per_step"] == 0 and 0 < row["service_rate"] <= 1
    assert evaluated("--seed", "5", "--episodes", "2") == first
    shipped = run.parent / "shipped"
    assert main(["export", "--run", str(run), "--out", str(shipped)]) == 0
    capsys.readouterr()
    assert main(["eval", "--run", str(shipped), "--actions", "matched", "--seed", "5",
                 "--episodes", "2"]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[-1])["per_seed"] == first["per_seed"]
    assert main(["eval", "--run", str(run), "--actions", "matched", "--episodes",
                 "100001"]) == 2
    assert "--episodes must be in [1, 100,000]" in capsys.readouterr().err.splitlines()[-1]


def test_the_documented_dispatch_loops_play_whole_episodes_and_matching_never_conflicts(
        run: Path) -> None:
    """The dispatch loops of docs/policies.md with the policy of `run`: sampled with a new key
    each minute, and matched on the state's candidates. Both take legal actions only and end
    after the task's 20 minutes; the matched episode makes no conflicting claim."""
    policy = cmat.load_policy(run, seed=0)
    env = policy.make_env()
    for matched in (False, True):
        key = jax.random.key(0)
        state, step = env.reset(key)
        minutes = 0
        while not bool(step.done):
            key, act_key, step_key = jax.random.split(key, 3)
            if matched:
                actions = matched_plan(np.asarray(policy.log_probs(step.obs, step.action_mask)),
                                       np.asarray(step.action_mask), np.asarray(state.candidates))
            else:
                actions = np.asarray(policy.act(step.obs, step.action_mask, act_key))
            assert np.asarray(step.action_mask)[np.arange(len(actions)), actions].all()
            state, step = env.step(step_key, state, jax.numpy.asarray(actions))
            minutes += 1
        assert minutes == 20
        if matched:
            assert float(step.metrics[DISPATCH_METRICS.index("conflicts_per_step")]) == 0


def test_reports_name_the_runs_evaluated_under_the_old_protocol(run: Path, tmp_path: Path) -> None:
    """A run records its evaluation protocol in sessions.jsonl; a results page names the runs
    whose sessions predate it (every evaluation replayed one set of episodes)."""
    sessions = (run / "sessions.jsonl").read_text().splitlines()
    assert sessions and all(json.loads(line)["eval_protocol"] == EVAL_PROTOCOL
                            for line in sessions)
    old = tmp_path / "old"
    old.mkdir()
    (old / "sessions.jsonl").write_text(
        json.dumps({"backend": "cpu", "cpus": 2, "seconds": 5.0}) + "\n"
        + json.dumps({"backend": "cpu", "cpus": 2, "seconds": 5.0, "eval_protocol": 2}) + "\n")
    assert eval_protocol(cast(Run, SimpleNamespace(path=old))) == 1
    assert eval_protocol(cast(Run, SimpleNamespace(path=run))) == EVAL_PROTOCOL
    assert eval_protocol(cast(Run, SimpleNamespace(path=tmp_path / "absent"))) is None
    summary = {"runs": [{"run": "a/cmat-s0-2", "eval_protocol": 1},
                        {"run": "a/mat-s0-2", "eval_protocol": 2},
                        {"run": "a/mappo-s0-2", "eval_protocol": None}]}
    text = old_protocol_text(summary)
    assert "1 of 3 runs were evaluated under the old protocol" in text
    assert text.endswith(": a/cmat-s0-2.")
    assert old_protocol_text({"runs": summary["runs"][1:]}) == ""


@pytest.mark.parametrize("slots", [4, 7])
def test_more_episodes_than_slots_play_one_after_another_and_count_each_once(
        slots: int) -> None:
    """A fresh greedy policy plays the same joint action in every episode of a one-step matrix
    game whose payoffs are all positive, so every episode returns the same: the mean over 10
    episodes played in fewer slots (1 to 3 episodes each) is that return."""
    import jax

    from cmat.algorithms import build_algorithm
    from cmat.envs import make_env
    from cmat.resolve import load_config
    from cmat.runners.evaluation import evaluate_in_graph

    config = load_config(overrides=["env=matrix:fig1", "env_kwargs.payoff=[[10,4],[6,8]]"])
    env = make_env(config.env, **config.env_kwargs)
    algorithm = build_algorithm(config.algo, config.network, env.spec, config.ppo, config.options)
    _, timestep = env.reset(jax.random.PRNGKey(0))
    params = algorithm.init(jax.random.PRNGKey(1), timestep.obs, timestep.action_mask)
    one = evaluate_in_graph(env, algorithm, params, jax.random.PRNGKey(2), 1)
    many = evaluate_in_graph(env, algorithm, params, jax.random.PRNGKey(2), 10, max_slots=slots)
    assert float(many["episode_return"]) == pytest.approx(float(one["episode_return"]))
    assert float(one["episode_return"]) in (10.0, 4.0, 6.0, 8.0)
