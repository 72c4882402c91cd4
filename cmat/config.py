"""Typed run configuration: dataclass defaults, overridden by a YAML file, then by `key=value`.

Defaults are the reference MAT hyper-parameters for SMAC (the reference MAT implementation's
SMAC train scripts) except where a field's docstring says otherwise. OmegaConf merges and
type-checks the layers; the result is converted back to these frozen dataclasses, so a typo or a
wrong type fails before any tracing.
"""

from __future__ import annotations

import ast
import functools
import math
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from cmat.errors import CmatError

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
FINETUNE_MODES = ("consensus", "action")
JOINT_CLIPS = ("joint", "per_agent")
ENTROPY_REDUCTIONS = ("mean", "sum")
LOSS_ORDERS = ("sampled", "index")
LOGGERS = ("tensorboard", "wandb")
NONFINITE_POLICIES = ("error", "warn")
"""What a host environment does with a NaN or infinite observation, reward or state
(`TrainConfig.host_nonfinite`): stop the run with a one-line error, or replace the values by 0
and count them (`metrics.csv` column `env_nonfinite`)."""
EVAL_ACTIONS = ("greedy", "sample")
"""How evaluation acts (`TrainConfig.eval_actions`)."""

@dataclass(frozen=True)
class NetworkConfig:
    """Network sizes (paper Sec. Network Architecture) and CMAT's consensus options. Each
    algorithm reads the fields its entry lists in `network_fields` (MAPPO and HAPPO read
    `n_embd` as their MLPs' width); `cmat config --algo NAME` marks the fields it does not."""

    n_embd: int = 64
    """Hidden size d of every block."""
    n_head: int = 1
    """Attention heads; must divide n_embd."""
    n_block: int = 1
    """Transformer blocks in the encoder and in the decoder."""
    mlp_layers: int = 2
    """MAPPO and HAPPO: hidden layers of the actor's and the critic's MLPs (on-policy's MLPBase:
    2; HARL's tuned SMAC configs: `hidden_sizes` [64, 64, 64], 3)."""
    compressor_heads: int = 4
    """h, the number of soft mixtures each compressor forms (eq. critic_compressor); the paper
    does not give it."""
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
    output layer (in place of `init_gain`). Gain 1 makes every latent start as a distinct
    product policy, which is what lets the mixture find a coordinated optimum: on
    matrix:penalty (benchmarks/matrix_optimum.py) gain 0.01 left all 10 seeds on the safe
    (1, 1)."""
    init_gain: float = 0.01
    """Orthogonal-init gain of the reference MAT's small layers (`init_(…)` without
    `activate`, mat/algorithms/mat/algorithm/ma_transformer.py): the action and value output
    layers, the query, key, value and output projections of every attention and the second
    layer of every feed-forward block. Layers followed by an activation keep the ReLU gain √2."""
    retention_decay: float = 0.8
    """Sable and feed-forward Sable: scale in [0, 1] of every head's decay κ (Mava's
    `decay_scaling_factor`, mava/configs/network/rec_retention.yaml and ff_retention.yaml)."""
    retention_chunk: int | None = None
    """Sable (the recurrent one): timesteps per chunk of the chunkwise training pass (memory
    O(chunk²) instead of O(rollout_length²); a pass's last chunk is shorter where the chunk does
    not divide its steps); None: the whole rollout in one parallel pass (Mava's default)."""
    attention_block: int = 0
    """CMAT, MAT, PMAT, Triple-BERT: the encoder's self-attention over agents in blocks of this
    many agents (queries), one block at a time and recomputed in the backward pass, so its
    memory grows linearly in the number of agents at a fixed batch instead of quadratically;
    0 attends with all agents at once. The same result up to floating-point order, and the
    same parameters: a run may change it when resumed. Other attentions (compressors,
    decoder cross-attention) already scale linearly in n at a fixed m."""
    log_std_init: float = 1.0
    """Initial learned log-std of continuous heads; std = sigmoid(log_std) · 0.5, so 1 starts
    at std ≈ 0.37 (the reference MAT Decoder's `torch.ones(action_dim)`)."""


@dataclass(frozen=True)
class PPOConfig:
    """Single-agent PPO over the joint action (paper eq. cmat, eq. ratio)."""

    lr: float = 5e-4
    """Adam learning rate (the reference MAT's `lr`)."""
    adam_eps: float = 1e-5
    """Adam's epsilon (the reference MAT's `opti_eps`)."""
    epochs: int = 15
    """Passes over each update's batch (`ppo_epoch`)."""
    num_minibatches: int = 1
    """Minibatches each pass is split into (`num_mini_batch`); must divide
    num_envs × rollout_length."""
    minibatch_chunks: int = 1
    """Sequential slices each minibatch's gradient is computed in
    (`cmat.algorithms.sgd.minibatch_gradient`): k > 1 keeps the activations of one slice at a
    time, so the gradient is the same (up to floating-point order) at about 1/k of the
    activation memory. Without active masks the slices' gradients are averaged; with them the
    network pass is recomputed slice by slice for the backward pass. A memory knob for large
    minibatches (`benchmarks/throughput.py --preset mava`), faster there too; at small ones it
    costs time. Must divide the minibatch size."""
    clip_eps: float = 0.05
    """Clip range of the joint ratio and of the clipped value loss."""
    ent_coef: float = 0.01
    """Weight c_ent of the entropy bonus in the total loss (`entropy_coef`)."""
    value_coef: float = 1.0
    """Weight c_v of the value loss in the total loss (`value_loss_coef`)."""
    max_grad_norm: float = 10.0
    """Global gradient norm the gradients are clipped to before Adam (`max_grad_norm`)."""
    gamma: float = 0.99
    """Discount factor."""
    gae_lambda: float = 0.95
    """λ of generalised advantage estimation (GAE)."""
    target_tau: float = 0.1
    """Soft-update rate of the target critic phi- <- tau*phi + (1-tau)*phi- after each update
    (Algorithm 1). The paper gives no value; tau=1 is standard PPO (GAE and value targets from
    the critic that collected the data), the default of MAT, PMAT, MAPPO and HAPPO. 1, 0.1 and
    0.01 measured alike for CMAT on matrix:fig1 and SMAX 3m (benchmarks/target_tau.py)."""
    active_masks: bool = False
    """Leave inactive agents (`TimeStep.alive` False: dead, absent) out of the per-agent means
    of the policy loss and entropy, and out of advantage normalisation, as the reference MAT,
    MAPPO and HAPPO do (`use_policy_active_masks`). CMAT and Triple-BERT's joint ratio has no
    per-agent mean; with this option their entropy is averaged over active agents only."""
    value_active_masks: bool | None = None
    """Leave inactive agents out of the mean of a per-agent value loss (MAT's and PMAT's
    V(ô_i)); None: as `active_masks`. The reference MAT's SMAC script turns it off:
    `use_value_active_masks` is a store_false flag (default True) that
    `mat/scripts/train_smac.sh` passes, so every agent's value is regressed, dead ones too."""
    per_agent_gae: bool = False
    """MAT and PMAT only: GAE per agent on each agent's own V(ô_i), each V(ô_i) regressed on
    its own return (the reference MAT with value normalisation, mat/runner/shared/
    base_runner.py + utils/shared_buffer.py). False: one GAE on the team value
    V(O) = mean_i V(ô_i)."""
    value_norm: bool = True
    """Running mean/std normalisation of value targets (MAT's ValueNorm)."""
    huber_loss: bool = True
    """Huber value loss instead of the squared error (`use_huber_loss`)."""
    huber_delta: float = 10.0
    """δ of the Huber value loss (`huber_delta`)."""
    clipped_value_loss: bool = True
    """PPO's clipped value loss: the worse of the new value's error and that of the old value
    moved at most clip_eps (`use_clipped_value_loss`)."""
    normalize_advantages: bool = True
    """Normalise each update's advantages to zero mean and unit std."""
    joint_clip: str = "joint"
    """CMAT and Triple-BERT: 'joint' clips the joint ratio R = Π_i r_i to [1−ε, 1+ε] (paper
    eq. cmat); 'per_agent' clips it to [(1−ε)^k, (1+ε)^k] for the k active agents of the
    sample, i.e. holds the per-agent geometric mean R^(1/k) to [1−ε, 1+ε], so the per-agent trust
    region does not shrink as 1/n."""
    entropy_reduction: str = "mean"
    """CMAT and Triple-BERT: 'mean' over agents (the paper, as MAT) or 'sum' (the entropy of the
    joint policy Π_i π_i, which single-agent PPO on the joint action would regularise)."""
    target_kl: float | None = None
    """KL early stop (well-known PPO practice, e.g. CleanRL): after an epoch whose mean
    approximate KL (of the ratio the algorithm clips, measured on each minibatch before its
    step) exceeds this, the update's remaining epochs are skipped. None: every epoch runs (the
    paper, the references)."""
    consensus_ent_coef: float = 0.01
    """Stochastic consensus only: weight of the consensus policy's entropy bonus."""
    order_loss_coef: float = 1.0
    """PMAT only: weight of the clipped PPO term on the sampled agent order's log-probability."""
    order_in_loss: str = "sampled"
    """PMAT only: the decision order its loss decodes the stored actions along: 'sampled' (the
    order acting sampled them in, the paper's reading) or 'index' (the agents' index order, as
    the reference's training pass does)."""


@dataclass(frozen=True)
class TrainConfig:
    """One training run: environment, budget, seeds, network and PPO settings."""

    env: str = "matrix:fig1"
    """Environment id, PREFIX:NAME, of a suite in the registry (cmat.envs.suites;
    docs/suites.md): matrix:NAME, smax:SCENARIO, mpe:NAME, jumanji:TASK (RWARE, LBF),
    mabrax:TASK, dispatch:CITY-N-LEVEL (fleet dispatch) or a user's
    jax:package.module:factory (in-graph: a cmat MarlEnv or a JaxMARL MultiAgentEnv), a host
    environment (pettingzoo:package.module:factory, mamujoco:SCENARIO-CONF, grf:SCENARIO), or
    a suite an installed package adds."""
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Keyword arguments for the environment factory (e.g. payoff for matrix games)."""
    algo: str = "cmat"
    """One of the registry's algorithms (`cmat.algorithms.entries`): cmat, mat,
    pmat, triple_bert, happo, mappo, sable (the recurrent Sable), ff_sable."""
    total_steps: int = 200_000
    """Environment steps per seed (one step = one joint action in one environment)."""
    num_envs: int = 32
    """Parallel environments per seed (the reference's rollout threads)."""
    rollout_length: int = 100
    """Steps per environment between updates (the reference's episode length)."""
    seeds: int = 1
    """Independent seeds trained at once by vmap."""
    seed: int = 0
    """Base seed; seed s of a run uses seed + s."""
    log_interval: int | None = None
    """Updates between log rows, evaluations and checkpoints; None gives about 20 per run."""
    eval_episodes: int = 32
    """Evaluation episodes per seed at each log interval."""
    eval_actions: str = "greedy"
    """How evaluation acts: 'greedy', each agent's most likely action (MAT's protocol), or
    'sample', actions drawn from the policy as in training (Mava evaluates Sable so). Agents
    that see the same observation take the same greedy action: a fleet's vehicles in one zone
    can spread over its orders only by sampling (`cmat.envs.dispatch`)."""
    checkpoint_interval: int = 0
    """Env steps per seed between the periodic checkpoints kept beside `latest` and `best`
    (`checkpoints/step-N.ckpt`, written at the first chunk at or past each multiple); 0 keeps
    none."""
    keep_checkpoints: int = 5
    """How many periodic checkpoints to keep, the most recent (older ones are deleted as new
    ones are written); 0 keeps them all."""
    host_workers: int | None = None
    """Host environments only: worker processes that step them (0: in this process); None takes
    the suite's measured default (cmat.envs.host.DEFAULT_WORKERS)."""
    host_crash_limit: int = 3
    """Host environments only: crashes in a row of one environment (exceptions inside its
    simulator's reset or step) that stop the run; fewer restart it (cmat.envs.host.pool)."""
    host_nonfinite: str = "error"
    """Host environments only: a NaN or infinite observation, reward or state stops the run with
    a one-line error ('error'), or is replaced by 0 and counted in metrics.csv's `env_nonfinite`
    ('warn')."""
    finetune: str | None = None
    """None (joint training), or the paper's fine-tuning stage (Algorithm 1, B), CMAT only:
    'consensus' trains only Critic-MLP, decoder and Actor-Compressor; 'action' trains only
    Critic-MLP and Actor-MLP. The rest is frozen by an optimizer mask (`cmat finetune`)."""
    finetune_from: str | None = None
    """The run directory a fine-tuning run started from (recorded by `cmat finetune`)."""
    logger: str = "tensorboard"
    """Where scalars go besides metrics.csv: 'tensorboard' (the run's tb/), or 'wandb' (also
    Weights & Biases, the `wandb` extra). W&B runs offline, into the run's wandb/, unless the
    user asked for online logging (WANDB_MODE=online, or WANDB_API_KEY set); WANDB_PROJECT
    names the project (default cmat)."""
    preset: str | None = None
    """A named set of values the algorithm declares (its entry's `presets`), applied over its
    reference defaults and under `--config` / `--set`: 'paper' is the paper's exact settings
    (`cmat train --preset paper`); CMAT's 'tuned' names its default, the learning-speed
    study's configuration (docs/algorithms.md). None: the algorithm's defaults."""
    network: NetworkConfig = field(default_factory=NetworkConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.rollout_length

    @property
    def num_updates(self) -> int:
        """The run's budget in whole updates: `total_steps` rounded up to a multiple of
        `steps_per_update`. The one rounding rule: training, resume, `cmat eval` and the
        experiment runner all count a run as complete at exactly `budget_steps`."""
        return max(1, math.ceil(self.total_steps / self.steps_per_update))

    @property
    def budget_steps(self) -> int:
        """Env steps per seed a complete run has trained: `num_updates` whole updates."""
        return self.num_updates * self.steps_per_update

    @property
    def updates_per_log(self) -> int:
        return self.log_interval or max(1, self.num_updates // 20)


INT32_MAX = 2**31 - 1
"""The largest count a program can hold: JAX's integers are int32 unless x64 is enabled."""


def validate(config: TrainConfig) -> TrainConfig:
    """Reject values the trainer cannot run with, naming the field. What depends on the
    algorithm (its name, its fine-tuning stages, its options) is checked by
    `cmat.algorithms.check_config`."""
    net, ppo = config.network, config.ppo
    checks = [
        (config.total_steps > 0, f"steps must be > 0, got {config.total_steps}"),
        (config.seeds > 0, f"seeds must be > 0, got {config.seeds}"),
        (config.num_envs > 0, f"num_envs must be > 0, got {config.num_envs}"),
        (config.rollout_length > 0, f"rollout_length must be > 0, got {config.rollout_length}"),
        (config.eval_episodes > 0, f"eval_episodes must be > 0, got {config.eval_episodes}"),
        (config.checkpoint_interval >= 0,
         f"checkpoint_interval must be >= 0, got {config.checkpoint_interval}"),
        (config.keep_checkpoints >= 0,
         f"keep_checkpoints must be >= 0, got {config.keep_checkpoints}"),
        (config.eval_actions in EVAL_ACTIONS,
         f"eval_actions must be greedy or sample, got {config.eval_actions!r}"),
        (config.host_workers is None or config.host_workers >= 0,
         f"host_workers must be >= 0, got {config.host_workers}"),
        (config.host_crash_limit >= 1,
         f"host_crash_limit must be >= 1, got {config.host_crash_limit}"),
        (config.logger in LOGGERS,
         f"logger must be one of {', '.join(LOGGERS)}, got {config.logger!r}"),
        (config.host_nonfinite in NONFINITE_POLICIES,
         f"host_nonfinite must be error or warn, got {config.host_nonfinite!r}"),
        (config.log_interval is None or config.log_interval > 0,
         f"log_interval must be > 0, got {config.log_interval}"),
        (net.n_embd > 0 and net.n_head > 0 and net.n_embd % net.n_head == 0,
         f"network.n_embd ({net.n_embd}) must be divisible by network.n_head ({net.n_head})"),
        (net.n_block > 0, f"network.n_block must be > 0, got {net.n_block}"),
        (net.mlp_layers > 0, f"network.mlp_layers must be > 0, got {net.mlp_layers}"),
        (net.compressor_heads > 0,
         f"network.compressor_heads must be > 0, got {net.compressor_heads}"),
        (valid_iterations(net.consensus_iterations),
         f"network.consensus_iterations (m) must be >= 0, got {net.consensus_iterations!r} "
         f"(or one of {', '.join(ITERATION_RULES)}: relative to the number of agents n)"),
        (config.finetune is None or config.finetune in FINETUNE_MODES,
         f"finetune must be one of {', '.join(FINETUNE_MODES)}, got {config.finetune!r}"),
        (net.consensus_policy in CONSENSUS_POLICIES,
         f"network.consensus_policy must be one of {CONSENSUS_POLICIES}, "
         f"got {net.consensus_policy!r}"),
        (net.consensus_codes > 0,
         f"network.consensus_codes must be > 0, got {net.consensus_codes}"),
        (net.latent_head_gain > 0,
         f"network.latent_head_gain must be > 0, got {net.latent_head_gain}"),
        (net.consensus_source in CONSENSUS_SOURCES,
         f"network.consensus_source must be one of {CONSENSUS_SOURCES}, "
         f"got {net.consensus_source!r}"),
        (0.0 <= net.retention_decay <= 1.0,
         f"network.retention_decay must be in [0, 1], got {net.retention_decay}"),
        (net.retention_chunk is None or net.retention_chunk > 0,
         f"network.retention_chunk must be > 0 or null, got {net.retention_chunk}"),
        (config.algo != "sable" or ppo.num_minibatches <= 0
         or config.num_envs % ppo.num_minibatches == 0,
         f"Sable's minibatches are whole sequences: num_envs "
         f"({config.num_envs}) must be divisible by ppo.num_minibatches "
         f"({ppo.num_minibatches})"),
        (0 < ppo.clip_eps < 1, f"ppo.clip_eps must be in (0, 1), got {ppo.clip_eps}"),
        (config.steps_per_update > 1,
         f"num_envs * rollout_length must be at least 2, got {config.steps_per_update}: "
         f"advantages are normalised over an update's samples, which makes a single "
         f"sample's advantage 0 and stops learning"),
        (ppo.epochs > 0, f"ppo.epochs must be > 0, got {ppo.epochs}"),
        (ppo.num_minibatches > 0, f"ppo.num_minibatches must be > 0, got {ppo.num_minibatches}"),
        (ppo.num_minibatches <= 0 or config.steps_per_update % ppo.num_minibatches == 0,
         f"num_envs * rollout_length ({config.steps_per_update}) must be divisible by "
         f"ppo.num_minibatches ({ppo.num_minibatches})"),
        (ppo.minibatch_chunks > 0,
         f"ppo.minibatch_chunks must be > 0, got {ppo.minibatch_chunks}"),
        (ppo.num_minibatches <= 0 or ppo.minibatch_chunks <= 0
         or config.steps_per_update // ppo.num_minibatches % ppo.minibatch_chunks == 0,
         f"the minibatch size ({config.steps_per_update // max(ppo.num_minibatches, 1)}) must "
         f"be divisible by ppo.minibatch_chunks ({ppo.minibatch_chunks})"),
        (ppo.joint_clip in JOINT_CLIPS,
         f"ppo.joint_clip must be one of {', '.join(JOINT_CLIPS)}, got {ppo.joint_clip!r}"),
        (ppo.order_in_loss in LOSS_ORDERS,
         f"ppo.order_in_loss must be one of {', '.join(LOSS_ORDERS)}, got {ppo.order_in_loss!r}"),
        (ppo.entropy_reduction in ENTROPY_REDUCTIONS,
         f"ppo.entropy_reduction must be one of {', '.join(ENTROPY_REDUCTIONS)}, "
         f"got {ppo.entropy_reduction!r}"),
        (ppo.target_kl is None or (math.isfinite(ppo.target_kl) and ppo.target_kl > 0),
         f"ppo.target_kl must be > 0 or null, got {ppo.target_kl}"),
        (config.steps_per_update <= 0 or config.total_steps <= 0
         or max(config.budget_steps, config.steps_per_update * config.seeds) <= INT32_MAX,
         f"steps ({config.total_steps:,} per seed) and num_envs * rollout_length * seeds "
         f"({config.steps_per_update * config.seeds:,}) must each be at most {INT32_MAX:,}: "
         f"the trainer counts env steps in int32"),
    ]
    for ok, message in checks:
        if not ok:
            raise CmatError(f"invalid config: {message}")
    for name, value in numeric_fields(config):
        if isinstance(value, int) and not isinstance(value, bool) and abs(value) > INT32_MAX:
            raise CmatError(f"invalid config: {name} must be within ±{INT32_MAX:,} (JAX "
                            f"computes in int32), got {value:,}")
        if isinstance(value, float) and not math.isfinite(value):
            raise CmatError(f"invalid config: {name} must be a finite number, got {value}")
        low, high, closed_low = NUMERIC_RANGES.get(name, (None, None, True))
        too_low = low is not None and (value < low if closed_low else value <= low)
        if too_low or (high is not None and value > high):
            lower = "" if low is None else ("[" if closed_low else "(") + f"{low}, "
            upper = "inf)" if high is None else f"{high}]"
            raise CmatError(f"invalid config: {name} must be in {lower}{upper}, got {value}")
    return config


NUMERIC_RANGES: dict[str, tuple[float | None, float | None, bool]] = {
    "ppo.lr": (0.0, None, False),
    "ppo.adam_eps": (0.0, None, False),
    "ppo.clip_eps": (0.0, 1.0, False),
    "ppo.ent_coef": (0.0, None, True),
    "ppo.value_coef": (0.0, None, True),
    "ppo.max_grad_norm": (0.0, None, False),
    "ppo.gamma": (0.0, 1.0, True),
    "ppo.gae_lambda": (0.0, 1.0, True),
    "ppo.target_tau": (0.0, 1.0, False),
    "ppo.huber_delta": (0.0, None, False),
    "ppo.consensus_ent_coef": (0.0, None, True),
    "ppo.order_loss_coef": (0.0, None, True),
    "network.init_gain": (0.0, None, False),
    "network.latent_head_gain": (0.0, None, False),
    "network.attention_block": (0, None, True),
}
"""Allowed range of numeric fields not checked above: (low, high, low included); None is
unbounded. Every float field must also be finite."""


def numeric_fields(config: Any, prefix: str = "") -> list[tuple[str, float]]:
    """Every int and float field of a config dataclass, nested ones included, by dotted name."""
    found: list[tuple[str, float]] = []
    for item in fields(config):
        value = getattr(config, item.name)
        if is_dataclass(value):
            found += numeric_fields(value, f"{prefix}{item.name}.")
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            found.append((f"{prefix}{item.name}", value))
    return found


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
        raise CmatError(f"invalid config: network.consensus_iterations {m!r} is not an integer "
                        f"or one of {', '.join(ITERATION_RULES)}")
    numerator, denominator = ITERATION_RULES[rule]
    return num_agents * numerator // denominator


ConfigSources = dict[str, str]
"""Where each value of a config came from: dotted field name (`ppo.lr`; `env_kwargs` as one
field) -> 'default', 'suite NAME', 'algorithm NAME', 'preset NAME', 'file PATH',
'command line', or what else set it (`RunDir` writes them as comments in config.yaml)."""

NESTED_FIELDS = ("network", "ppo")
VERSION_HEADER = "# written by cmat "
"""The first line of a config.yaml: the version of cmat that wrote it (`written_by`)."""
LAYOUT_HEADER = "# config layout "
CONFIG_LAYOUT = 2
"""The layout of the config.yaml this version writes, on its second line (`LAYOUT_HEADER`).
Layout 1 (no such line; run directories written before 2026-12-06) chose Sable's variant with
`network.recurrent` (false: the feed-forward one); layout 2 names it by the algorithm, `sable`
(recurrent) or `ff_sable`. `upgrade` reads layout 1."""


def field_names() -> list[str]:
    """Every field of TrainConfig by dotted name (`ppo.lr`; `env_kwargs` as one field)."""
    return layer_fields(asdict(TrainConfig()))


def layer_fields(values: Any) -> list[str]:
    """The dotted field names a config layer (a nested mapping) sets."""
    if not isinstance(values, dict):
        return []
    names: list[str] = []
    for key, value in values.items():
        if key in NESTED_FIELDS and isinstance(value, dict):
            names += [f"{key}.{inner}" for inner in value]
        else:
            names.append(str(key))
    return names


def to_yaml(config: TrainConfig, sources: ConfigSources | None = None) -> str:
    """The config as YAML (read back by `from_yaml`); with `sources`, every value carries its
    source as a comment (`lr: 5.0e-05  # suite mamujoco`)."""
    from cmat.version import __version__

    header = f"{VERSION_HEADER}{__version__}\n{LAYOUT_HEADER}{CONFIG_LAYOUT}\n"
    if sources is None:
        dumped: str = yaml.safe_dump(asdict(config), sort_keys=False)
        return header + dumped
    lines = [
        *header.splitlines(),
        "# Resolved run config. Each value's comment says where it came from: default (the",
        "# dataclasses in cmat/config.py), suite (cmat/envs/suites.py), algorithm (its",
        "# reference_defaults), preset, file, command line.",
    ]
    for key, value in asdict(config).items():
        if key in NESTED_FIELDS:
            lines.append(f"{key}:")
            lines += [source_line(f"  {inner}", item, sources.get(f"{key}.{inner}"))
                      for inner, item in value.items()]
        else:
            lines.append(source_line(key, value, sources.get(key)))
    return "\n".join(lines) + "\n"


@functools.cache
def field_docs() -> dict[str, str]:
    """Every config field's docstring (the string literal after it in this module's
    dataclasses) by dotted name, `ppo.lr` for the nested ones; what `cmat config` prints."""
    sections = {"NetworkConfig": "network.", "PPOConfig": "ppo.", "TrainConfig": ""}
    docs: dict[str, str] = {}
    for node in ast.parse(Path(__file__).read_text()).body:
        if not isinstance(node, ast.ClassDef) or node.name not in sections:
            continue
        for field_node, after in zip(node.body, node.body[1:]):
            if (isinstance(field_node, ast.AnnAssign) and isinstance(field_node.target, ast.Name)
                    and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                    and isinstance(after.value.value, str)):
                docs[sections[node.name] + field_node.target.id] = " ".join(
                    after.value.value.split()
                )
    return docs


def source_line(key: str, value: Any, source: str | None) -> str:
    text = yaml.safe_dump(value, default_flow_style=True, width=1 << 30)
    text = text.removesuffix("\n...\n").rstrip("\n")
    return f"{key}: {text}" + (f"  # {source}" if source else "")


def read_sources(text: str) -> ConfigSources:
    """The sources written by `to_yaml` into a config.yaml (empty for one written without)."""
    sources: ConfigSources = {}
    section = ""
    for line in text.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        indented = line.startswith(" ")
        key, _, rest = line.strip().partition(":")
        if not indented:
            section = key if not rest.strip() else ""
        value, marker, source = rest.rpartition("  # ")
        if marker and value.strip():
            sources[f"{section}.{key}" if indented and section else key] = source.strip()
    return sources


def written_by(text: str) -> str | None:
    """The cmat version named in a config.yaml's first line (None: written before 0.1.0
    recorded it)."""
    first = text.partition("\n")[0]
    return first.removeprefix(VERSION_HEADER).strip() if first.startswith(VERSION_HEADER) else None


class UniqueKeyLoader(yaml.SafeLoader):  # type: ignore[misc]  # yaml has no stubs here
    """PyYAML's safe loader, except that a key given twice in one mapping is an error (PyYAML
    keeps the last value silently, so a config or spec would lose the first setting unseen)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} appears twice in one mapping (line "
                    f"{key_node.start_mark.line + 1})", key_node.start_mark)
            seen.add(key)
        mapping: dict[Any, Any] = super().construct_mapping(node, deep=deep)
        return mapping


def load_yaml(text: str) -> Any:
    """Parse YAML `text` with `UniqueKeyLoader`; raises yaml.YAMLError."""
    return yaml.load(text, Loader=UniqueKeyLoader)


def layout(text: str) -> int:
    """The layout of a config.yaml (`CONFIG_LAYOUT`): its `LAYOUT_HEADER` line's, else 1."""
    for line in text.splitlines()[:2]:
        if line.startswith(LAYOUT_HEADER) and line.removeprefix(LAYOUT_HEADER).isdigit():
            return int(line.removeprefix(LAYOUT_HEADER))
    return 1


def upgrade(loaded: Any, written_in: int) -> Any:
    """A config mapping of layout `written_in` in today's layout (`CONFIG_LAYOUT`); raises
    CmatError for a layout newer than this version reads."""
    if written_in > CONFIG_LAYOUT:
        raise CmatError(f"config layout {written_in} is newer than this cmat reads "
                        f"({CONFIG_LAYOUT}); update cmat")
    if written_in == 1 and isinstance(loaded, dict) and isinstance(loaded.get("network"), dict):
        network = {k: v for k, v in loaded["network"].items() if k != "recurrent"}
        algo = loaded.get("algo")
        if algo == "sable" and not loaded["network"].get("recurrent", False):
            algo = "ff_sable"
        loaded = {**loaded, "algo": algo, "network": network}
    return loaded


def from_yaml(text: str) -> TrainConfig:
    """Read a resolved config written by `to_yaml` (a run directory's config.yaml), of any
    layout (`upgrade`)."""
    try:
        loaded = upgrade(load_yaml(text), layout(text))
        config = OmegaConf.to_object(
            OmegaConf.merge(OmegaConf.structured(TrainConfig), OmegaConf.create(loaded))
        )
    except (yaml.YAMLError, OmegaConfBaseException, ValueError) as error:
        raise CmatError(f"unreadable run config: {one_line(error)}") from None
    assert isinstance(config, TrainConfig)
    return validate(config)


def one_line(error: BaseException) -> str:
    """The first line of an exception message (OmegaConf appends a multi-line context)."""
    text = str(error).strip().splitlines()
    return text[0] if text else type(error).__name__
