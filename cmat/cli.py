"""Command line: `cmat train`, `cmat finetune`, `cmat eval`, `cmat render`, `cmat plot`,
`cmat config`, `cmat experiment`.

Every user error (CmatError, an unreadable file) is one line `cmat: error: ...` on stderr and
exit code 2, as argparse does for usage errors.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import textwrap
import time
from pathlib import Path
from typing import NoReturn

from cmat.algorithms import algorithm_entry, algorithm_names
from cmat.api import (
    budget_note,
    build_trainer,
    default_out,
    evaluate_run,
    json_number,
    start_run,
    train,
    train_into,
)
from cmat.config import FINETUNE_MODES, HOST_EPISODES, INT32_MAX, TrainConfig, validate
from cmat.configfile import field_docs, field_names, to_mapping, to_yaml
from cmat.envs import probe_env
from cmat.envs.suites import registry, suite_of
from cmat.errors import CmatError
from cmat.plots import plot_diagnostics, plot_runs
from cmat.resolve import explain, load_config, resolve_config
from cmat.rundir import RunDir, parse_checkpoint
from cmat.runners import distributed
from cmat.version import __version__


class Parser(argparse.ArgumentParser):
    """argparse with its usage errors on one line, as every other error of the CLI, pointing
    to the command's --help instead of printing the usage first (exit code 2, as argparse's)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"cmat: error: {message} (see `{self.prog} --help`)\n")


CHECKPOINT_HELP = ("which checkpoint: latest (default), best (each seed's parameters at its best "
                   "evaluation) or the env steps of a kept periodic one")


