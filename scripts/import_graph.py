"""cmat's internal import graph: one line per module, ``module -> imported cmat modules``.

Usage: ``python scripts/import_graph.py [--check]``. Every import counts, also those inside
functions; ``from package import module`` counts as an import of the module. With ``--check``
it prints only the imports that go upwards in `LAYERS`, the import cycles between modules and
those between algorithm packages (`cmat/algorithms/NAME/`: one may import another's modules,
never in a cycle), and exits 1 when there is one.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "cmat"

LAYERS = {
    "cmat.errors": 0, "cmat.version": 0, "cmat.plugins": 0,
    "cmat.config": 1, "cmat.envs": 1,
    "cmat.networks": 2,
    "cmat.algorithms": 3,
    "cmat.configfile": 4, "cmat.resolve": 4, "cmat.rundir": 4, "cmat.plots": 4,
    "cmat.runners": 5,
    "cmat.experiments": 6, "cmat.policy": 6,
    "cmat.render": 7, "cmat.api": 7,
    "cmat.cli": 8, "cmat.__main__": 8, "cmat": 8,
}
"""Layer of each package or top-level module: a module imports only from its own package or
from lower layers."""


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def is_module(name: str) -> bool:
    """Whether `name` is a module or package of cmat's (a file of PACKAGE)."""
    path = PACKAGE.parent.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def imports(path: Path) -> set[str]:
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.startswith("cmat"))
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("cmat"):
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names
                         if is_module(f"{node.module}.{alias.name}"))
    return found


def unit(module: str) -> str:
    """The package or top-level module `module` belongs to (a key of LAYERS)."""
    return ".".join(module.split(".")[:2])


def algorithm_package(module: str) -> str | None:
    """The algorithm package (`cmat.algorithms.NAME`, a folder) `module` belongs to, or None."""
    parts = module.split(".")
    package = ".".join(parts[:3])
    if parts[:2] != ["cmat", "algorithms"] or len(parts) < 3:
        return None
    return package if (PACKAGE.parent.joinpath(*parts[:3]) / "__init__.py").is_file() else None


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        for target in graph.get(module, ()):
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == module:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="list upward imports and cycles only; exit 1 if there is one")
    args = parser.parse_args()
    graph = {
        module_name(path): imports(path) - {module_name(path)}
        for path in sorted(PACKAGE.rglob("*.py"))
    }
    if not args.check:
        for module, targets in sorted(graph.items()):
            print(f"{module} -> {', '.join(sorted(targets)) or '-'}")
        return 0
    problems = 0
    for module, targets in sorted(graph.items()):
        for target in sorted(targets):
            if unit(target) != unit(module) and LAYERS[unit(target)] > LAYERS[unit(module)]:
                print(f"upward import: {module} -> {target}")
                problems += 1
    package_graph = {
        module: {
            target for target in targets
            if target in graph and not module.startswith(target + ".")
        }
        for module, targets in graph.items()
    }
    for component in cycles(package_graph):
        print(f"import cycle: {' <-> '.join(component)}")
        problems += 1
    algorithm_graph: dict[str, set[str]] = {}
    for module, targets in graph.items():
        if (source := algorithm_package(module)) is not None:
            algorithm_graph.setdefault(source, set()).update(
                package for package in map(algorithm_package, targets)
                if package is not None and package != source
            )
    for component in cycles(algorithm_graph):
        print(f"import cycle between algorithm packages: {' <-> '.join(component)}")
        problems += 1
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
