"""Command line: `cmat train`, `cmat eval`, `cmat plot`.

Every user error (CmatError, an unreadable file) is one line `cmat: error: ...` on stderr and
exit code 2, as argparse does for usage errors.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from cmat.config import TrainConfig, load_config, validate
from cmat.errors import CmatError
from cmat.experiments.plots import plot_runs
from cmat.rundir import RunDir
from cmat.runners.loop import run_training

if TYPE_CHECKING:
    from cmat.runners.trainer import Trainer

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cmat", description="Consensus Multi-Agent Transformer: train, evaluate, plot."
    )
    commands = parser.add_subparsers(dest="command", required=True)

    train = commands.add_parser("train", help="train a new run or resume one")
    train.add_argument("--env", help="environment id (matrix:NAME, smax:SCENARIO, mpe:NAME)")
    train.add_argument("--algo", help="algorithm (default cmat)")
    train.add_argument("--steps", type=int, help="environment steps per seed (total_steps)")
    train.add_argument("--seeds", type=int, help="independent seeds trained at once")
    train.add_argument("--config", type=Path, metavar="FILE.yaml", help="YAML config file")
    train.add_argument(
        "--set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
        help="config overrides, e.g. ppo.lr=1e-4 num_envs=8 (applied after --config)",
    )
    train.add_argument("--out", type=Path, metavar="DIR",
                       help="run directory (default runs/<env>-<timestamp>)")
    train.add_argument("--resume", type=Path, metavar="DIR",
                       help="continue the run in DIR (only --steps may be given with it)")
    train.set_defaults(handler=train_command)

    evaluate = commands.add_parser("eval", help="greedy evaluation of a run's checkpoint")
    evaluate.add_argument("--run", type=Path, required=True, metavar="DIR", help="run directory")
    evaluate.add_argument("--episodes", type=int,
                          help="episodes per seed (default: the run's eval_episodes)")
    evaluate.set_defaults(handler=eval_command)

    plot = commands.add_parser("plot", help="evaluation curves of run directories")
    plot.add_argument("runs", type=Path, nargs="+", metavar="DIR", help="run directories")
    plot.add_argument("--out", type=Path, required=True, metavar="FILE.png", help="image to write")
    plot.set_defaults(handler=plot_command)
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
        args.handler(args)
    except CmatError as error:
        return fail(str(error))
    except OSError as error:
        return fail(f"{error.strerror}: {error.filename}" if error.filename else str(error))
    except KeyboardInterrupt:
        print("cmat: interrupted", file=sys.stderr)
        return 130
    return 0


def fail(message: str) -> int:
    print(f"cmat: error: {' '.join(message.split())}", file=sys.stderr)
    return 2


def train_command(args: argparse.Namespace) -> None:
    if args.resume is not None:
        if any(value is not None for value in (args.env, args.algo, args.seeds, args.config,
                                                args.out)) or args.set:
            raise CmatError("--resume takes no other option than --steps")
        run_dir = RunDir.open(args.resume)
        config = run_dir.config()
        if args.steps is not None:
            config = validate(dataclasses.replace(config, total_steps=args.steps))
        trainer = build_trainer(config)
    else:
        flags = {"env": args.env, "algo": args.algo, "total_steps": args.steps, "seeds": args.seeds}
        explicit = [f"{key}={value}" for key, value in flags.items() if value is not None]
        config = load_config(args.config, [*args.set, *explicit])
        trainer = build_trainer(config)
        run_dir = RunDir.create(args.out or default_out(config), config)
    try:
        run_training(trainer, run_dir, resume=args.resume is not None)
    except KeyboardInterrupt:
        print(f"cmat: stopped at the last checkpoint; continue with: "
              f"cmat train --resume {run_dir.path}", file=sys.stderr)
        raise
    print(f"run directory: {run_dir.path}")


def eval_command(args: argparse.Namespace) -> None:
    run_dir = RunDir.open(args.run)
    config = run_dir.config()
    if args.episodes is not None and args.episodes <= 0:
        raise CmatError(f"--episodes must be > 0, got {args.episodes}")
    data, _ = run_dir.load_checkpoint()
    trainer = build_trainer(config)
    result = trainer.evaluate(
        trainer.from_bytes(data), args.episodes or config.eval_episodes, seed=config.seed
    )
    per_seed = [
        {"seed": config.seed + index,
         "episode_return": json_number(result["episode_return"][index]),
         "win_rate": json_number(result["win_rate"][index])}
        for index in range(config.seeds)
    ]
    print(json.dumps({"per_seed": per_seed}))


def plot_command(args: argparse.Namespace) -> None:
    plot_runs(args.runs, args.out)
    print(f"wrote {args.out}")


def build_trainer(config: TrainConfig) -> Trainer:
    """The trainer for `config`; JAX is imported here, after the log level is set."""
    from cmat.runners.trainer import Trainer

    return Trainer(config)


def default_out(config: TrainConfig) -> Path:
    return Path("runs") / f"{config.env.replace(':', '_')}-{time.strftime('%Y%m%d-%H%M%S')}"


def json_number(value: float) -> float | None:
    return None if math.isnan(value) else float(value)
