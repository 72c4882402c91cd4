"""The Python API: what the command line does, as functions and a `Run`.

    import cmat

    run = cmat.train(env="smax:3m", algo="cmat", steps=300_000, seeds=3, out="runs/3m",
                     num_envs=8, ppo={"lr": 1e-4})
    run.metrics                 # metrics.csv as a DataFrame: one row per seed, kind and chunk
    run.config                  # the resolved TrainConfig (config.yaml)
    run.evaluate(episodes=100)  # fresh evaluation episodes: a DataFrame, one row per seed
    policy = run.policy()       # cmat.Policy, to act in your own loop
    report = cmat.experiment("dispatch", out="runs/dispatch")

`train` resolves its config through the same layers as `cmat train` (cmat.resolve: defaults,
suite, algorithm, its task values, preset, YAML file, then the keyword arguments) and runs the
same checks; every user error is a `CmatError` carrying the one line the CLI prints. The CLI
(cmat.cli) is a thin layer over this module. Importing it imports no JAX; training does.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import sys
import time
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cmat.algorithms.cmat.options import CMATOptions
from cmat.config import (
    EVAL_ACTIONS,
    HOST_EPISODES,
    INT32_MAX,
    ConfigSources,
    TrainConfig,
    validate,
)
from cmat.errors import CmatError
from cmat.resolve import resolve_config
from cmat.rundir import Checkpoint, RunDir
from cmat.runners import distributed
from cmat.runners.loop import resume_is_complete, run_training

if TYPE_CHECKING:
    import pandas as pd

    from cmat.experiments.plan import Plan
    from cmat.policy import Policy
    from cmat.runners.base import Trainer, TrainerState

PathArg = str | PathLike[str]


@dataclass(frozen=True)
class Run:
    """A run directory (written by `train`, `cmat train` or an experiment grid) and what can be
    read and done with it. `Run(path)` reads nothing until asked; `open_run` checks it."""

    path: Path

    @property
    def config(self) -> TrainConfig:
        """The run's resolved config (config.yaml). Raises CmatError if it is unreadable."""
        return RunDir(self.path).config()

    @property
    def sources(self) -> ConfigSources:
        """Where each config value came from (`ppo.lr` -> `algorithm cmat`, ...)."""
        return RunDir(self.path).sources()

    @property
    def metrics(self) -> pd.DataFrame:
        """metrics.csv: one row per seed, kind (`train` or `eval`) and chunk; columns `kind`,
        `seed`, `env_steps`, `episode_return`, `win_rate`, the losses and diagnostics, the
        algorithm's and the environment's own metrics (numbers, NaN where a row has none)."""
        import pandas as pd

        frame = pd.DataFrame(RunDir(self.path).read_metrics(),
                             columns=RunDir(self.path).metrics_header() or None)
        numeric = [column for column in frame.columns if column != "kind"]
        frame[numeric] = frame[numeric].apply(pd.to_numeric, errors="coerce")
        for column in ("seed", "env_steps"):
            if column in frame:
                frame[column] = frame[column].astype("int64")
        return frame

    @property
    def env_steps(self) -> int:
        """Env steps per seed of the latest checkpoint."""
        return RunDir(self.path).checkpoint_steps()[0]

    @property
    def complete(self) -> bool:
        """Whether the run has trained its whole budget."""
        return self.env_steps == self.config.budget_steps

    def evaluate(
        self,
        episodes: int | None = None,
        actions: str | None = None,
        seed: int = 0,
        iterations: int | None = None,
        checkpoint: Checkpoint = "latest",
    ) -> pd.DataFrame:
        """`cmat eval`: evaluate the latest checkpoint on `episodes` fresh episodes per seed
        (default the run's `eval_episodes`), acting `greedy` or `sample` (default the run's
        `eval_actions`) or, on a dispatch task, `matched` (the policy's most likely claims in
        which no order goes to two vehicles, `cmat.envs.dispatch.matched`); `seed` picks the
        episodes (docs/evaluation.md); `iterations` runs a CMAT decoder for fewer consensus
        iterations than it was trained with; `checkpoint` is `latest`, `best` or the env steps
        of a kept periodic one.

        Returns one row per trained seed (`seed` and the evaluation metrics: `episode_return`,
        `win_rate`, environment metrics); `frame.attrs` holds what `cmat eval` prints beside
        them (env_steps, complete, episodes_per_seed, actions, episode_seed, ...).
        Raises CmatError for an argument out of range or an unreadable run."""
        import pandas as pd

        extra, per_seed = evaluate_run(RunDir.open(self.path), episodes, actions, seed,
                                       iterations, checkpoint)
        frame = pd.DataFrame(per_seed).astype(float).astype({"seed": "int64"})
        frame.attrs.update(extra)
        return frame

    def policy(self, seed: int | None = None, checkpoint: Checkpoint = "latest") -> Policy:
        """One seed's trained policy (default the run's first seed) from `checkpoint`:
        `cmat.load_policy`."""
        from cmat.policy import load_policy

        return load_policy(self.path, seed, checkpoint)

    @property
    def checkpoints(self) -> list[Checkpoint]:
        """The checkpoints the run keeps: latest, best, then periodic ones by env steps."""
        return RunDir(self.path).checkpoints()

    def resume(self, steps: int | None = None) -> Run:
        """`cmat train --resume`: continue training to the run's budget (or to `steps` per
        seed); returns this run."""
        return train(resume=self.path, steps=steps)

    def plot(self, out: PathArg, diagnostics: bool = False) -> Path:
        """`cmat plot`: the evaluation curves (or, with `diagnostics`, the per-update
        diagnostics) of this run into the image `out`; returns its path."""
        from cmat.plots import plot_diagnostics, plot_runs

        (plot_diagnostics if diagnostics else plot_runs)([self.path], Path(out))
        return Path(out)


