"""`cmat config`: every field with its value, its source and its docstring."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from typing import Any

import jax
import numpy as np
import pytest

import cmat
from cmat.algorithms import algorithm_entry, algorithm_names, algorithm_options, build_algorithm
from cmat.cli import main
from cmat.config import NetworkConfig
from cmat.configfile import field_docs, field_names
from cmat.envs import make_env

pytestmark = pytest.mark.quick_compiles

@pytest.mark.parametrize("algo", algorithm_names())
def test_every_config_field_has_a_docstring(algo: str) -> None:
    docs = field_docs(algo)
    missing = [name for name in field_names(algo) if not docs.get(name)]
    assert not missing, missing
    assert any(name.startswith(f"{algo}.") for name in docs) == bool(
        dataclasses.fields(algorithm_options(algo)))


def test_config_shows_the_algorithms_reference_values_with_their_source(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["config", "--algo", "happo", "--env", "smax:3m", "--set", "ppo.lr=1e-4"]) == 0
    out = capsys.readouterr().out
    assert "ppo.clip_eps = 0.2  [algorithm happo]" in out
    assert "num_envs = 32  [suite smax]" in out
    assert "ppo.lr = 0.0001  [command line]" in out
    assert "ppo.lr = 0.0001  [command line]\n    Adam learning rate" in out
    fields = [line.split(" = ")[0] for line in out.splitlines() if not line.startswith((" ", "#"))]
    assert fields == field_names("happo")
    assert "happo.mlp_layers = 2  [default]" in out
    assert "# suite smax: MAT's SMAC scripts" in out
    assert main(["config", "--algo", "mappo", "--env", "smax:5m_vs_6m"]) == 0
    out = capsys.readouterr().out
    assert "ppo.clip_eps = 0.05  [algorithm mappo on smax:5m_vs_6m]" in out
    assert "ppo.epochs = 10  [algorithm mappo on smax:5m_vs_6m]" in out


@pytest.mark.unit
def test_config_imports_no_jax_and_builds_the_environment_only_when_asked(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A fresh interpreter prints the config of a SMAX task without importing JAX; an unknown
    scenario passes there and is one error line with `--check-env`."""
    script = ("import sys; from cmat.cli import main; "
              "code = main(['config', '--env', 'smax:3mm', '--algo', 'mat']); "
              "print(code, 'jax' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120, check=True)
    assert done.stdout.splitlines()[-1] == "0 False", done.stderr[-2000:]
    assert main(["config", "--env", "smax:3mm", "--check-env"]) == 2
    assert "unknown SMAX scenario '3mm'" in capsys.readouterr().err


def test_config_with_an_unknown_algorithm_is_one_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["config", "--algo", "nope"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


CHANGED_NETWORK_FIELDS = {
    "n_embd": 32, "n_head": 2, "n_block": 2, "init_gain": 0.5, "log_std_init": 0.0,
}


@pytest.mark.parametrize("algo", algorithm_names())
def test_network_fields_an_algorithm_does_not_declare_leave_it_unchanged(algo: str) -> None:
    assert set(CHANGED_NETWORK_FIELDS) == {f.name for f in dataclasses.fields(NetworkConfig)}
    env = make_env("matrix:fig1")
    _, timestep = env.reset(jax.random.PRNGKey(0))

    def built(network: NetworkConfig) -> tuple[Any, Any]:
        algorithm = build_algorithm(algo, network, env.spec)
        params = algorithm.init(jax.random.PRNGKey(1), timestep.obs, timestep.action_mask)
        return params, algorithm.greedy(params, timestep.obs, timestep.action_mask)

    declared = algorithm_entry(algo).network_fields
    assert set(declared) <= set(CHANGED_NETWORK_FIELDS)
    reference_params, reference_actions = built(NetworkConfig())
    for name, value in CHANGED_NETWORK_FIELDS.items():
        if name in declared:
            continue
        params, actions = built(dataclasses.replace(NetworkConfig(), **{name: value}))
        assert jax.tree.structure(params) == jax.tree.structure(reference_params), name
        for got, want in zip(jax.tree.leaves(params), jax.tree.leaves(reference_params),
                             strict=True):
            np.testing.assert_array_equal(got, want, err_msg=name)
        np.testing.assert_array_equal(actions, reference_actions, err_msg=name)


def test_config_marks_the_network_fields_an_algorithm_does_not_read(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["config", "--algo", "mappo"]) == 0
    out = capsys.readouterr().out
    assert "network.n_embd = 64  [default]\n" in out
    assert "network.n_head = 1  [default; not read by mappo]" in out
    assert main(["config", "--algo", "cmat"]) == 0
    unread = [line.split(" = ")[0] for line in capsys.readouterr().out.splitlines()
              if "not read by cmat" in line]
    assert unread == []


def test_explain_lists_every_layer_of_a_key_and_the_last_wins(
    tmp_path: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    """A key set by every layer: the suite, the algorithm on a task, a preset, a file and the
    command line each appear once, in that order, and the last is the resolved value."""
    from cmat.resolve import explain, resolve_config

    file = tmp_path / "mine.yaml"
    file.write_text("ppo:\n  epochs: 7\n")
    overrides = ["algo=mappo", "env=smax:5m_vs_6m", "preset=paper"]
    rows = explain("ppo.epochs", file, overrides)
    labels = [label for label, _ in rows]
    assert labels[0] == "default" and labels[-1] == f"file {file}"
    assert "algorithm mappo on smax:5m_vs_6m" in labels
    assert rows[labels.index("algorithm mappo on smax:5m_vs_6m")][1] == 10
    assert resolve_config(file, overrides)[0].ppo.epochs == rows[-1][1] == 7
    rows = explain("ppo.epochs", file, [*overrides, "ppo.epochs=3"])
    assert rows[-1] == ("command line", 3)
    assert main(["config", "--algo", "mappo", "--env", "smax:5m_vs_6m", "--config", str(file),
                 "--explain", "ppo.epochs"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[-1] == f"ppo.epochs = 7  [file {file}]  <- used"
    assert len(lines) == len(explain("ppo.epochs", file, ["algo=mappo", "env=smax:5m_vs_6m"]))
    assert main(["config", "--explain", "ppo.epoch"]) == 2
    assert "did you mean 'ppo.epochs'?" in capsys.readouterr().err


@pytest.mark.unit
def test_an_algorithms_section_is_named_by_it_and_explained_layer_by_layer() -> None:
    """The dispatch suite sets Sable's retention chunk only (`sable:` in its settings) and
    the command line sets it again; the paper preset and the command line set CMAT's m; another
    algorithm's run never sees those sections."""
    from cmat.resolve import explain, resolve_config

    overrides = ["env=dispatch:grid-100-mid", "algo=sable", "sable.retention_chunk=2"]
    assert explain("sable.retention_chunk", None, overrides) == [
        ("default", None), ("suite dispatch", 1), ("command line", 2)]
    config, sources = resolve_config(None, overrides)
    assert config.options.retention_chunk == 2
    assert sources["sable.retention_chunk"] == "command line"
    overrides = ["env=dispatch:grid-100-mid", "preset=paper", "cmat.consensus_iterations=3"]
    assert explain("cmat.consensus_iterations", None, overrides) == [
        ("default", None), ("preset paper", "n"), ("command line", 3)]
    config, sources = resolve_config(None, overrides)
    assert config.options.consensus_iterations == 3
    assert sources["cmat.consensus_iterations"] == "command line"
    mat, sources = resolve_config(None, ["env=dispatch:grid-100-mid", "algo=mat"])
    assert type(mat.options).__name__ == "MATOptions"
    assert not any(name.startswith(("cmat.", "sable.")) for name in sources)


@pytest.mark.unit
@pytest.mark.parametrize(("overrides", "message"), [
    (["algo=mat", "cmat.consensus_iterations=2"],
     "cmat.consensus_iterations is an option of cmat, and this run's algo is mat"),
    (["algo=mappo", "ppo.joint_clip=per_agent"], "unknown key ppo.joint_clip"),
    (["algo=cmat", "cmat.consensus_iteration=2"], "unknown key cmat.consensus_iteration"),
    (["algo=sable", "sable.retention_chunk=abc"],
     "sable.retention_chunk: expected an integer, got 'abc'"),
    (["algo=ff_sable", "ff_sable.retention_chunk=4"], "unknown key ff_sable.retention_chunk"),
    (["algo=pmat", "pmat.order_loss_coef=-1"], "pmat.order_loss_coef must be in [0.0, inf)"),
    (["algo=happo", "happo=3"], "happo: a section (set its keys as happo.KEY=VALUE), got 3"),
    (["algo=mat", "options.per_agent_gae=false"], "unknown key options; the algorithm's section"),
])
def test_a_bad_section_key_is_one_line_naming_it(overrides: list[str], message: str) -> None:
    from cmat.resolve import load_config

    with pytest.raises(cmat.CmatError) as raised:
        load_config(overrides=overrides)
    assert message in str(raised.value) and "\n" not in str(raised.value)
