"""PPO's epochs × minibatches of gradient steps, as one function of the loss.

The loss is a value, as in Brax's `training/gradients.py`: the shared update passes an
algorithm's `loss`, HAPPO one loss per agent phase. The optimiser is passed too, so a caller can
restrict it (fine-tuning masks, HAPPO's per-agent phases) without this module knowing why.
`PPOAlgorithm` holds what every algorithm inherits unless it overrides it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax

from cmat.algorithms.base import ActResult, Batch, Loss, Params, loss_is_sample_mean
from cmat.algorithms.ppo import block_grad_norms
from cmat.config import PPOConfig
from cmat.errors import CmatError

Metrics = dict[str, jax.Array]

TRAIN, FROZEN = "train", "frozen"
"""The labels of `Algorithm.finetune_labels`."""


def minibatch_sgd(
    loss: Loss, optimizer: optax.GradientTransformation, params: Params, opt_state: Any,
    batch: Batch, rng: jax.Array, ppo: PPOConfig,
    epoch_batch: Callable[[Batch, jax.Array], Batch] | None = None,
) -> tuple[Params, Any, Metrics]:
    """`ppo.epochs` passes over `batch` [B, ...] in `ppo.num_minibatches` shuffled minibatches,
    one optimiser step on `loss(params, minibatch, ppo)` each. With `epoch_batch`, each pass
    runs over `epoch_batch(batch, key)` with a fresh key (Sable's agent shuffle).

    Returns the new parameters and optimiser state and the loss's metrics averaged over the
    steps, with `loss`, `grad_norm` (global norm before clipping) and the per-block gradient
    norms (`cmat.algorithms.ppo.block_grad_norms`). With `ppo.target_kl`, the epochs after the
    first whose mean `approx_kl` exceeds it are skipped, the averages run over the epochs that
    ran, and `epochs_run` says how many did. B must be divisible by `ppo.num_minibatches`
    (`TrainConfig.validate` checks it).
    """
    def minibatch_step(
        carry: tuple[Params, Any], minibatch: Batch
    ) -> tuple[tuple[Params, Any], Metrics]:
        params, opt_state = carry
        (value, metrics), grads = minibatch_gradient(loss, params, minibatch, ppo)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        metrics = {
            **metrics, "loss": value, "grad_norm": optax.tree.norm(grads),
            **block_grad_norms(grads),
        }
        return (optax.apply_updates(params, updates), opt_state), metrics

    def epoch(
        carry: tuple[Params, Any], key: jax.Array, batch: Batch
    ) -> tuple[tuple[Params, Any], Metrics]:
        passed = batch
        if epoch_batch is not None:
            key, batch_key = jax.random.split(key)
            passed = epoch_batch(batch, batch_key)
        size = passed.advantages.shape[0]
        order = jax.random.permutation(key, size)
        minibatches = jax.tree.map(
            lambda x: x[order].reshape(
                ppo.num_minibatches, size // ppo.num_minibatches, *x.shape[1:]
            ),
            passed,
        )
        return jax.lax.scan(minibatch_step, carry, minibatches)

    keys = jax.random.split(rng, ppo.epochs)
    if ppo.target_kl is None:
        (params, opt_state), metrics = jax.lax.scan(
            lambda carry, key: epoch(carry, key, batch), (params, opt_state), keys
        )
        return params, opt_state, jax.tree.map(jnp.mean, metrics)
    target_kl = ppo.target_kl
    traced_epoch = jax.jit(epoch)

    def early_stopping_epoch(
        carry: tuple[Params, Any, jax.Array], key: jax.Array
    ) -> tuple[tuple[Params, Any, jax.Array], Metrics]:
        """An epoch unless an earlier one passed `ppo.target_kl` (then the state is kept); the
        skipped branch's shapes and the epoch share one trace of the jitted epoch."""
        params, opt_state, stopped = carry
        shapes = jax.eval_shape(traced_epoch, (params, opt_state), key, batch)[1]
        skipped = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)
        (params, opt_state), metrics = jax.lax.cond(
            stopped, lambda c: (c, skipped), lambda c: traced_epoch(c, key, batch),
            (params, opt_state),
        )
        ran = ~stopped
        stopped = stopped | (jnp.mean(metrics["approx_kl"]) > target_kl)
        return (params, opt_state, stopped), {**metrics, "ran": ran}

    (params, opt_state, _), metrics = jax.lax.scan(
        early_stopping_epoch, (params, opt_state, jnp.asarray(False)), keys
    )
    ran = metrics.pop("ran")
    epochs_run = jnp.sum(ran)
    averaged = jax.tree.map(
        lambda x: jnp.sum(jnp.mean(x, axis=1) * ran) / jnp.maximum(epochs_run, 1), metrics
    )
    return params, opt_state, {**averaged, "epochs_run": epochs_run.astype(jnp.float32)}


