"""Typed run configuration: dataclass defaults, overridden by a YAML file, then by `key=value`.

Defaults are the reference MAT hyper-parameters for SMAC (the reference MAT implementation's
SMAC train scripts) except where a field's docstring says otherwise. The sections here are those
every algorithm reads; each algorithm's own is an `AlgorithmOptions` subclass in its package's
`options.py`. OmegaConf merges and type-checks the layers (`cmat.resolve`); the result is
converted back to these frozen dataclasses, so a typo or a wrong type fails before any tracing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any, ClassVar

import yaml

from cmat.errors import CmatError

FINETUNE_MODES = ("consensus", "action")
LOGGERS = ("tensorboard", "wandb")
NONFINITE_POLICIES = ("error", "warn")
"""What a host environment does with a NaN or infinite observation, reward or state
(`TrainConfig.host_nonfinite`): stop the run with a one-line error, or replace the values by 0
and count them (`metrics.csv` column `env_nonfinite`)."""
HOST_EPISODES = 100_000
"""The most episodes `cmat eval` plays at once on the host (the dispatch baselines and matched
decoding, `cmat.envs.dispatch.baselines.rollout`: one batch in the host's memory)."""

EVAL_ACTIONS = ("greedy", "sample")
"""How evaluation acts (`TrainConfig.eval_actions`)."""

@dataclass(frozen=True)
class NetworkConfig:
    """Network sizes every algorithm shares (paper Sec. Network Architecture); what only one
    algorithm's network has is in its own section (`AlgorithmOptions`). Each algorithm reads the
    fields its entry lists in `network_fields` (MAPPO and HAPPO read `n_embd` as their MLPs'
    width); `cmat config --algo NAME` marks the fields it does not."""

    n_embd: int = 64
    """Hidden size d of every block."""
    n_head: int = 1
    """Attention heads; must divide n_embd."""
    n_block: int = 1
    """Transformer blocks in the encoder and in the decoder."""
    init_gain: float = 0.01
    """Orthogonal-init gain of the reference MAT's small layers (`init_(…)` without
    `activate`, mat/algorithms/mat/algorithm/ma_transformer.py): the action and value output
    layers, the query, key, value and output projections of every attention and the second
    layer of every feed-forward block. Layers followed by an activation keep the ReLU gain √2."""
    log_std_init: float = 1.0
    """Initial learned log-std of continuous heads; std = sigmoid(log_std) · 0.5, so 1 starts
    at std ≈ 0.37 (the reference MAT Decoder's `torch.ones(action_dim)`)."""


@dataclass(frozen=True)
class PPOConfig:
    """The PPO settings every algorithm reads (paper eq. cmat, eq. ratio; the reference MAT's
    names in parentheses); an algorithm's own loss options are in its section
    (`AlgorithmOptions`)."""

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
    target_kl: float | None = None
    """KL early stop (well-known PPO practice, e.g. CleanRL): after an epoch whose mean
    approximate KL (of the ratio the algorithm clips, measured on each minibatch before its
    step) exceeds this, the update's remaining epochs are skipped. None: every epoch runs (the
    paper, the references)."""


@dataclass(frozen=True)
class AlgorithmOptions:
    """The run config's section of the chosen algorithm: its network's and its loss's own
    options, nothing another algorithm reads. Each algorithm package declares a frozen
    subclass (its entry's `options`; `cmat.algorithms.cmat.options.CMATOptions`, …) whose
    fields carry defaults and docstrings as here; this base has none (an algorithm without
    options of its own). In a config file and on the command line the section is named by the
    algorithm (`cmat.consensus_iterations`, `--set sable.retention_chunk=16`); in Python it is
    `TrainConfig.options`."""

    network_options: ClassVar[tuple[str, ...]] = ()
    """The fields that shape the network's parameters: recorded with each checkpoint, fixed
    for a fine-tuning run (the others, loss options and how the network computes, may
    change)."""

    def checks(self, section: str, config: TrainConfig) -> list[tuple[bool, str]]:
        """(holds, message) for each rule of these options (`validate` raises the first that
        fails); `section` is the name the messages give the section (the algorithm's). A
        subclass extends its bases' list (`super().checks`)."""
        return []


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
    options: AlgorithmOptions = field(default_factory=AlgorithmOptions)
    """The algorithm's section (its entry's `options` class); the base `AlgorithmOptions()`
    stands for the algorithm's defaults until `cmat.algorithms.check_config` fills them in."""

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
        (config.finetune is None or config.finetune in FINETUNE_MODES,
         f"finetune must be one of {', '.join(FINETUNE_MODES)}, got {config.finetune!r}"),
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
        (ppo.target_kl is None or (math.isfinite(ppo.target_kl) and ppo.target_kl > 0),
         f"ppo.target_kl must be > 0 or null, got {ppo.target_kl}"),
        (config.steps_per_update <= 0 or config.total_steps <= 0
         or max(config.budget_steps, config.steps_per_update * config.seeds) <= INT32_MAX,
         f"steps ({config.total_steps:,} per seed) and num_envs * rollout_length * seeds "
         f"({config.steps_per_update * config.seeds:,}) must each be at most {INT32_MAX:,}: "
         f"the trainer counts env steps in int32"),
        *config.options.checks(config.algo, config),
    ]
    for ok, message in checks:
        if not ok:
            raise CmatError(f"invalid config: {message}")
    for name, value in numeric_fields(config):
        if name.startswith("options."):
            name = f"{config.algo}.{name.removeprefix('options.')}"
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
    "network.init_gain": (0.0, None, False),
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


ConfigSources = dict[str, str]
"""Where each value of a config came from: dotted field name (`ppo.lr`,
`cmat.consensus_iterations` for the algorithm's section; `env_kwargs` as one field) ->
'default', 'suite NAME', 'algorithm NAME', 'preset NAME', 'file PATH', 'command line', or what
else set it (`cmat.configfile.to_yaml` writes them as comments in config.yaml)."""

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


def one_line(error: BaseException) -> str:
    """The first line of an exception message (OmegaConf appends a multi-line context)."""
    text = str(error).strip().splitlines()
    return text[0] if text else type(error).__name__
