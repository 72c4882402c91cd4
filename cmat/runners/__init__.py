"""Trainers: the rollout-and-update loop of a run, in-graph (`trainer.JaxTrainer`) or with host
simulators (`host.HostTrainer`), and what drives them (`loop`, `checkpoints`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from cmat.config import TrainConfig
    from cmat.runners.base import Trainer


def build_trainer(config: TrainConfig) -> Trainer:
    """`HostTrainer` for host environment ids, `JaxTrainer` for in-graph ones (JAX is imported
    here, on first use)."""
    from cmat.envs.host import is_host_env
    from cmat.runners.host import HostTrainer
    from cmat.runners.trainer import JaxTrainer

    return HostTrainer(config) if is_host_env(config.env) else JaxTrainer(config)