def minibatch_gradient(
    loss: Loss, params: Params, minibatch: Batch, ppo: PPOConfig
) -> tuple[tuple[jax.Array, Metrics], Params]:
    """`jax.value_and_grad` of `loss` (with its metrics) on `minibatch` [B, ...].

    With `ppo.minibatch_chunks` = k > 1 and a loss that is a plain mean over samples
    (`loss_is_sample_mean`: no active masks), the minibatch is split into k equal slices whose
    values, metrics and gradients are computed one after another (`jax.lax.scan`) and
    averaged: the same loss and gradient up to floating-point order, with one slice's
    activations live at a time and nothing recomputed. The metrics are the slices' means, so
    the loss terms are the minibatch's and the diagnostics averaged over active steps (the
    per-agent ones) weight the slices equally. With active masks the means' denominators
    differ between slices, so the loss itself runs its network in k recomputed slices instead
    (`cmat.algorithms.base.chunked`), which costs a second forward pass (docs/speed.md). B must
    be divisible by k (`TrainConfig.validate` checks it)."""
    grad_fn = jax.value_and_grad(loss, has_aux=True)
    chunks = ppo.minibatch_chunks
    if chunks == 1 or not loss_is_sample_mean(ppo):
        result: tuple[tuple[jax.Array, Metrics], Params] = grad_fn(params, minibatch, ppo)
        return result
    whole = dataclasses.replace(ppo, minibatch_chunks=1)
    slices = jax.tree.map(lambda x: x.reshape(chunks, -1, *x.shape[1:]), minibatch)

    def slice_gradient(piece: Batch) -> tuple[tuple[jax.Array, Metrics], Params]:
        result: tuple[tuple[jax.Array, Metrics], Params] = grad_fn(params, piece, whole)
        return result

    def accumulate(total: Any, piece: Batch) -> tuple[Any, None]:
        return jax.tree.map(
            lambda sum_so_far, term: sum_so_far + term / chunks, total, slice_gradient(piece)
        ), None

    first = jax.tree.map(lambda x: x[0], slices)
    zeros = jax.tree.map(
        lambda x: jnp.zeros(x.shape, x.dtype), jax.eval_shape(slice_gradient, first)
    )
    mean: tuple[tuple[jax.Array, Metrics], Params] = jax.lax.scan(accumulate, zeros, slices)[0]
    return mean


def finetune_optimizer(
    optimizer: optax.GradientTransformation, labels: Any
) -> optax.GradientTransformation:
    """`optimizer` on the leaves `labels` (a tree like the params, or a function of them) marks
    TRAIN; zero updates, so bit-identical weights, on those it marks FROZEN.

    Gradient clipping inside `optimizer` then sees only the trained leaves' gradients, as
    freezing by `requires_grad = False` does in the PyTorch reference.
    """
    return optax.multi_transform({TRAIN: optimizer, FROZEN: optax.set_to_zero()}, labels)


class PPOAlgorithm:
    """The defaults of `cmat.algorithms.base.Algorithm`: `update` is `minibatch_sgd` on the
    algorithm's own `loss`, no fine-tuning stages (a recurrent algorithm adds
    `cmat.algorithms.base.Recurrent`'s methods). Algorithms inherit it and
    override what differs."""

    def act(
        self, params: Params, obs: jax.Array, action_mask: jax.Array, key: jax.Array,
        global_state: jax.Array | None = None,
    ) -> ActResult:
        raise NotImplementedError

    def greedy(self, params: Params, obs: jax.Array, action_mask: jax.Array) -> jax.Array:
        raise NotImplementedError

    def value(
        self, params: Params, obs: jax.Array, global_state: jax.Array | None = None
    ) -> jax.Array:
        raise NotImplementedError

    def loss(self, params: Params, batch: Batch, ppo: PPOConfig) -> tuple[jax.Array, Metrics]:
        raise NotImplementedError

    def update(
        self, optimizer: optax.GradientTransformation, params: Params, opt_state: Any,
        batch: Batch, rng: jax.Array, ppo: PPOConfig,
    ) -> tuple[Params, Any, Metrics]:
        return minibatch_sgd(self.loss, optimizer, params, opt_state, batch, rng, ppo)

    def finetune_labels(self, params: Params, mode: str) -> Any:
        raise CmatError(f"{type(self).__name__} has no fine-tuning stages (asked for {mode!r})")

