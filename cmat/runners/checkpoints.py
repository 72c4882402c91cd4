"""The checkpoints a run keeps beside `latest`: each seed's best, the periodic ones, and the
best policy's evaluation on ten times the episodes once the run completes.

- `best.ckpt`: after each evaluation, every seed whose evaluation metric (the win rate where
  the environment has one, else the episode return) beats its best so far has its parameters,
  target critic, optimiser and value-normaliser state copied into the best checkpoint; the other
  seeds keep theirs. Its update counter and random key are the latest's, so it restores like
  any checkpoint; its header records each seed's best score and env steps (`best`). A run
  resumed from a directory without one (written before best checkpoints existed, or a carried
  copy without it) starts tracking at its next evaluation.
- `step-N.ckpt`: the latest checkpoint as it was at the first chunk at or past each multiple of
  `checkpoint_interval` env steps; the `keep_checkpoints` most recent are kept.
- The absolute metric (Gorsane et al., 2022, "Towards a standardised performance evaluation
  protocol for cooperative MARL", the protocol marl-eval and Mava report): once the run has
  trained its whole budget, the best checkpoint is evaluated on ten times `eval_episodes`
  episodes per seed (episode seed `ABSOLUTE_EPISODE_SEED`, which no training evaluation uses);
  the result is a metrics.csv row of kind `absolute` per seed, at the budget's env steps, with
  `best_env_steps`, the steps its parameters come from.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np

from cmat.config import INT32_MAX
from cmat.rundir import RunDir, network_record

if TYPE_CHECKING:
    from cmat.runners.base import Trainer, TrainerState
    from cmat.runners.learner import LearnerState

ABSOLUTE_FACTOR = 10
"""Episodes of the absolute evaluation, in multiples of `eval_episodes` (Mava's factor)."""
ABSOLUTE_EPISODE_SEED = INT32_MAX
"""The episode seed of the absolute evaluation: training evaluates at env step t with seed t,
and a budget reaches this only at the limit itself."""
BEST_FIELDS = ("params", "target_params", "opt_state", "value_norm")
"""The learner fields a seed's best checkpoint takes from the chunk where it was best."""


def score_metric(trainer: Trainer) -> str:
    """The evaluation metric the best checkpoint is chosen by."""
    return "win_rate" if trainer.env_spec.has_win_rate else "episode_return"


class BestCheckpoint:
    """Each seed's best evaluation so far, and `best.ckpt` kept in step with it."""

    def __init__(self, trainer: Trainer, run_dir: RunDir) -> None:
        self.trainer = trainer
        self.run_dir = run_dir
        seeds = trainer.config.seeds
        record = (run_dir.checkpoint_header("best") or {}).get("best") or {}
        scores, steps = record.get("scores"), record.get("env_steps")
        if (isinstance(scores, list) and isinstance(steps, list)
                and len(scores) == len(steps) == seeds):
            self.scores = np.array([-np.inf if s is None else s for s in scores], np.float64)
            self.steps = np.array(steps, np.int64)
        else:
            self.scores, self.steps = np.full(seeds, -np.inf), np.zeros(seeds, np.int64)
        self.learner: LearnerState | None = None
        """The best learner state on the host, once this process has loaded or made it."""

    def update(self, state: TrainerState, evaluation: dict[str, Any], env_steps: int) -> None:
        """Take the seeds of `state` whose evaluation beats their best, and rewrite best.ckpt
        where one does."""
        from cmat.runners.devices import to_host

        scores = np.asarray(evaluation[score_metric(self.trainer)], np.float64)
        improved = np.nan_to_num(scores, nan=-np.inf) > self.scores
        if not improved.any():
            return
        current = to_host(state.learner)
        base = current if improved.all() else self.best_learner(state)
        self.learner = merged(base, current, improved)
        self.scores = np.where(improved, scores, self.scores)
        self.steps = np.where(improved, env_steps, self.steps)
        best = dataclasses.replace(state, learner=self.learner)
        record = {"scores": [None if np.isinf(s) else float(s) for s in self.scores],
                  "env_steps": [int(s) for s in self.steps],
                  "metric": score_metric(self.trainer)}
        self.run_dir.save_checkpoint(self.trainer.to_bytes(best), env_steps,
                                     network_record(self.trainer.config), which="best",
                                     extra={"best": record})

    def best_learner(self, state: TrainerState) -> LearnerState:
        """The best learner state: this process's, else best.ckpt's, else `state`'s."""
        from cmat.runners.devices import to_host

        if self.learner is None:
            if "best" in self.run_dir.checkpoints() and np.isfinite(self.scores).any():
                data, _ = self.run_dir.load_checkpoint("best")
                self.learner = to_host(self.trainer.from_bytes(data).learner)
            else:
                self.learner = to_host(state.learner)
        return self.learner

    def absolute(self, state: TrainerState) -> dict[str, np.ndarray]:
        """The best checkpoint's evaluation on `ABSOLUTE_FACTOR` × eval_episodes episodes per
        seed, with `best_env_steps`."""
        config = self.trainer.config
        best = dataclasses.replace(state, learner=self.best_learner(state))
        result = self.trainer.evaluate(best, ABSOLUTE_FACTOR * config.eval_episodes,
                                       episode_seed=ABSOLUTE_EPISODE_SEED)
        return {**result, "best_env_steps": self.steps.copy()}


def merged(best: LearnerState, current: LearnerState, improved: np.ndarray) -> LearnerState:
    """`current` with the `BEST_FIELDS` of the seeds not `improved` taken from `best` (every
    leaf has a leading seed axis)."""
    import jax

    def pick(old: Any, new: Any) -> Any:
        new = np.asarray(new)
        return np.where(improved.reshape((-1,) + (1,) * (new.ndim - 1)), new, np.asarray(old))

    return dataclasses.replace(current, **{
        name: jax.tree.map(pick, getattr(best, name), getattr(current, name))
        for name in BEST_FIELDS})


def keep_periodic(trainer: Trainer, run_dir: RunDir, data: bytes, before: int,
                  env_steps: int) -> None:
    """Write `data` (the latest checkpoint's bytes at `env_steps`) as a periodic checkpoint
    when this chunk crossed a multiple of `checkpoint_interval`, and delete all but the
    `keep_checkpoints` most recent."""
    config = trainer.config
    interval = config.checkpoint_interval
    if interval <= 0 or env_steps // interval == before // interval:
        return
    run_dir.save_checkpoint(data, env_steps, network_record(config), which=env_steps)
    periodic = run_dir.periodic_checkpoints()
    if config.keep_checkpoints:
        for old in periodic[:-config.keep_checkpoints]:
            run_dir.checkpoint_file(old).unlink(missing_ok=True)
