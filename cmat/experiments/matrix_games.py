"""Where a trained policy ends on a one-step matrix game: the paper's Fig. 1 argument, measured."""

from __future__ import annotations

from typing import cast

import jax
import numpy as np

from cmat.config import TrainConfig
from cmat.envs.matrix import MatrixGame
from cmat.runners.trainer import JaxTrainer


def greedy_joint_actions(trainer: JaxTrainer, params: object) -> np.ndarray:
    """[seeds, agents] greedy joint action of every seed (matrix games have one state)."""
    _, timestep = trainer.setup.collector.env.reset(jax.random.PRNGKey(0))
    greedy = jax.jit(jax.vmap(trainer.learner_setup.algorithm.greedy, in_axes=(0, None, None)))
    return np.asarray(greedy(params, timestep.obs, timestep.action_mask))


def train_and_count_optimum(config: TrainConfig) -> tuple[int, np.ndarray]:
    """Train every seed of `config` in one chunk; how many end with a greedy joint action of the
    game's highest payoff (any of them, where several tie), and every seed's joint action."""
    trainer = JaxTrainer(config)
    state, _ = trainer.train_chunk(trainer.init())
    joint = greedy_joint_actions(trainer, state.learner.params)
    payoff = np.asarray(cast(MatrixGame, trainer.setup.collector.env).payoff)
    optimal = payoff[joint[:, 0], joint[:, 1]] == payoff.max()
    return int(np.sum(optimal)), joint