def open_run(path: PathArg) -> Run:
    """The run in directory `path`. Raises CmatError if it holds no run."""
    return Run(RunDir.open(Path(path)).path)


def train(
    env: str | None = None,
    algo: str | None = None,
    *,
    steps: int | None = None,
    seeds: int | None = None,
    preset: str | None = None,
    config: PathArg | None = None,
    out: PathArg | None = None,
    resume: PathArg | None = None,
    **settings: Any,
) -> Run:
    """`cmat train`: train `algo` (default cmat) on `env` (default matrix:fig1) for `steps` env
    steps per seed with `seeds` seeds at once, into the run directory `out` (default
    runs/ENV-TIMESTAMP); returns the `Run`.

    `preset` names a setting of the algorithm (`paper`), `config` a YAML file, and `settings`
    any other config field, later layers winning: `num_envs=8`, `ppo={"lr": 1e-4}` or
    `**{"network.n_embd": 32}` (`cmat config` lists every field). `resume` continues the run in
    that directory instead; only `steps` may be given with it.

    Raises CmatError for every problem `cmat train` reports (an unknown environment, field or
    preset, a value out of range, an `out` that already holds a run); a new run that fails
    before its first chunk is written leaves no directory behind."""
    if resume is not None:
        if any(value is not None for value in (env, algo, seeds, preset, config, out)) or settings:
            raise CmatError("resume takes no other option than steps")
        run_dir = RunDir.open(Path(resume))
        run_dir.refuse_saved_policy()
        resumed = run_dir.config()
        if steps is not None:
            resumed = validate(dataclasses.replace(resumed, total_steps=steps))
        if not resume_is_complete(resumed, run_dir, run_dir.recorded_steps()):
            trainer = distributed_trainer(resumed)
            if distributed.is_follower():
                distributed.follow(trainer, run_dir.sources(), run_dir.path, resume=True)
            else:
                train_into(trainer, run_dir, resume=True)
        return Run(run_dir.path)
    flags = {"env": env, "algo": algo, "total_steps": steps, "seeds": seeds, "preset": preset}
    values = {**{key: value for key, value in flags.items() if value is not None}, **settings}
    resolved, sources = resolve_config(None if config is None else Path(config),
                                       values=values)
    return start_run(resolved, sources, None if out is None else Path(out))


