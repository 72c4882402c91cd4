"""CMAT's section of the run config (`cmat:` in a config file, `--set cmat.KEY=VALUE`): the
consensus (paper eq. decoder, eq. actor_compressor, eq. critic_compressor) and the joint
ratio's loss options. JAX-free."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

from cmat.algorithms.options import EncoderOptions, JointRatioOptions
from cmat.errors import CmatError

if TYPE_CHECKING:
    from cmat.config import TrainConfig

CONSENSUS_SOURCES = ("mixture", "last")
CONSENSUS_POLICIES = ("deterministic", "categorical", "gaussian")
ITERATION_RULES = {"n": (1, 1), "n/2": (1, 2), "2n": (2, 1)}
"""m given relative to the number of agents n: name -> (numerator, denominator), m = ⌊n·a/b⌋."""
LARGE_TEAM = 32
"""Teams of more agents than this are large: where m is left unset (None), they get
`LARGE_TEAM_ITERATIONS` consensus iterations instead of the paper's m = n. Every task of the
paper (at most 27 agents) keeps m = n."""
LARGE_TEAM_ITERATIONS = 2
"""m for large teams, chosen from CMAT at m = 1, 2, 5 and 10 on the 100-vehicle dispatch task
(grid-100-mid, 24,000 steps, 3 seeds; docs/dispatch.md, "Consensus iterations on a large
fleet"): m = 2 scored highest (return 23.0 ± 0.6 against 20.7-21.5 for the others), and larger
m did not learn better, while the decoder's cost grows with m."""


@dataclass(frozen=True)
class CompressorOptions(EncoderOptions):
    """The soft-mixture compressors of CMAT and Triple-BERT (paper eq. critic_compressor)."""

    compressor_heads: int = 4
    """h, the number of soft mixtures each compressor forms (eq. critic_compressor); the paper
    does not give it."""

    network_options: ClassVar[tuple[str, ...]] = (*EncoderOptions.network_options,
                                                  "compressor_heads")

    def checks(self, section: str, config: TrainConfig) -> list[tuple[bool, str]]:
        return [*super().checks(section, config),
                (self.compressor_heads > 0,
                 f"{section}.compressor_heads must be > 0, got {self.compressor_heads}")]


@dataclass(frozen=True)
class CMATOptions(CompressorOptions, JointRatioOptions):
    """CMAT's options: the compressors, the consensus decoder and its policy, the joint ratio."""

    consensus_iterations: int | str | None = None
    """m, decoder iterations (eq. decoder): an integer >= 0, or 'n', 'n/2' (⌊n/2⌋) or '2n'
    resolved against the environment's number of agents n (the paper's ablation values). None:
    the paper's m = n for teams of up to `LARGE_TEAM` (32) agents, `LARGE_TEAM_ITERATIONS` (2)
    above (`--preset paper` sets 'n' for every team); 0 uses e0 alone. See
    `resolve_iterations`."""
    consensus_source: str = "mixture"
    """'mixture': c = Actor-Compressor(e0..em) (eq. actor_compressor, the default);
    'last': c = e_m (the paper's ablation)."""
    consensus_policy: str = "deterministic"
    """π_c(c | O) (paper eq. joint-stochastic): 'deterministic' c = μ(O) (the paper's method);
    'categorical' samples one of `consensus_codes` latent codes z from logits on μ(O) and acts on
    μ(O) + embedding(z); 'gaussian' samples c ~ N(μ(O), σ²) with a learned, state-independent σ.
    A sampled latent's log-probability enters the joint ratio."""
    consensus_codes: int = 8
    """K, the number of latent codes of the categorical consensus policy."""
    latent_head_gain: float = 1.0
    """Stochastic consensus only: orthogonal-init gain of the code logits and of the Actor-MLP's
    output layer (in place of `network.init_gain`). Gain 1 makes every latent start as a
    distinct product policy, which is what lets the mixture find a coordinated optimum: on
    matrix:penalty (benchmarks/matrix_optimum.py) gain 0.01 left all 10 seeds on the safe
    (1, 1)."""
    consensus_ent_coef: float = 0.01
    """Stochastic consensus only: weight of the consensus policy's entropy bonus."""

    network_options: ClassVar[tuple[str, ...]] = (
        *CompressorOptions.network_options, "consensus_iterations", "consensus_source",
        "consensus_policy", "consensus_codes", "latent_head_gain")

    def checks(self, section: str, config: TrainConfig) -> list[tuple[bool, str]]:
        return [
            *super().checks(section, config),
            (valid_iterations(self.consensus_iterations),
             f"{section}.consensus_iterations (m) must be >= 0, got "
             f"{self.consensus_iterations!r} (or one of {', '.join(ITERATION_RULES)}: relative "
             f"to the number of agents n)"),
            (self.consensus_source in CONSENSUS_SOURCES,
             f"{section}.consensus_source must be one of {CONSENSUS_SOURCES}, "
             f"got {self.consensus_source!r}"),
            (self.consensus_policy in CONSENSUS_POLICIES,
             f"{section}.consensus_policy must be one of {CONSENSUS_POLICIES}, "
             f"got {self.consensus_policy!r}"),
            (self.consensus_codes > 0,
             f"{section}.consensus_codes must be > 0, got {self.consensus_codes}"),
            (self.latent_head_gain > 0,
             f"{section}.latent_head_gain must be in (0.0, inf), got {self.latent_head_gain}"),
            (self.consensus_ent_coef >= 0,
             f"{section}.consensus_ent_coef must be in [0.0, inf), got "
             f"{self.consensus_ent_coef}"),
        ]

    def iterations(self, num_agents: int) -> int:
        """m for a team of `num_agents` (`resolve_iterations`)."""
        return resolve_iterations(self.consensus_iterations, num_agents)


def valid_iterations(m: int | str | None) -> bool:
    if isinstance(m, bool):
        return False
    return m is None or (isinstance(m, int) and m >= 0) or m in ITERATION_RULES


def resolve_iterations(m: int | str | None, num_agents: int) -> int:
    """The number of decoder iterations for `num_agents` agents: 'n' gives n, 'n/2' gives
    ⌊n/2⌋, '2n' gives 2n, an integer itself; None gives n up to `LARGE_TEAM` agents and
    `LARGE_TEAM_ITERATIONS` above."""
    if isinstance(m, int) and not isinstance(m, bool):
        return m
    if m is None and num_agents > LARGE_TEAM:
        return LARGE_TEAM_ITERATIONS
    rule = "n" if m is None else m
    if rule not in ITERATION_RULES:
        raise CmatError(f"invalid config: cmat.consensus_iterations {m!r} is not an integer "
                        f"or one of {', '.join(ITERATION_RULES)}")
    numerator, denominator = ITERATION_RULES[rule]
    return num_agents * numerator // denominator
