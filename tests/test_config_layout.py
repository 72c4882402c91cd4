"""Run directories of an earlier config layout (cmat.config.CONFIG_LAYOUT) still load: layout 1
chose Sable's variant with `network.recurrent`, layout 2 names it by the algorithm."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml

import cmat
from cmat.cli import main
from cmat.config import CONFIG_LAYOUT, TrainConfig, from_yaml, layout, to_yaml

pytestmark = pytest.mark.quick_compiles


def layout_1(config: TrainConfig, **network: object) -> str:
    """`config` as cmat wrote config.yaml before layout 2: no layout line, every network field
    including `recurrent`."""
    loaded = yaml.safe_load(to_yaml(config))
    loaded["network"].update(network)
    return "# written by cmat 0.1.0\n" + yaml.safe_dump(loaded, sort_keys=False)


@pytest.mark.parametrize(("algo", "recurrent", "now"), [
    ("sable", False, "ff_sable"), ("sable", True, "sable"), ("cmat", False, "cmat"),
    ("mappo", True, "mappo"),
])
@pytest.mark.unit
def test_a_layout_1_config_reads_as_todays(algo: str, recurrent: bool, now: str) -> None:
    text = layout_1(TrainConfig(algo=algo), recurrent=recurrent)
    assert layout(text) == 1
    config = from_yaml(text)
    assert config.algo == now
    assert to_yaml(config).splitlines()[1] == f"# config layout {CONFIG_LAYOUT}"
    assert layout(to_yaml(config)) == CONFIG_LAYOUT


@pytest.mark.unit
def test_a_newer_layout_is_one_line_naming_both_layouts() -> None:
    text = to_yaml(TrainConfig()).replace(f"# config layout {CONFIG_LAYOUT}",
                                          f"# config layout {CONFIG_LAYOUT + 1}")
    with pytest.raises(cmat.CmatError, match=f"config layout {CONFIG_LAYOUT + 1} is newer"):
        from_yaml(text)


def test_a_feed_forward_sable_run_of_layout_1_evaluates_and_resumes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A feed-forward Sable run written as layout 1 (`algo: sable`, `network.recurrent: false`)
    evaluates to the same figures as today's `ff_sable` run it was made from, and resumes."""
    run = tmp_path / "run"
    assert main(["train", "--env", "matrix:fig1", "--algo", "ff_sable", "--steps", "200",
                 "--out", str(run), "--set", "network.n_embd=16", "num_envs=4",
                 "rollout_length=25", "eval_episodes=4"]) == 0
    capsys.readouterr()
    assert main(["eval", "--run", str(run)]) == 0
    today = json.loads(capsys.readouterr().out)
    old = tmp_path / "old"
    shutil.copytree(run, old)
    config = cmat.open_run(run).config
    written = yaml.safe_load(layout_1(config, recurrent=False))
    written["algo"] = "sable"
    (old / "config.yaml").write_text("# written by cmat 0.1.0\n" + yaml.safe_dump(written))
    assert main(["eval", "--run", str(old)]) == 0
    assert json.loads(capsys.readouterr().out) == today
    assert cmat.open_run(old).config.algo == "ff_sable"
    assert main(["train", "--resume", str(old), "--steps", "300"]) == 0
    assert cmat.open_run(old).config.algo == "ff_sable"
