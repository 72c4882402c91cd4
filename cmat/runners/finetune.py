"""Fine-tuning (Algorithm 1, B): a new run that continues a CMAT run's parameters with a block
frozen.

What carries over from the source checkpoint: the parameters, the target critic and the value
normaliser's statistics (the critic's outputs live in its normalised space). What starts fresh:
the optimizer state, because the masked optimizer's state has another structure and Adam's
moments were accumulated on the joint objective (Adam restarts with its bias correction, so the
first steps are about lr in size); the environments, the update counter (a fine-tuning run
counts its own env steps from 0, as the paper's fine-tuning curves do) and the random stream.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

from cmat.algorithms import check_config, finetune_stage_error
from cmat.config import ConfigSources, TrainConfig, validate
from cmat.errors import CmatError
from cmat.resolve import resolve_config

if TYPE_CHECKING:
    from cmat.runners.base import Trainer, TrainerState

FIXED_FIELDS = ("env", "env_kwargs", "algo", "seeds", "seed", "network")
"""What a fine-tuning run cannot change: the checkpoint holds parameters for exactly these, and
for the algorithm's `network_options`."""


def finetune_config(
    source: TrainConfig,
    source_dir: Path,
    mode: str,
    steps: int | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    source_sources: ConfigSources | None = None,
) -> tuple[TrainConfig, ConfigSources]:
    """The source run's config with the fine-tuning stage, its budget and `key=value` overrides
    (e.g. a lower ppo.lr) applied, and each value's source (`source_sources`, the source run's,
    for what it keeps)."""
    if error := finetune_stage_error(source.algo, mode):
        raise CmatError(f"{source_dir}: {error}")
    for override in overrides:
        key = override.split("=", 1)[0].strip()
        field, _, inner = key.partition(".")
        if field in FIXED_FIELDS or (field == source.algo
                                     and inner in source.options.network_options):
            raise CmatError(f"fine-tuning cannot change {field if field in FIXED_FIELDS else key} "
                            f"of the source run (its checkpoint holds the parameters for it)")
        if field in ("finetune", "finetune_from"):
            raise CmatError(f"--set {key}: a fine-tuning stage is named by --mode and --from")
    config, sources = resolve_config(None, overrides, base=source, base_sources=source_sources)
    config = dataclasses.replace(
        config,
        finetune=mode,
        finetune_from=str(source_dir),
        total_steps=steps if steps is not None else config.total_steps,
    )
    stage = "cmat finetune"
    sources.update(finetune=stage, finetune_from=stage)
    if steps is not None:
        sources["total_steps"] = stage
    return check_config(validate(config)), sources


def finetune_start(trainer: Trainer, source: TrainerState) -> TrainerState:
    """The first state of a fine-tuning run: `trainer`'s fresh state carrying the source
    run's parameters, target critic and value normaliser (`source`, its checkpoint's state),
    with a fresh optimizer state for `trainer`'s masked optimizer."""
    import jax

    fresh = trainer.init()
    learner = dataclasses.replace(
        fresh.learner,
        params=source.learner.params,
        target_params=source.learner.target_params,
        value_norm=source.learner.value_norm,
        opt_state=jax.vmap(trainer.learner_setup.optimizer.init)(source.learner.params),
        rng=jax.vmap(lambda key: jax.random.fold_in(key, 1))(fresh.learner.rng),
    )
    return dataclasses.replace(fresh, learner=learner)
