"""HAPPO (Kuba et al. 2022; HARL, Zhong et al. 2024): heterogeneous agents updated one by one.

Every agent has its own actor (separate parameters, input o_i); the centralized critic is MAPPO's.
Each update draws a random order i_1..i_n. Agent i_m runs PPO epochs × minibatches on
−E[min(r·M·A, clip(r, 1−ε, 1+ε)·M·A)] − c_ent·H, with its own ratio r = π_{i_m} / π_{i_m},old
and the compounding factor M = Π_{k<m} π_{i_k}^new / π_{i_k}^old of the agents updated before
it, on the same samples and held constant; then the critic is trained on the value loss.

The run's one optimiser serves all phases: each phase moves only its own parameters and their
Adam moments, and every phase restarts from the update's step count, so each actor and the critic
keep their own moments and step count exactly as HARL's separate optimisers do (every phase takes
the same epochs × minibatches steps). An agent's phase works on its own actor's slice of the
stacked actors and of their moments (`agent_phase`), so it costs one actor's optimiser steps, not
n actors' (a 1,000-vehicle fleet's update would otherwise be quadratic in the fleet).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any, ClassVar, cast

import distrax
import jax
import jax.numpy as jnp
import optax

from cmat.algorithms.base import Batch, Loss, Params, active_mask
from cmat.algorithms.mappo.algorithm import MAPPO
from cmat.algorithms.ppo import clipped_surrogate_loss, masked_mean, policy_diagnostics
from cmat.algorithms.sgd import minibatch_sgd
from cmat.config import PPOConfig
from cmat.networks.heads import action_distribution


def compounding_factors(
    new_log_probs: jax.Array, old_log_probs: jax.Array, order: jax.Array
) -> jax.Array:
    """M of every agent [..., n]: Π π_j^new / π_j^old over the agents j before it in `order`.

    Agents not updated yet carry new = old, so their ratio is exactly 1.
    """
    log_ratios = (new_log_probs - old_log_probs)[..., order]
    before = jnp.cumsum(log_ratios, axis=-1)[..., :-1]
    before = jnp.concatenate([jnp.zeros_like(log_ratios[..., :1]), before], axis=-1)
    return jnp.exp(before)[..., jnp.argsort(order)]


def select_state(optimizer: optax.GradientTransformation, mask: Params, new: Any, old: Any) -> Any:
    """Optimiser state: its param-shaped leaves (Adam moments) from `new` where `mask` holds and
    from `old` elsewhere; its other leaves (step counts) from `new`."""
    choose = optax.tree_utils.tree_map_params(
        optimizer, lambda _, m: m, new, mask, transform_non_params=lambda _: jnp.asarray(True))
    return jax.tree.map(jnp.where, choose, new, old)


def restricted(
    optimizer: optax.GradientTransformation, mask: Params
) -> optax.GradientTransformation:
    """`optimizer` moving only the params where `mask` holds: the others and their moments stay
    bit-identical (a zero gradient alone would still move them through Adam's momentum)."""

    def update(grads: Params, state: Any, params: Params | None = None) -> tuple[Params, Any]:
        updates, new_state = optimizer.update(grads, state, params)
        updates = jax.tree.map(lambda m, u: jnp.where(m, u, jnp.zeros_like(u)), mask, updates)
        return updates, select_state(optimizer, mask, new_state, state)

    return optax.GradientTransformation(optimizer.init, update)


def train_phase(
    optimizer: optax.GradientTransformation, loss: Loss, mask: Params, params: Params,
    opt_state: Any, batch: Batch, rng: jax.Array, ppo: PPOConfig,
) -> tuple[Params, Any, dict[str, jax.Array]]:
    """PPO's epochs × minibatches on `loss`, moving only the params `mask` selects."""
    return minibatch_sgd(loss, restricted(optimizer, mask), params, opt_state, batch, rng, ppo)


def agent_columns(batch: Batch, agent: jax.Array) -> Batch:
    """`batch` with its per-agent fields [B, n, ...] cut to agent `agent`'s column [B, 1, ...]
    (the team's advantages, values, targets and global states as they are): what an agent's
    phase shuffles into minibatches every epoch, so a phase moves one agent's samples, not the
    team's."""
    def column(x: jax.Array) -> jax.Array:
        return jax.lax.dynamic_slice_in_dim(x, agent, 1, axis=1)

    return batch._replace(
        obs=column(batch.obs), action_mask=column(batch.action_mask),
        actions=column(batch.actions), log_probs=column(batch.log_probs),
        alive=None if batch.alive is None else column(batch.alive),
    )


def agent_phase(
    optimizer: optax.GradientTransformation, loss: Loss, agent: jax.Array, params: Params,
    opt_state: Any, batch: Batch, rng: jax.Array, ppo: PPOConfig,
) -> tuple[Params, Any, dict[str, jax.Array]]:
    """Agent `agent`'s phase: `train_phase` on {"actor": its own actor, "critic": the critic
    (frozen)}, cut from the stacked actors [n, ...] and from the matching Adam moments, then
    written back. `loss(own, batch, ppo)` takes that cut tree. The same numbers as `train_phase`
    over the whole tree with every other actor masked (tests/test_baselines_mlp.py), in one
    actor's time and memory instead of n actors'. The step counts come from the phase."""
    def take(x: jax.Array) -> jax.Array:
        return cast(jax.Array, jax.lax.dynamic_index_in_dim(x, agent, keepdims=False))

    def put(whole: jax.Array, part: jax.Array) -> jax.Array:
        return cast(jax.Array, jax.lax.dynamic_update_index_in_dim(whole, part, agent, 0))

    is_actor = {"actor": jax.tree.map(lambda _: True, params["actor"]),
                "critic": jax.tree.map(lambda _: False, params["critic"])}
    actor_moment = optax.tree_utils.tree_map_params(
        optimizer, lambda _, actor: actor, opt_state, is_actor,
        transform_non_params=lambda _: False)
    own = {"actor": jax.tree.map(take, params["actor"]), "critic": params["critic"]}
    own_state = jax.tree.map(lambda cut, x: take(x) if cut else x, actor_moment, opt_state)
    own, own_state, metrics = train_phase(
        optimizer, loss, is_actor, own, own_state, batch, rng, ppo)
    params = {"actor": jax.tree.map(put, params["actor"], own["actor"]),
              "critic": params["critic"]}
    state = jax.tree.map(lambda cut, whole, part: put(whole, part) if cut else part,
                         actor_moment, opt_state, own_state)
    return params, state, metrics


@dataclass(frozen=True)
class HAPPO(MAPPO):
    """Params {"actor": the n actors stacked on a leading agent axis, "critic": ...}.

    `loss` (MAPPO's) is the simultaneous objective, every M = 1; `update` is the sequential one.
    """

    shared_actor: ClassVar[bool] = False
    """Each agent has its own actor, on o_i alone."""

    def init(self, key: jax.Array, obs: jax.Array, action_mask: jax.Array) -> Params:
        """Each actor initialised on its own key, one after another (`lax.map`: a vmapped
        orthogonal init hangs XLA:CPU, and n unrolled ones make the program grow with n)."""
        keys = jax.random.split(key, self.num_agents + 1)
        actors = jax.lax.map(lambda agent: self.actor.init(*agent),
                             (keys[:-1], obs, action_mask))
        return {
            "actor": actors,
            "critic": self.critic.init(keys[-1], self.critic_input(obs, self.blank_state)),
        }

    def policy(
        self, params: Params, obs: jax.Array, action_mask: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """Agent i's own actor on o_i: action parameters [..., n, A] and log-stds [n, A]."""
        apply = jax.vmap(self.actor.apply, in_axes=(0, -2, -2), out_axes=(-2, 0))
        return cast(tuple[jax.Array, jax.Array], apply(params["actor"], obs, action_mask))

    def agent_distribution(
        self, actor: Params, agent: int | jax.Array, batch: Batch
    ) -> distrax.Distribution:
        """Agent `agent`'s distributions [B] on the samples of a batch, from its own actor's
        parameters (one slice of params["actor"])."""
        action_params, log_std = cast(
            tuple[jax.Array, jax.Array],
            self.actor.apply(actor, batch.obs[:, agent], batch.action_mask[:, agent]),
        )
        return action_distribution(action_params, log_std, self.discrete)

    def agent_loss(
        self, agent: int | jax.Array, own: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        """One agent's clipped surrogate and entropy from its own actor (`own["actor"]`, the
        tree `agent_phase` trains); `batch.advantages` already hold M·A. With
        `ppo.active_masks` both average over the samples where the agent is active."""
        distribution = self.agent_distribution(own["actor"], agent, batch)
        team_mask = active_mask(batch, ppo)
        mask = None if team_mask is None else team_mask[:, agent]
        log_ratio = distribution.log_prob(batch.actions[:, agent]) - batch.log_probs[:, agent]
        policy_loss, diagnostics = clipped_surrogate_loss(
            log_ratio, batch.advantages, ppo.clip_eps, mask
        )
        entropy = masked_mean(distribution.entropy(), mask)
        total = policy_loss - ppo.ent_coef * entropy
        return total, {"policy_loss": policy_loss, "entropy": entropy, **diagnostics}

    def critic_phase_loss(
        self, params: Params, batch: Batch, ppo: PPOConfig
    ) -> tuple[jax.Array, dict[str, jax.Array]]:
        critic_loss = self.critic_loss(params, batch, ppo)
        return ppo.value_coef * critic_loss, {"value_loss": critic_loss}

    def update(
        self, optimizer: optax.GradientTransformation, params: Params, opt_state: Any,
        batch: Batch, rng: jax.Array, ppo: PPOConfig,
    ) -> tuple[Params, Any, dict[str, jax.Array]]:
        """The sequential update (module docstring): agents in a random order, then the critic.

        The joint and per-agent ratio diagnostics compare the final actors with the collecting
        ones; `grad_norm_actor` is the mean over the agent phases."""
        keys = jax.random.split(rng, self.num_agents + 2)
        order = jax.random.permutation(keys[0], self.num_agents)
        moment = optax.tree_utils.tree_map_params(
            optimizer, lambda _: True, opt_state, transform_non_params=lambda _: False)
        critic_only = {
            "actor": jax.tree.map(lambda _: jnp.asarray(False), params["actor"]),
            "critic": jax.tree.map(lambda _: jnp.asarray(True), params["critic"]),
        }

        def restart(state: Any) -> Any:
            """`state`'s moments with the update's starting step counts."""
            return jax.tree.map(lambda is_moment, now, start: now if is_moment else start,
                                moment, state, opt_state)

        Carry = tuple[Params, Any, jax.Array]

        def update_agent(
            carry: Carry, step: tuple[jax.Array, jax.Array]
        ) -> tuple[Carry, dict[str, jax.Array]]:
            params, state, new_log_probs = carry
            agent, key = step
            factor = compounding_factors(new_log_probs, batch.log_probs, order)[:, agent]
            params, state, metrics = agent_phase(
                optimizer, partial(self.agent_loss, 0), agent, params, restart(state),
                agent_columns(batch._replace(advantages=factor * batch.advantages), agent), key,
                ppo,
            )
            actor = jax.tree.map(
                lambda x: jax.lax.dynamic_index_in_dim(x, agent, keepdims=False), params["actor"])
            updated = self.agent_distribution(actor, agent, batch)
            new_log_probs = new_log_probs.at[:, agent].set(
                updated.log_prob(batch.actions[:, agent])
            )
            return (params, state, new_log_probs), metrics

        (params, state, new_log_probs), agent_metrics = jax.lax.scan(
            update_agent, (params, opt_state, batch.log_probs), (order, keys[2:])
        )
        params, state, critic_metrics = train_phase(
            optimizer, self.critic_phase_loss, critic_only, params, restart(state), batch,
            keys[1], ppo,
        )
        metrics = jax.tree.map(jnp.mean, agent_metrics)
        phases = self.num_agents + 1
        agent_log_ratio = new_log_probs - batch.log_probs
        entropies = self.distribution(params, batch.obs, batch.action_mask).entropy()
        return params, state, {
            **metrics,
            **policy_diagnostics(
                agent_log_ratio, jnp.sum(agent_log_ratio, axis=-1), ppo.clip_eps,
                entropies, batch.alive,
            ),
            "value_loss": critic_metrics["value_loss"],
            "loss": metrics["loss"] + critic_metrics["loss"],
            "grad_norm": (jnp.sum(agent_metrics["grad_norm"]) + critic_metrics["grad_norm"])
            / phases,
            "grad_norm_critic": critic_metrics["grad_norm_critic"],
        }
