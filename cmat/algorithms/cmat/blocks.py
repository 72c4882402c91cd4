"""CMAT's parameter blocks by name: what fine-tuning trains, and m at evaluation time.

The blocks are the top-level modules of `network.CMATNetwork` (paper Fig. 2,
Algorithm 1): encoder, critic_compressor, critic_mlp, decoder, actor_compressor, actor_mlp, and
latent_consensus when the consensus is stochastic.
A block the configuration never calls has no parameters (decoder at m = 0, actor_compressor with
consensus_source = last); the sets below then simply name fewer blocks.
"""

from __future__ import annotations

from typing import Any

import jax

from cmat.algorithms.base import Params
from cmat.algorithms.sgd import FROZEN, TRAIN
from cmat.errors import CmatError

CMAT_BLOCKS = (
    "encoder", "critic_compressor", "critic_mlp", "decoder", "actor_compressor", "actor_mlp",
    "latent_consensus",
)

FINETUNE_TRAINABLE: dict[str, tuple[str, ...]] = {
    "consensus": ("critic_mlp", "decoder", "actor_compressor", "latent_consensus"),
    "action": ("critic_mlp", "actor_mlp"),
}
"""The blocks each fine-tuning stage trains (Algorithm 1, B); every other block is frozen. Its
stages are those CMAT's entry declares (`cmat.algorithms.cmat.FINETUNE_STAGES`), in order.
Consensus enhancement freezes the action policy (Actor-MLP, with the continuous heads' log_std,
which is a parameter of the Actor-MLP) and the encoder and Critic-Compressor, which the paper
names as neither; action-policy enhancement freezes everything that forms the consensus. With a
stochastic consensus (`cmat.consensus_policy`), its policy π_c (`latent_consensus`) is part of
the consensus generation μ: trained with it, frozen with it."""

def finetune_labels(params: Params, mode: str) -> Any:
    """A tree like `params` labelling each leaf TRAIN or FROZEN for fine-tuning `mode`.

    A parameter block this module does not know is an error, not silently frozen or trained:
    the freeze sets must then be extended for it.
    """
    trainable = FINETUNE_TRAINABLE[mode]
    blocks = params["params"]
    unknown = sorted(set(blocks) - set(CMAT_BLOCKS))
    if unknown:
        raise CmatError(
            f"fine-tuning does not know CMAT parameter block {unknown[0]!r}; "
            f"known blocks: {', '.join(CMAT_BLOCKS)}"
        )
    return {
        "params": {
            name: jax.tree.map(lambda _, label=(TRAIN if name in trainable else FROZEN): label,
                               block)
            for name, block in blocks.items()
        }
    }


def with_iterations(params: Params, iterations: int) -> Params:
    """Parameters of a network trained with m >= `iterations`, for running it with m = iterations.

    The decoder is weight-shared across iterations; only its positional table is per iteration,
    so stopping the refinement early keeps the first `iterations` rows (any leading axes, e.g.
    seeds, are kept). At 0 the decoder is not run and its parameters are dropped.
    """
    blocks = dict(params["params"])
    decoder = blocks.pop("decoder", None)
    if iterations == 0:
        return {**params, "params": blocks}
    trained = 0 if decoder is None else decoder["positions"].shape[-2]
    if trained < iterations:
        raise CmatError(
            f"m = {iterations} exceeds the m = {trained} the network was trained with: the decoder "
            f"has positional embeddings for {trained} iterations only"
        )
    blocks["decoder"] = {**decoder, "positions": decoder["positions"][..., :iterations, :]}
    return {**params, "params": blocks}
