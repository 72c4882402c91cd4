"""Option groups several algorithms' sections share (`cmat.config.AlgorithmOptions`): each
algorithm's `options.py` composes its section from these and fields of its own. JAX-free.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, TypeVar

from cmat.config import AlgorithmOptions
from cmat.errors import CmatError

if TYPE_CHECKING:
    from cmat.config import TrainConfig

Section = TypeVar("Section", bound=AlgorithmOptions)

JOINT_CLIPS = ("joint", "per_agent")
ENTROPY_REDUCTIONS = ("mean", "sum")


@dataclass(frozen=True)
class EncoderOptions(AlgorithmOptions):
    """How an encoder over agents attends (CMAT, MAT, PMAT, Triple-BERT)."""

    attention_block: int = 0
    """The encoder's self-attention over agents in blocks of this many agents (queries), one
    block at a time and recomputed in the backward pass, so its memory grows linearly in the
    number of agents at a fixed batch instead of quadratically; 0 attends with all agents at
    once. The same result up to floating-point order, and the same parameters: a run may change
    it when resumed. Other attentions (compressors, decoder cross-attention) already scale
    linearly in n at a fixed m."""
    inducing_points: int = 0
    """k > 0: each encoder block's agents attend through k learned vectors instead of to each
    other (the Set Transformer's induced set attention, `cmat.networks.layers.EncoderBlock`), so
    the encoder's time, not only its memory, grows linearly in the number of agents; still
    equivariant in the agents, so CMAT stays order independent. A different network (k more
    parameters per block and a second attention): fixed for a run. 0 (the default, and the
    paper's encoder): full self-attention over agents. A departure from the paper for teams
    large enough that n² scores dominate a step (docs/dispatch.md, "Large fleets: vehicles
    attending through inducing points")."""

    network_options: ClassVar[tuple[str, ...]] = ("inducing_points",)

    def checks(self, section: str, config: TrainConfig) -> list[tuple[bool, str]]:
        return [*super().checks(section, config),
                (self.attention_block >= 0,
                 f"{section}.attention_block must be >= 0, got {self.attention_block}"),
                (self.inducing_points >= 0,
                 f"{section}.inducing_points must be >= 0, got {self.inducing_points}")]


@dataclass(frozen=True)
class JointRatioOptions(AlgorithmOptions):
    """The joint ratio's loss options (CMAT, Triple-BERT: single-agent PPO on the joint action,
    paper eq. cmat)."""

    joint_clip: str = "joint"
    """'joint' clips the joint ratio R = Π_i r_i to [1−ε, 1+ε] (paper eq. cmat); 'per_agent'
    clips it to [(1−ε)^k, (1+ε)^k] for the k active agents of the sample, i.e. holds the
    per-agent geometric mean R^(1/k) to [1−ε, 1+ε], so the per-agent trust region does not
    shrink as 1/n."""
    entropy_reduction: str = "mean"
    """'mean' over agents (the paper, as MAT) or 'sum' (the entropy of the joint policy
    Π_i π_i, which single-agent PPO on the joint action would regularise)."""

    def checks(self, section: str, config: TrainConfig) -> list[tuple[bool, str]]:
        return [
            *super().checks(section, config),
            (self.joint_clip in JOINT_CLIPS, f"{section}.joint_clip must be one of "
             f"{', '.join(JOINT_CLIPS)}, got {self.joint_clip!r}"),
            (self.entropy_reduction in ENTROPY_REDUCTIONS,
             f"{section}.entropy_reduction must be one of {', '.join(ENTROPY_REDUCTIONS)}, "
             f"got {self.entropy_reduction!r}"),
        ]


@dataclass(frozen=True)
class PerAgentValueOptions(AlgorithmOptions):
    """Per-agent values (MAT, PMAT, Sable: a value V(ô_i) per agent)."""

    per_agent_gae: bool = False
    """GAE per agent on each agent's own V(ô_i), each V(ô_i) regressed on its own return (the
    reference MAT with value normalisation, mat/runner/shared/base_runner.py +
    utils/shared_buffer.py; Mava's Sable). False: one GAE on the team value
    V(O) = mean_i V(ô_i)."""


def options_of(options: AlgorithmOptions | None, cls: type[Section]) -> Section:
    """`options` as the section class `cls` of an algorithm: `cls`'s defaults for None or the
    bare base (`TrainConfig`'s default). Raises CmatError for another algorithm's section."""
    if options is None or type(options) is AlgorithmOptions:
        return cls()
    if not isinstance(options, cls):
        raise CmatError(f"invalid config: the options are {cls.__name__}, got "
                        f"{type(options).__name__}")
    return options
