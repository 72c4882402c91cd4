"""`cmat config`: every field with its value, its source and its docstring."""

from __future__ import annotations

import pytest

from cmat.cli import main
from cmat.config import field_docs, field_names


def test_every_config_field_has_a_docstring() -> None:
    docs = field_docs()
    missing = [name for name in field_names() if not docs.get(name)]
    assert not missing, missing


def test_config_shows_the_algorithms_reference_values_with_their_source(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["config", "--algo", "happo", "--env", "smax:3m", "--set", "ppo.lr=1e-4"]) == 0
    out = capsys.readouterr().out
    assert "ppo.clip_eps = 0.2  [algorithm happo]" in out
    assert "num_envs = 32  [suite smax]" in out
    assert "ppo.lr = 0.0001  [command line]" in out
    assert "ppo.lr = 0.0001  [command line]\n    Adam learning rate" in out
    fields = [line.split(" = ")[0] for line in out.splitlines() if not line.startswith(" ")]
    assert fields == field_names()


def test_config_with_an_unknown_algorithm_is_one_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["config", "--algo", "nope"]) == 2
    assert capsys.readouterr().err.count("\n") == 1