def checkpoint_argument(text: str) -> str | int:
    """`--checkpoint`'s value (`parse_checkpoint`), a usage error where it names none."""
    try:
        return parse_checkpoint(text)
    except CmatError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="cmat", description="Consensus Multi-Agent Transformer: train, evaluate, plot."
    )
    parser.add_argument("--version", action="version", version=f"cmat {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)

    train = commands.add_parser("train", help="train a new run or resume one")
    train.add_argument("--env", help="environment id: "
                       + ", ".join(suite.ids for suite in registry().values())
                       + "; default matrix:fig1, the paper's Fig. 1 game, which trains in "
                         "seconds")
    train.add_argument("--algo", help=f"algorithm: {', '.join(algorithm_names())} (default cmat)")
    train.add_argument("--steps", type=int, help="environment steps per seed (total_steps)")
    train.add_argument("--seeds", type=int, help="independent seeds trained at once")
    train.add_argument("--config", type=Path, metavar="FILE.yaml", help="YAML config file")
    train.add_argument(
        "--preset", metavar="NAME",
        help="a named setting of the algorithm, applied before --config and --set: 'paper' is "
             "the paper's exact settings; for cmat, 'tuned' names its default, the "
             "learning-speed study's configuration (default: the algorithm's own defaults)",
    )
    train.add_argument(
        "--set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
        help="config overrides, e.g. ppo.lr=1e-4 num_envs=8 (applied after --config)",
    )
    train.add_argument("--out", type=Path, metavar="DIR",
                       help="run directory (default runs/<env>-<timestamp>)")
    train.add_argument("--resume", type=Path, metavar="DIR",
                       help="continue the run in DIR (only --steps may be given with it)")
    train.add_argument("--dry-run", action="store_true",
                       help="print the resolved config, each value with its source (default, "
                            "suite, algorithm, preset, file, command line), and the "
                            "environment's agents and actions; train nothing")
    cluster = train.add_argument_group(
        "one run across several processes (docs/distributed.md)")
    cluster.add_argument("--coordinator", metavar="HOST:PORT|auto",
                         help="join a run of several processes whose process 0 listens at "
                              "HOST:PORT; 'auto' where JAX finds the cluster (SLURM, Open MPI)")
    cluster.add_argument("--processes", type=int, metavar="N",
                         help="the run's number of processes (with --coordinator HOST:PORT)")
    cluster.add_argument("--process-id", type=int, metavar="I",
                         help="this process's number, 0 to N-1; process 0 writes the run")
    train.set_defaults(handler=train_command)

    evaluate = commands.add_parser(
        "eval", help="evaluation of a run's checkpoint (acting as its eval_actions: greedy, "
                     "sampled on dispatch), or of a classical dispatch baseline (--baseline)")
    evaluate.add_argument("--run", type=Path, metavar="DIR",
                          help="run directory (with --baseline: evaluate the baseline on the "
                               "run's environment and options)")
    evaluate.add_argument("--episodes", type=int,
                          help="episodes per seed (default: the run's eval_episodes; 32 for a "
                               "baseline without --run)")
    evaluate.add_argument("--actions", choices=("greedy", "sample", "matched"),
                          help="act greedily or sample the policy (default: the run's "
                               "eval_actions); matched: dispatch tasks, the policy's most "
                               "likely claims in which no order goes to two vehicles, on the "
                               "episodes the baselines play with --seed")
    evaluate.add_argument("--baseline", metavar="NAME",
                          help="dispatch tasks only: evaluate the classical policy NAME "
                               "(random, greedy, hungarian) instead of a checkpoint")
    evaluate.add_argument("--env", metavar="ID",
                          help="with --baseline and no --run: the dispatch task to evaluate on")
    evaluate.add_argument("--set", action="extend", nargs="+", default=[],
                          metavar="env_kwargs.NAME=VALUE",
                          help="with --baseline --env: the task's options, as for train (e.g. "
                               "env_kwargs.city_file=my_city.npz)")
    evaluate.add_argument("--seed", type=int, default=0,
                          help="which evaluation episodes (start states and draws) each seed "
                               "plays (default 0; training evaluates at env step t with seed t, "
                               "so 0 replays none of them)")
    evaluate.add_argument("--checkpoint", type=checkpoint_argument, default="latest",
                          metavar="WHICH", help=CHECKPOINT_HELP)
    evaluate.add_argument(
        "--iterations", type=int, metavar="K",
        help="CMAT only: run the decoder for K consensus iterations instead of the trained m "
             "(0 <= K <= m; the decoder is weight-shared, only its positional table is per "
             "iteration)",
    )
    evaluate.set_defaults(handler=eval_command)

    render = commands.add_parser(
        "render", help="greedy episodes of a trained policy drawn into a GIF or MP4"
    )
    render.add_argument("--run", type=Path, required=True, metavar="DIR", help="run directory")
    render.add_argument("--seed", type=int,
                        help="which of the run's seeds (default: its first); also seeds the "
                             "episodes")
    render.add_argument("--episodes", type=int, default=1, help="episodes to draw (default 1)")
    render.add_argument("--checkpoint", type=checkpoint_argument, default="latest",
                        metavar="WHICH", help=CHECKPOINT_HELP)
    render.add_argument("--fps", type=int, default=8, help="frames per second (default 8)")
    render.add_argument("--max-steps", type=int, metavar="N",
                        help="draw at most N steps of each episode (default: whole episodes)")
    render.add_argument("--out", type=Path, required=True, metavar="FILE.gif|FILE.mp4",
                        help="animation to write (.gif; .mp4 needs ffmpeg)")
    render.set_defaults(handler=render_command)

    export = commands.add_parser(
        "export", help="one seed's policy from a run, saved for deployment: config and "
                       "parameters, which cmat.load_policy(DIR) acts from")
    export.add_argument("--run", type=Path, required=True, metavar="DIR", help="run directory")
    export.add_argument("--seed", type=int, help="which of the run's seeds (default: its first)")
    export.add_argument("--checkpoint", type=checkpoint_argument, default="latest",
                        metavar="WHICH", help=CHECKPOINT_HELP)
    export.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="the new directory to write (must not exist)")
    export.set_defaults(handler=export_command)

    plot = commands.add_parser("plot", help="evaluation curves of run directories")
    plot.add_argument("runs", type=Path, nargs="+", metavar="DIR", help="run directories")
    plot.add_argument("--out", type=Path, required=True, metavar="FILE.png", help="image to write")
    plot.add_argument(
        "--diagnostics", action="store_true",
        help="draw the per-update training diagnostics instead (clip fraction and approximate "
             "KL of the joint and per-agent ratios, explained variance, entropy per agent, "
             "gradient norm per block)",
    )
    plot.set_defaults(handler=plot_command)

    finetune = commands.add_parser(
        "finetune", help="continue a CMAT run with blocks frozen (paper Algorithm 1, B)"
    )
    finetune.add_argument("--from", dest="source", type=Path, required=True, metavar="RUN_DIR",
                          help="the CMAT run directory whose checkpoint to continue")
    finetune.add_argument(
        "--mode", required=True, choices=FINETUNE_MODES,
        help="consensus: train only Critic-MLP, decoder, Actor-Compressor; "
             "action: train only Critic-MLP and Actor-MLP",
    )
    finetune.add_argument("--checkpoint", type=checkpoint_argument, default="latest",
                          metavar="WHICH", help=CHECKPOINT_HELP)
    finetune.add_argument("--steps", type=int,
                          help="fine-tuning env steps per seed (default: the source's total_steps)")
    finetune.add_argument(
        "--set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
        help="config overrides on top of the source run's config, e.g. ppo.lr=1e-4",
    )
    finetune.add_argument("--out", type=Path, metavar="DIR",
                          help="new run directory (default runs/<env>-finetune-<mode>-<timestamp>)")
    finetune.set_defaults(handler=finetune_command)

    show = commands.add_parser(
        "config", help="every config field: its value for an algorithm and env, where that "
                       "value comes from, and what the field means",
    )
    show.add_argument("--algo", help=f"algorithm: {', '.join(algorithm_names())} (default cmat)")
    show.add_argument("--env", help="environment id (its suite's settings apply)")
    show.add_argument("--preset", metavar="NAME", help="a named setting of the algorithm")
    show.add_argument("--set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
                      help="config overrides, as for train")
    show.add_argument("--config", type=Path, metavar="FILE.yaml", help="YAML config file")
    show.add_argument("--explain", metavar="KEY",
                      help="print every layer's value of the field KEY (e.g. ppo.lr), top to "
                           "bottom: the default, the suite, the algorithm, its task values, the "
                           "preset, the file, the command line; the last one is used")
    show.add_argument("--check-env", action="store_true",
                      help="also build the environment with its options, which checks its name "
                           "and options here (imports its suite and JAX: seconds more); "
                           "`cmat train` always does")
    show.set_defaults(handler=config_command)

    experiment = commands.add_parser(
        "experiment", help="run a grid of algorithms x environments x seeds x variants"
    )
    experiment.add_argument("spec", type=Path, metavar="SPEC",
                            help="experiment spec: a YAML file, or the name of one shipped with "
                                 "cmat (dispatch, smax_benchmark, smoke, ...)")
    experiment.add_argument("--out", type=Path, metavar="DIR",
                            help="experiment directory (default runs/experiments/<spec name>)")
    experiment.add_argument("--parallel", type=int, metavar="K",
                            help="runs at once (default: what fits this machine; with --ray, "
                                 "every ready run)")
    experiment.add_argument("--ray", metavar="ADDRESS",
                            help="run on the Ray cluster at ADDRESS (needs the ray extra)")
    experiment.add_argument("--dry-run", action="store_true",
                            help="print the plan (what is reused, resumed, redone) and stop")
    experiment.add_argument("--report-only", action="store_true",
                            help="write the figures and tables from the complete runs on disk "
                                 "and start no run (a grid still in progress, or split over "
                                 "machines)")
    experiment.add_argument("--only", nargs="+", metavar="PATTERN",
                            help="run only the grid's runs whose names (ENV/VARIANT/ALGO-sA-B, "
                                 "as --dry-run lists them) match a shell pattern, e.g. "
                                 "'smax_2s3z/*' '*/default/mappo-*'")
    experiment.add_argument("--export", type=Path, metavar="DIR",
                            help="copy the complete runs' results without checkpoints "
                                 "(config, metrics, checkpoint header) into DIR and report "
                                 "there, to commit or share; a copy of DIR continues the grid "
                                 "elsewhere as --out")
    experiment.add_argument("--seeds-per-run", type=int, metavar="K",
                            help="seeds one run trains together, for the seeds that have no run "
                                 "on disk yet (default: the spec's seeds_per_run); 1 finishes a "
                                 "long cell one seed at a time")
    experiment.add_argument("--carry", action="store_true",
                            help="with --export: also copy the checkpoints the grid still needs "
                                 "(partial runs, and bases of fine-tuning stages still to run), "
                                 "so a copy of DIR continues them instead of starting over")
    experiment.set_defaults(handler=experiment_command)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit code."""
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit:
        return exit.code if isinstance(exit.code, int) else 2
    try:
        supervised = distributed.SUPERVISED in os.environ
        if args.command == "train" and cluster_flags(args) and not supervised:
            process = ("this process" if args.process_id is None
                       else f"process {args.process_id} of {args.processes}")
            return distributed.supervise(sys.argv[1:] if argv is None else argv, process,
                                         args.out or args.resume)
        args.handler(args)
    except CmatError as error:
        return fail(str(error))
    except BrokenPipeError:  # the reader of stdout left (`cmat config | head`): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as error:
        return fail(f"{error.strerror}: {error.filename}" if error.filename else str(error))
    except KeyboardInterrupt:
        print("cmat: interrupted", file=sys.stderr)
        return 130
    return 0


def cluster_flags(args: argparse.Namespace) -> bool:
    """Whether `cmat train` joins a run of several processes; CmatError where its cluster
    flags do not fit together or with --dry-run."""
    if args.coordinator is None:
        if args.processes is not None or args.process_id is not None:
            raise CmatError("--processes and --process-id need --coordinator HOST:PORT")
        return False
    if args.dry_run:
        raise CmatError("--dry-run takes no --coordinator")
    distributed.check_cluster(args.coordinator, args.processes, args.process_id)
    return True


def run() -> NoReturn:
    """The `cmat` and `python -m cmat` entry point: `main`'s exit code. After an interrupt
    the process ends without Python's finalisation: a Ctrl-C during a compile or a chunk
    leaves XLA's threads running, and tearing the interpreter down under them crashed the
    process (a segmentation fault or an abort, where 130 was due). Everything a run keeps is
    already written by then."""
    code = main()
    if distributed.active():
        distributed.finish(code)
    if code == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


def fail(message: str) -> int:
    print(f"cmat: error: {' '.join(message.split())}", file=sys.stderr)
    return 2


def config_command(args: argparse.Namespace) -> None:
    """Print each field as `name = value  [source]` with its docstring indented below."""
    explicit = flag_overrides({"algo": args.algo, "env": args.env, "preset": args.preset})
    config, sources = resolve_config(args.config, [*args.set, *explicit])
    if args.explain is not None:
        rows = explain(args.explain, args.config, [*args.set, *explicit])
        for number, (label, value) in enumerate(rows):
            used = "  <- used" if number == len(rows) - 1 else ""
            print(f"{args.explain} = {value!r}  [{label}]{used}")
        return
    unavailable = (probe_env(config.env, config.env_kwargs)[1] if args.check_env
                   else suite_of(config.env).unavailable(config.env))
    docs = field_docs(config.algo)
    values = to_mapping(config)
    flat = {name: values[name.partition(".")[0]][name.partition(".")[2]] if "." in name
            else values[name] for name in field_names(config.algo)}
    read = {f"network.{name}" for name in algorithm_entry(config.algo).network_fields}
    for name, value in flat.items():
        unread = (f"; not read by {config.algo}"
                  if name.startswith("network.") and name not in read else "")
        print(f"{name} = {value!r}  [{sources.get(name, 'default')}{unread}]")
        if docs.get(name):
            print(textwrap.fill(docs[name], width=96, initial_indent="    ",
                                subsequent_indent="    "))
    suite = config.env.partition(":")[0]
    if suite in registry():
        print(f"# suite {suite}: {registry()[suite].source}")
    if unavailable is not None:
        print(f"# {config.env} cannot be built on this machine: {unavailable}")


def train_command(args: argparse.Namespace) -> None:
    if args.coordinator is not None:
        distributed.quiet_runtime_log()
        distributed.initialize(args.coordinator, args.processes, args.process_id)
    if args.resume is not None:
        if any(value is not None for value in (args.env, args.algo, args.seeds, args.config,
                                                args.out, args.preset)) or args.set:
            raise CmatError("--resume takes no other option than --steps")
        if args.dry_run:
            run_dir = RunDir.open(args.resume)
            run_dir.refuse_saved_policy()
            config = run_dir.config()
            if args.steps is not None:
                config = validate(dataclasses.replace(config, total_steps=args.steps))
            print(to_yaml(config, run_dir.resumed_sources(config)), end="")
            print(f"# {describe_env(config)}")
            return
        train(resume=args.resume, steps=args.steps)
        return
    flags = {"env": args.env, "algo": args.algo, "total_steps": args.steps, "seeds": args.seeds,
             "preset": args.preset}
    explicit = flag_overrides(flags)
    config, sources = resolve_config(args.config, [*args.set, *explicit])
    if args.dry_run:
        description = describe_env(config)
        print(to_yaml(config, sources), end="")
        print(f"# {description}")
        print(f"# {budget_note(config, sources['total_steps'])}")
        return
    start_run(config, sources, args.out)


def flag_overrides(flags: dict[str, str | int | None]) -> list[str]:
    """KEY=VALUE overrides from the flags given: a string flag is quoted, so that YAML reads
    `--env 'smax: 3m'`, `--env pettingzoo:` or `--env true` as the string typed."""
    return [f"{key}='{value.replace(chr(39), chr(39) * 2)}'" if isinstance(value, str)
            else f"{key}={value}" for key, value in flags.items() if value is not None]


def describe_env(config: TrainConfig) -> str:
    """One line on the environment `config` names: agents, observation size, actions.

    Raises CmatError where it cannot be built (unknown id, missing suite package)."""
    spec = build_trainer(config).env_spec
    actions = (f"{spec.action_dim} discrete actions" if spec.discrete
               else f"{spec.action_dim}-dimensional continuous actions")
    return (f"{config.env}: {spec.num_agents} agents, observations of size {spec.obs_dim}, "
            f"{actions}; {config.budget_steps:,} env steps per seed in "
            f"{config.num_updates:,} updates of {config.steps_per_update:,} steps")


def eval_command(args: argparse.Namespace) -> None:
    if args.baseline is not None:
        if not 0 <= args.seed <= INT32_MAX:
            raise CmatError(f"--seed must be in [0, {INT32_MAX:,}], got {args.seed:,}")
        baseline_command(args)
        return
    if args.run is None:
        raise CmatError("cmat eval needs --run DIR (or --baseline NAME with --env ID or --run)")
    if args.set:
        raise CmatError("--set applies to --baseline --env; a run is evaluated with its own "
                        "config")
    run_dir = RunDir.open(args.run)
    config = run_dir.config()
    episodes = args.episodes or config.eval_episodes
    seeds = 1 if run_dir.is_saved_policy else config.seeds
    progress(f"evaluating {run_dir.path}: {episodes:,} episodes for each of {seeds} "
             f"seed{'s' if seeds > 1 else ''} on {config.env} (compiling first) ...")
    start = time.perf_counter()
    extra, per_seed = evaluate_run(run_dir, args.episodes, args.actions, args.seed,
                                   args.iterations, args.checkpoint)
    progress(f"evaluated in {time.perf_counter() - start:.0f} s")
    print(json.dumps({**extra, "per_seed": per_seed}))


def progress(message: str) -> None:
    """A progress line on stderr where it is a terminal (a script that reads stdout or a log
    gets none)."""
    if sys.stderr.isatty():
        print(f"cmat: {message}", file=sys.stderr, flush=True)


def baseline_command(args: argparse.Namespace) -> None:
    """Evaluate a classical dispatch policy (`cmat.envs.dispatch.baselines`) on `--run`'s
    environment and options or on `--env`, printing what `eval` prints for a run."""
    if (args.run is None) == (args.env is None):
        raise CmatError("--baseline needs exactly one of --env ID and --run DIR")
    if args.iterations is not None:
        raise CmatError("--iterations applies to cmat runs only, not to a baseline")
    if args.actions is not None:
        raise CmatError("--actions applies to a run's policy, not to a baseline")
    if args.run is not None:
        if args.set:
            raise CmatError("--set applies to --baseline --env; with --run the baseline takes "
                            "the run's options")
        config = RunDir.open(args.run).config()
        env_id, env_kwargs, episodes = config.env, config.env_kwargs, config.eval_episodes
    else:
        other = [item for item in args.set if not item.startswith("env_kwargs.")]
        if other:
            raise CmatError(f"--set with --baseline takes the task's options "
                            f"(env_kwargs.NAME=VALUE) only, got {other[0]!r}")
        config = load_config(None, [f"env={args.env}", *args.set])
        env_id, env_kwargs, episodes = args.env, config.env_kwargs, 32
    episodes = args.episodes if args.episodes is not None else episodes
    if not 0 < episodes <= HOST_EPISODES:
        raise CmatError(f"--episodes must be in [1, {HOST_EPISODES:,}] for a baseline, got "
                        f"{episodes:,}")
    from cmat.envs.dispatch.baselines import baseline_env, evaluate_means

    means = evaluate_means(baseline_env(env_id, env_kwargs), args.baseline, episodes, args.seed)
    summary = {name: json_number(value) for name, value in means.items()}
    print(json.dumps({"baseline": args.baseline, "env": env_id, "episodes_per_seed": episodes,
                      "per_seed": [{"seed": args.seed, **summary}]}))


def finetune_command(args: argparse.Namespace) -> None:
    from cmat.runners.finetune import finetune_config, finetune_start

    if args.steps is not None and args.steps <= 0:
        raise CmatError(f"--steps must be > 0, got {args.steps}")
    source_dir = RunDir.open(args.source)
    source_config = source_dir.config()
    config, sources = finetune_config(source_config, source_dir.path, args.mode, args.steps,
                                      args.set, source_dir.sources())
    from cmat.runners.base import restore_run

    source_state, source_steps = restore_run(source_dir, build_trainer(source_config),
                                             args.checkpoint)
    trainer = build_trainer(config)
    state = finetune_start(trainer, source_state)
    run_dir = (RunDir.create_named(default_out(config), config, sources) if args.out is None
               else RunDir.create(args.out, config, sources))
    print(f"fine-tuning ({args.mode}) from {source_dir.path}'s {args.checkpoint} checkpoint "
          f"at {source_steps} env steps",
          file=sys.stderr)
    train_into(trainer, run_dir, resume=False, start=state)


def experiment_command(args: argparse.Namespace) -> None:
    from cmat.experiments.runner import run_experiment

    run_experiment(args.spec, out=args.out, parallel=args.parallel, ray_address=args.ray,
                   dry_run=args.dry_run, report_only=args.report_only, only=args.only,
                   export=args.export, carry=args.carry, seeds_per_run=args.seeds_per_run)


def render_command(args: argparse.Namespace) -> None:
    from cmat.policy import load_policy
    from cmat.render import check_request, render_episodes

    check_request(RunDir.open(args.run).config().env, args.out, args.episodes, args.fps)
    policy = load_policy(args.run, args.seed, args.checkpoint)
    frames = render_episodes(policy, args.out, args.episodes, policy.seed, args.fps,
                             args.max_steps)
    print(f"wrote {args.out} ({frames} frames, seed {policy.seed})")


def export_command(args: argparse.Namespace) -> None:
    from cmat.policy import load_policy

    if args.out.exists() or args.out.is_symlink():
        raise CmatError(f"{args.out} already exists; a policy is saved to a new directory")
    policy = load_policy(args.run, args.seed, args.checkpoint)
    policy.save(args.out)
    size = sum(file.stat().st_size for file in args.out.iterdir())
    print(f"wrote {args.out}: {policy.config.algo} on {policy.config.env}, seed {policy.seed}, "
          f"{policy.env_steps:,} env steps, {size / 1e6:.2f} MB")


def plot_command(args: argparse.Namespace) -> None:
    (plot_diagnostics if args.diagnostics else plot_runs)(args.runs, args.out)
    print(f"wrote {args.out}")
