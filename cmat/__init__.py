"""cmat: the Consensus Multi-Agent Transformer for cooperative multi-agent RL, in JAX."""

__version__ = "0.1.0"