def start_run(config: TrainConfig, sources: ConfigSources, out: Path | None) -> Run:
    """Build the trainer of `config`, create the run directory (`out`, or a new one under
    runs/) once its environment has reset, and train it to its budget."""
    trainer = distributed_trainer(config)
    if distributed.active():
        if out is None:
            raise CmatError("a run of several processes needs --out DIR (out=): the directory "
                            "process 0 writes, named the same in every process")
        if distributed.is_follower():
            print(f"cmat: {distributed.describe()}: process 0 writes the run {out}", flush=True)
            distributed.follow(trainer, sources, Path(out), resume=False)
            return Run(Path(out))
    if out is not None:
        out = RunDir.check_free(out).path
    print(budget_note(config, sources["total_steps"]), flush=True)
    start = trainer.init()  # an environment that fails at reset leaves no run directory
    run_dir = (RunDir.create_named(default_out(config), config, sources) if out is None
               else RunDir.create(out, config, sources))
    train_into(trainer, run_dir, resume=False, start=start)
    return Run(run_dir.path)


def experiment(
    spec: PathArg,
    out: PathArg | None = None,
    parallel: int | None = None,
    only: list[str] | None = None,
    report_only: bool = False,
    seeds_per_run: int | None = None,
) -> Experiment:
    """`cmat experiment`: run what is missing of the grid in `spec` (a YAML file, or the name
    of a spec shipped in cmat/experiments/specs, e.g. `dispatch`) in `out` (default
    runs/experiments/SPEC_NAME), `parallel` runs at once, only the runs matching the shell
    patterns `only`, or none with `report_only`, the seeds without a run on disk grouped
    `seeds_per_run` to a run (default: the spec's); then write its report. Returns the
    `Experiment`.

    Raises CmatError for a bad spec or directory, and after reporting, if runs failed."""
    from cmat.experiments.runner import run_experiment

    plan = run_experiment(Path(spec), out=None if out is None else Path(out),
                          parallel=parallel, only=only, report_only=report_only,
                          seeds_per_run=seeds_per_run)
    return Experiment(plan.out, plan)


@dataclass(frozen=True)
class Experiment:
    """An experiment directory after `experiment`: its report and its runs."""

    path: Path
    plan: Plan
    """The grid: `plan.runs` (name, path, status and outcome of every run)."""

    @property
    def report(self) -> Path:
        """results.md: scores, aggregate statistics, tables, figures."""
        return self.path / "results.md"

    @property
    def results(self) -> dict[str, Any]:
        """results.json: the numbers of results.md."""
        loaded: dict[str, Any] = json.loads((self.path / "results.json").read_text())
        return loaded

    @property
    def runs(self) -> dict[str, Run]:
        """Every complete run of the grid by name (`ENV/VARIANT/ALGO-sFIRST-LAST`)."""
        from cmat.experiments.plan import FINISHED

        return {run.name: Run(run.path) for run in self.plan.runs if run.status == FINISHED}


