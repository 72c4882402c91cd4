"""The package imports only downwards and has no import cycle (scripts/import_graph.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "import_graph.py"


def check_copy(root: Path) -> subprocess.CompletedProcess[str]:
    """`import_graph.py --check` run from a copy under `root`, on the package `root/cmat`."""
    copy = root / "scripts" / "import_graph.py"
    copy.parent.mkdir()
    copy.write_text(SCRIPT.read_text())
    return subprocess.run(
        [sys.executable, str(copy), "--check"], capture_output=True, text=True, check=False
    )


def test_no_upward_import_and_no_cycle() -> None:
    result = subprocess.run(
        [sys.executable, str(SCRIPT), "--check"], capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_check_finds_an_upward_import_and_a_cycle(tmp_path: Path) -> None:
    package = tmp_path / "cmat"
    (package / "networks").mkdir(parents=True)
    (package / "algorithms").mkdir()
    for init in (package, package / "networks", package / "algorithms"):
        (init / "__init__.py").write_text("")
    (package / "networks" / "net.py").write_text("from cmat.algorithms.algo import X\n")
    (package / "algorithms" / "algo.py").write_text("def f():\n    import cmat.networks.net\n")
    result = check_copy(tmp_path)
    assert result.returncode == 1
    assert "upward import: cmat.networks.net -> cmat.algorithms.algo" in result.stdout
    assert "import cycle: cmat.algorithms.algo <-> cmat.networks.net" in result.stdout


def test_the_check_finds_algorithm_packages_that_import_each_other(tmp_path: Path) -> None:
    """No module imports itself back, but package a's `__init__` imports package b, whose
    class imports a's: a cycle between algorithm packages."""
    algorithms = tmp_path / "cmat" / "algorithms"
    for package in ("a", "b"):
        (algorithms / package).mkdir(parents=True)
        (algorithms / package / "algorithm.py").write_text("")
    for init in (tmp_path / "cmat", algorithms, algorithms / "b"):
        (init / "__init__.py").write_text("")
    (algorithms / "a" / "__init__.py").write_text("from cmat.algorithms import b\n")
    (algorithms / "b" / "algorithm.py").write_text("from cmat.algorithms.a.algorithm import X\n")
    result = check_copy(tmp_path)
    assert result.returncode == 1
    assert result.stdout.splitlines() == [
        "import cycle between algorithm packages: cmat.algorithms.a <-> cmat.algorithms.b"]
