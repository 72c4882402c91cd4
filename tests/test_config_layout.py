"""Run directories of an earlier config layout (cmat.configfile.CONFIG_LAYOUT) still load: layout
1 chose Sable's variant with `network.recurrent`, layout 2 named it by the algorithm and kept the
algorithms' own options in the shared sections, layout 3 in the algorithm's."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml

import cmat
from cmat.algorithms import algorithm_names
from cmat.cli import main
from cmat.config import TrainConfig
from cmat.configfile import CONFIG_LAYOUT, MOVED, from_yaml, layout, to_mapping, to_yaml
from cmat.resolve import load_config

pytestmark = pytest.mark.quick_compiles


def layout_2(config: TrainConfig) -> dict[str, object]:
    """`config` as layout 2 held it: every field of `MOVED` in the shared sections, those the
    algorithm does not have at their layout-2 defaults."""
    loaded = to_mapping(config)
    own = loaded.pop(config.algo)
    unread = {"network": {"mlp_layers": 2, "compressor_heads": 4, "consensus_iterations": None,
                          "consensus_source": "mixture", "consensus_policy": "deterministic",
                          "consensus_codes": 8, "latent_head_gain": 1.0, "retention_decay": 0.8,
                          "retention_chunk": None, "attention_block": 0},
              "ppo": {"per_agent_gae": False, "joint_clip": "joint", "entropy_reduction": "mean",
                      "consensus_ent_coef": 0.01, "order_loss_coef": 1.0,
                      "order_in_loss": "sampled"}}
    for section, moved in MOVED.items():
        assert set(moved) == set(unread[section])
        loaded[section] |= {name: own.get(name, unread[section][name]) for name in moved}
    return loaded


def layout_1(config: TrainConfig, **network: object) -> str:
    """`config` as cmat wrote config.yaml before layout 2: no layout line, every network field
    including `recurrent`."""
    loaded = layout_2(config)
    loaded["network"].update(network)  # type: ignore[attr-defined]
    return "# written by cmat 0.1.0\n" + yaml.safe_dump(loaded, sort_keys=False)


@pytest.mark.parametrize("algo", algorithm_names())
@pytest.mark.unit
def test_a_layout_2_config_reads_as_todays(algo: str) -> None:
    """Each algorithm's own options move from the shared sections into its section, with their
    values; the options of other algorithms that layout 2 held (unread) are dropped."""
    overrides = [f"algo={algo}", "env=smax:3m", "network.n_embd=32", "ppo.lr=1e-4"]
    config = load_config(overrides=overrides)
    text = "# written by cmat 0.2.0\n# config layout 2\n" + yaml.safe_dump(layout_2(config))
    assert layout(text) == 2
    assert from_yaml(text) == config
    assert from_yaml(to_yaml(config)) == config


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