def evaluate_run(
    run_dir: RunDir,
    episodes: int | None,
    actions: str | None,
    episode_seed: int,
    iterations: int | None,
    checkpoint: Checkpoint = "latest",
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """`cmat eval` of `run_dir`'s checkpoint: what it reports beside the metrics, and a row per
    seed (`seed` and each metric, NaN as None). Raises CmatError for an argument out of
    range."""
    if not 0 <= episode_seed <= INT32_MAX:
        raise CmatError(f"--seed must be in [0, {INT32_MAX:,}], got {episode_seed:,}")
    config = run_dir.config()
    saved = saved_policy(run_dir, checkpoint)
    if saved is not None:
        config = dataclasses.replace(saved.config, seed=saved.seed, seeds=1)
    if actions is not None:
        if actions not in (*EVAL_ACTIONS, MATCHED):
            raise CmatError(f"actions must be 'greedy', 'sample' or 'matched', got {actions!r}")
        if actions != MATCHED:
            config = dataclasses.replace(config, eval_actions=actions)
    if episodes is not None and not 0 < episodes <= INT32_MAX:
        raise CmatError(f"--episodes must be in [1, {INT32_MAX:,}], got {episodes:,}")
    if iterations is not None and config.algo != "cmat":
        raise CmatError(f"--iterations applies to cmat runs only; {run_dir.path} is a "
                        f"{config.algo!r} run")
    if actions == MATCHED:
        return evaluate_matched_run(run_dir, config, episodes, episode_seed, iterations,
                                    checkpoint)
    from cmat.runners.base import restore_run

    trainer = build_trainer(config)
    if saved is None:
        state, env_steps = restore_run(run_dir, trainer, checkpoint)
    else:
        import jax

        differs = [field.name for field in dataclasses.fields(saved.spec)
                   if getattr(trainer.env_spec, field.name) != getattr(saved.spec, field.name)]
        if differs:
            name = differs[0]
            raise CmatError(f"{run_dir.path}: its config.yaml builds an environment with "
                            f"{name} {getattr(trainer.env_spec, name)!r}, and the saved "
                            f"parameters act on {name} {getattr(saved.spec, name)!r}")
        state, env_steps = trainer.init(), saved.env_steps
        params = jax.tree.map(lambda leaf: leaf[None], saved.params)
        state = dataclasses.replace(state, learner=dataclasses.replace(state.learner,
                                                                       params=params))
    extra: dict[str, Any] = {
        "checkpoint": checkpoint if saved is None else "saved policy", "env_steps": env_steps,
        "budget_steps": config.budget_steps, "complete": env_steps == config.budget_steps,
    }
    if checkpoint == "best":
        extra["best_env_steps"] = (run_dir.checkpoint_header("best") or {})["best"]["env_steps"]
    if isinstance(config.options, CMATOptions):
        trained = config.options.iterations(trainer.env_spec.num_agents)
        extra["consensus_iterations"] = trained
        if iterations is not None:
            trainer, state = with_eval_iterations(config, state, trained, iterations)
            extra["consensus_iterations"] = iterations
    episodes = episodes or config.eval_episodes
    extra["episodes_per_seed"] = episodes
    extra["actions"] = config.eval_actions
    extra["episode_seed"] = episode_seed
    result = trainer.evaluate(state, episodes, episode_seed=episode_seed)
    per_seed = [
        {"seed": config.seed + index,
         **{name: json_number(values[index]) for name, values in result.items()}}
        for index in range(config.seeds)
    ]
    return extra, per_seed


def saved_policy(run_dir: RunDir, checkpoint: Checkpoint) -> Policy | None:
    """The policy `run_dir` holds where it is one saved by `Policy.save` (`cmat export`), which
    `cmat eval` evaluates as a run of its one seed; None for a run directory. CmatError for a
    `checkpoint` other than the default, which only a run directory has to choose from."""
    from cmat.policy import load_policy

    return load_policy(run_dir.path, checkpoint=checkpoint) if run_dir.is_saved_policy else None


MATCHED = "matched"
"""`cmat eval --actions matched`: a dispatch run's policy decoded into conflict-free claims
(`cmat.envs.dispatch.matched`)."""


def evaluate_matched_run(
    run_dir: RunDir, config: TrainConfig, episodes: int | None, episode_seed: int,
    iterations: int | None, checkpoint: Checkpoint,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """`evaluate_run` with `--actions matched`: every seed's policy on the episodes the dispatch
    baselines play with `episode_seed` (`cmat.envs.dispatch.baselines.rollout`), each step's
    claims matched (`cmat.envs.dispatch.matched.matched_plan`)."""
    if not config.env.startswith("dispatch:"):
        raise CmatError(f"--actions matched applies to dispatch tasks (vehicles matched to "
                        f"orders), not {config.env}")
    if iterations is not None:
        raise CmatError("--iterations does not combine with --actions matched")
    if episodes is not None and episodes > HOST_EPISODES:
        raise CmatError(f"--episodes must be in [1, {HOST_EPISODES:,}] with --actions matched, "
                        f"got {episodes:,}")
    from cmat.envs.dispatch.baselines import baseline_env, means
    from cmat.envs.dispatch.matched import evaluate_matched
    from cmat.policy import load_policy

    env = baseline_env(config.env, config.env_kwargs)
    episodes = episodes or config.eval_episodes
    policies = [load_policy(run_dir.path, seed=seed, checkpoint=checkpoint)
                for seed in range(config.seed, config.seed + config.seeds)]
    per_seed = []
    for policy in policies:
        figures = means(evaluate_matched(env, policy.log_probs, episodes, episode_seed))
        per_seed.append({"seed": policy.seed,
                         **{name: json_number(value) for name, value in figures.items()}})
    extra = {"checkpoint": "saved policy" if run_dir.is_saved_policy else checkpoint,
             "env_steps": policies[0].env_steps,
             "budget_steps": config.budget_steps, "complete": policies[0].complete,
             "episodes_per_seed": episodes, "actions": MATCHED, "episode_seed": episode_seed}
    return extra, per_seed


def with_eval_iterations(
    config: TrainConfig, state: TrainerState, trained: int, iterations: int
) -> tuple[Trainer, TrainerState]:
    """A trainer whose network runs `iterations` consensus iterations, and `state` with the
    decoder's positional table cut to them. Positions past the trained m were never learned, so
    asking for more is an error rather than an extrapolation."""
    from cmat.algorithms.cmat.blocks import with_iterations

    if not 0 <= iterations <= trained:
        raise CmatError(
            f"--iterations must be in 0..{trained} (the m this run was trained with: the decoder "
            f"has positional embeddings for {trained} iterations); got {iterations}. "
            f"Train with a larger cmat.consensus_iterations to evaluate more"
        )
    assert isinstance(config.options, CMATOptions)
    options = dataclasses.replace(config.options, consensus_iterations=iterations)
    eval_trainer = build_trainer(dataclasses.replace(config, options=options))
    learner = dataclasses.replace(
        state.learner, params=with_iterations(state.learner.params, iterations)
    )
    return eval_trainer, dataclasses.replace(state, learner=learner)


def budget_note(config: TrainConfig, source: str) -> str:
    """The line a new run starts with: the env steps each seed trains and where that budget
    comes from, and the rounding where the budget is not whole updates."""
    note = (f"training {config.budget_steps:,} env steps per seed ({config.seeds} seed"
            f"{'' if config.seeds == 1 else 's'}); total_steps {config.total_steps:,} from "
            f"{source}")
    if config.budget_steps != config.total_steps:
        note += (f", rounded up to whole updates of num_envs × rollout_length = "
                 f"{config.steps_per_update:,} steps")
    return note


def train_into(
    trainer: Trainer, run_dir: RunDir, resume: bool, start: TrainerState | None = None
) -> None:
    """`run_training`, telling the user how to continue if they interrupt it. A new run that
    stops on a CmatError or an interrupt before its first chunk is written (an environment that
    fails at its first steps, a non-finite first update, Ctrl-C during the first compile)
    leaves no directory behind: this process made it and it holds nothing but the config and
    the initial checkpoint."""
    try:
        with distributed.peer_failures(run_dir.path):
            run_training(trainer, run_dir, resume=resume, start=start)
    except (CmatError, OSError) as error:
        message = (f"cannot write {error.filename}: {error.strerror}"
                   if isinstance(error, OSError) and error.filename else str(error))
        if resume or run_dir.metrics_path.exists():
            if isinstance(error, OSError):
                raise CmatError(f"{message}; the run keeps its last checkpoint: continue with "
                                f"cmat train --resume {run_dir.path}") from None
            raise
        shutil.rmtree(run_dir.path, ignore_errors=True)
        raise CmatError(f"{message}; the new run directory {run_dir.path} was removed") from None
    except KeyboardInterrupt:
        if resume or run_dir.metrics_path.exists():
            print(f"cmat: stopped at the last checkpoint; continue with: "
                  f"cmat train --resume {run_dir.path}", file=sys.stderr)
        else:
            shutil.rmtree(run_dir.path, ignore_errors=True)
            print(f"cmat: stopped before the first update was saved; the new run directory "
                  f"{run_dir.path} was removed", file=sys.stderr)
        raise
    print(f"run directory: {run_dir.path}")


def build_trainer(config: TrainConfig) -> Trainer:
    """The trainer for `config` (`HostTrainer` for host environments, `JaxTrainer` for the
    others); JAX is imported here, after the log level is set."""
    from cmat.runners import build_trainer as build

    return build(config)


def distributed_trainer(config: TrainConfig) -> Trainer:
    """`build_trainer`; CmatError where this process is one of several
    (cmat.runners.distributed) and `config`'s environment runs on the host."""
    from cmat.envs.host import is_host_env

    if distributed.active() and is_host_env(config.env):
        raise CmatError(f"a run of several processes needs an in-graph environment; "
                        f"{config.env} runs on the host")
    return build_trainer(config)


def default_out(config: TrainConfig) -> Path:
    """runs/ENV[-finetune-MODE]-TIMESTAMP (`RunDir.create_named` adds -2, -3, ... if taken)."""
    stage = f"-finetune-{config.finetune}" if config.finetune else ""
    return Path("runs") / f"{config.env.replace(':', '_')}{stage}-{time.strftime('%Y%m%d-%H%M%S')}"


def json_number(value: float) -> float | None:
    return None if math.isnan(value) else float(value)
