"""Run directories written before the learner had its own state still load, evaluate and resume.

`tests/data/runs_before_learner_split/` holds runs written by cmat at commit 7e6733b (one flat
state with the environments' fields beside the learner's): in-graph CMAT and MAPPO on the Fig. 1
matrix game, 2 seeds, and host MAPPO on a PettingZoo game of tests/test_host_edge_cases.py.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import flax.serialization
import jax
import numpy as np
import pytest

from cmat.cli import build_trainer, main
from cmat.policy import load_policy
from cmat.rundir import RunDir

pytestmark = pytest.mark.quick_compiles

OLD_RUNS = Path(__file__).parent / "data" / "runs_before_learner_split"


@pytest.mark.parametrize("name", ["fig1_cmat", "fig1_mappo", "host_mappo"])
def test_an_old_checkpoint_restores_exactly(name: str) -> None:
    run = RunDir.open(OLD_RUNS / name)
    data, steps = run.load_checkpoint()
    trainer = build_trainer(run.config())
    try:
        state = trainer.from_bytes(data)
        assert trainer.env_steps(state) == steps
    finally:
        trainer.close()
    raw = flax.serialization.msgpack_restore(data)
    for field in ("params", "target_params", "rng", "update_step"):
        stored = jax.tree.leaves(raw[field])
        restored = jax.tree.leaves(getattr(state.learner, field))
        assert len(stored) == len(restored)
        for want, got in zip(stored, restored, strict=True):
            np.testing.assert_array_equal(np.asarray(got), want)
    if state.envs is not None:
        np.testing.assert_array_equal(np.asarray(state.envs.timestep.obs),
                                      raw["timestep"]["obs"])


@pytest.mark.parametrize("name", ["fig1_cmat", "fig1_mappo"])
def test_an_old_run_evaluates_and_resumes(name: str, tmp_path: Path) -> None:
    policy = load_policy(OLD_RUNS / name)
    assert policy.env_steps == 400
    run = tmp_path / name
    shutil.copytree(OLD_RUNS / name, run)
    assert main(["train", "--resume", str(run), "--steps", "800"]) == 0
    assert RunDir.open(run).load_checkpoint()[1] == 800
    evals = [row for row in RunDir.open(run).read_metrics() if row["kind"] == "eval"]
    assert {int(row["env_steps"]) for row in evals} == {400, 800}


def test_a_checkpoint_of_another_network_is_reported_where_it_first_differs() -> None:
    from cmat.runners.base import state_difference

    expected = {"a": {"w": jax.ShapeDtypeStruct((2, 3), np.float32)}, "b": None}

    def found(a: dict) -> dict:
        return {"a": a, "b": None}

    assert state_difference(expected, found({"w": np.zeros((2, 3))}), "state") is None
    assert (state_difference(expected, found({"w": np.zeros((3, 3))}), "state")
            == "shapes differ: state/a/w is (3, 3) in the checkpoint, (2, 3) for this config")
    assert (state_difference(expected, found({}), "state")
            == "state differs: state/a/w is not in the checkpoint")
    assert (state_difference(expected, found({"w": np.zeros((2, 3)), "bias": np.zeros(3)}),
                             "state")
            == "state differs: the checkpoint has state/a/bias, which this config's state lacks")
    assert (state_difference(expected, found({"w": {"kernel": np.zeros(2)}}), "state")
            == "state differs: state/a/w has another structure in the checkpoint")
