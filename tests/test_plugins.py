"""Suites and algorithms from other packages: a suite and an algorithm defined in tests/plugins
and named under the `cmat.suites` and `cmat.algorithms` entry points of a package installed for
the test (a dist-info on PYTHONPATH) are found, resolved with their own settings and trained by
`cmat train`, without any edit of cmat."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

pytestmark = pytest.mark.quick_compiles

PLUGINS = Path(__file__).parent / "plugins"


def installed(tmp_path: Path, entry: str, group: str = "cmat.suites") -> dict[str, str]:
    """An environment whose Python sees a package `cmat-coins` naming `entry` in `group`."""
    site = tmp_path / "site"
    info = site / "cmat_coins-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: cmat-coins\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[{group}]\n{entry}\n")
    path = os.pathsep.join([str(site), str(PLUGINS), os.environ.get("PYTHONPATH", "")])
    return {**os.environ, "PYTHONPATH": path, "JAX_PLATFORMS": "cpu"}


def cmat(env: dict[str, str], *arguments: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "cmat", *arguments], env=env,
                          capture_output=True, text=True, timeout=600, check=False)


def test_a_plugin_suite_is_found_configured_and_trained(tmp_path: Path) -> None:
    env = installed(tmp_path, "coins = cmat_coins:SUITE")
    assert "coins:N" in cmat(env, "train", "--help").stdout
    out = tmp_path / "run"
    done = cmat(env, "train", "--env", "coins:4", "--algo", "mappo", "--out", str(out))
    assert done.returncode == 0, done.stderr[-3000:]
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["total_steps"] == 2_000 and config["rollout_length"] == 10
    assert "suite coins" in (out / "config.yaml").read_text()
    evaluation = pd.read_csv(out / "metrics.csv").query("kind == 'eval'")
    assert evaluation["episode_return"].iloc[-1] == pytest.approx(1.0)
    unknown = cmat(env, "train", "--env", "coins:1", "--dry-run")
    assert unknown.returncode == 2
    assert unknown.stderr.strip() == ("cmat: error: unknown coins task '1'; available: 2 to 64 "
                                      "agents")


@pytest.mark.parametrize(("entry", "problem"), [
    ("coins = cmat_coins:missing", "cannot be loaded"),
    ("coins = cmat_coins:build", "is not a cmat.envs.suites.Suite (function)"),
    ("smax = cmat_coins:SUITE", "takes a name cmat has"),
])
def test_a_broken_plugin_is_skipped_with_one_line(tmp_path: Path, entry: str,
                                                   problem: str) -> None:
    done = cmat(installed(tmp_path, entry), "train", "--env", "matrix:fig1", "--dry-run")
    assert done.returncode == 0, done.stderr[-3000:]
    warnings = [line for line in done.stderr.splitlines() if line.startswith("cmat: warning")]
    assert len(warnings) == 1 and problem in warnings[0] and warnings[0].endswith("skipped")


def test_a_plugin_algorithm_is_found_configured_and_trained(tmp_path: Path) -> None:
    env = installed(tmp_path, "toy_mappo = cmat_toy_algorithm:ENTRY", "cmat.algorithms")
    assert "toy_mappo" in cmat(env, "train", "--help").stdout
    out = tmp_path / "run"
    done = cmat(env, "train", "--algo", "toy_mappo", "--out", str(out))
    assert done.returncode == 0, done.stderr[-3000:]
    text = (out / "config.yaml").read_text()
    assert yaml.safe_load(text)["ppo"]["lr"] == 1e-3 and "algorithm toy_mappo" in text
    assert yaml.safe_load(text)["toy_mappo"] == {"mlp_layers": 2}
    evaluation = pd.read_csv(out / "metrics.csv").query("kind == 'eval'")
    assert evaluation["episode_return"].iloc[-1] == pytest.approx(100.0)
    deeper = cmat(env, "train", "--algo", "toy_mappo", "--dry-run", "--set",
                  "toy_mappo.mlp_layers=3")
    assert "  mlp_layers: 3  # command line" in deeper.stdout, deeper.stderr[-3000:]
    broken = cmat(installed(tmp_path / "broken", "mat = cmat_toy_algorithm:ENTRY",
                            "cmat.algorithms"), "train", "--dry-run")
    assert broken.returncode == 0, broken.stderr[-3000:]
    assert [line for line in broken.stderr.splitlines() if line.startswith("cmat: warning")] == [
        "cmat: warning: the algorithm 'mat' (cmat_toy_algorithm:ENTRY) takes a name cmat has; "
        "skipped"]
