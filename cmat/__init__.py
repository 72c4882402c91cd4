"""cmat: the Consensus Multi-Agent Transformer for cooperative multi-agent RL, in JAX.

The Python API (cmat.api): `train`, `open_run`, `Run`, `experiment`, `Experiment`; trained
policies (cmat.policy): `load_policy`, `Policy`. Imported on first use, so that `import cmat`
stays free of JAX.
"""

from cmat.errors import CmatError
from cmat.version import __version__

__all__ = [
    "CmatError", "Experiment", "Policy", "Run", "__version__", "experiment", "load_policy",
    "open_run", "train",
]

LAZY = {"Policy": "cmat.policy", "load_policy": "cmat.policy", "train": "cmat.api",
        "open_run": "cmat.api", "Run": "cmat.api", "experiment": "cmat.api",
        "Experiment": "cmat.api"}


def __getattr__(name: str) -> object:
    if name in LAZY:
        import importlib

        return getattr(importlib.import_module(LAZY[name]), name)
    raise AttributeError(f"module 'cmat' has no attribute {name!r}")
