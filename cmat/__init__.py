"""cmat: the Consensus Multi-Agent Transformer for cooperative multi-agent RL, in JAX."""

from cmat.errors import CmatError
from cmat.version import __version__

__all__ = ["CmatError", "Policy", "__version__", "load_policy"]


def __getattr__(name: str) -> object:
    """`cmat.load_policy` and `cmat.Policy` (cmat.policy), imported on first use so that
    `import cmat` stays free of JAX."""
    if name in ("Policy", "load_policy"):
        from cmat import policy

        return getattr(policy, name)
    raise AttributeError(f"module 'cmat' has no attribute {name!r}")
