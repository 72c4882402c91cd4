"""The Sable network (Mahjoub et al. 2025): MAT's encoder-decoder with retention for attention.

O --RMSNorm, Dense, GELU--> blocks of [full retention over the agents, SwiGLU] --> Ô --> V(ô_i)
a^(k-1) --embed--> blocks of [causal self-retention over the action tokens, causal retention
from ô_k to them, SwiGLU] --> π_k(· | O, a^(<k))

Every sublayer is post-normalised with RMSNorm, as in the reference (mava/networks/
sable_network.py). Retention (cmat.networks.retention) has no softmax, so the decoder acts agent
by agent with a [hs, hs] state per retention instead of MAT's growing key/value cache: memory
linear in the number of agents. With `memory` the states also carry across the timesteps of an
episode (decayed by κ each step, reset at episode starts) and every retention adds the
sinusoidal encoding of the episode's timestep (the reference's `rec_sable`); without it (the
reference's `ff_sable`) every timestep starts from empty states.

Sequence methods take T timesteps of one team ([T, n, ...]); `encode`, `decode`, `value` and
`__call__` take one timestep and a decision order, as `cmat.algorithms.mat.network.MATNetwork`
does, so the MAT algorithm's acting and loss code runs on either network
(`cmat.algorithms.mat.algorithm.EncoderDecoder`).
"""

from __future__ import annotations

from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from cmat.algorithms.mat.network import MATOutput
from cmat.config import NetworkConfig
from cmat.networks.heads import (
    decode_in_order,
    mask_unavailable,
    previous_action_features,
    start_action,
)
from cmat.networks.layers import SMALL_GAIN, dense
from cmat.networks.retention import MultiScaleRetention, sinusoidal_encoding


class SableMemory(NamedTuple):
    """Retention states of one team, each [n_block, H, hs, hs]: the state after the last
    timestep acted (before its decay into the next)."""

    encoder: jax.Array
    tokens: jax.Array
    """The decoder's self-retention over action tokens."""
    cross: jax.Array
    """The decoder's retention from the agents' encodings to the action features."""


def empty_memory(config: NetworkConfig) -> SableMemory:
    """Sable's states before an episode's first step, [n_block, H, hs, hs] each."""
    size = config.n_embd // config.n_head
    empty = jnp.zeros((config.n_block, config.n_head, size, size))
    return SableMemory(empty, empty, empty)


class SwiGLU(nn.Module):
    """(swish(x W_gate) ⊙ x W_linear) W_output with every weight zero at initialisation, as the
    reference (mava/networks/torsos.py). All three gradients are then zero too, so the block
    stays the zero map through training; cmat keeps it so the network is the reference's."""

    n_embd: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        shape = (self.n_embd, self.n_embd)
        w_linear = self.param("W_linear", nn.initializers.zeros, shape)
        w_gate = self.param("W_gate", nn.initializers.zeros, shape)
        w_output = self.param("W_output", nn.initializers.zeros, shape)
        out: jax.Array = (jax.nn.swish(x @ w_gate) * (x @ w_linear)) @ w_output
        return out


class Retention(nn.Module):
    """`MultiScaleRetention` with Sable's optional timestep encoding added to its inputs."""

    n_embd: int
    n_head: int
    causal: bool
    decay_scale: float
    timestep_encoding: bool
    chunk_steps: int | None = None
    """Timesteps per chunk of the training form (None: all at once)."""

    def setup(self) -> None:
        self.retention = MultiScaleRetention(
            self.n_embd, self.n_head, self.causal, self.decay_scale
        )

    def encode(self, x: jax.Array, encoding: jax.Array) -> jax.Array:
        """x plus the timestep `encoding` (broadcast to it) when this retention uses one."""
        return x + encoding if self.timestep_encoding else x

    def __call__(
        self, query: jax.Array, key: jax.Array, state: jax.Array, starts: jax.Array,
        positions: jax.Array,
    ) -> tuple[jax.Array, jax.Array]:
        """[T, N, d] query and key (the value is the key); positions [T]."""
        encoding = sinusoidal_encoding(positions, self.n_embd)[:, None, :]
        query, key = self.encode(query, encoding), self.encode(key, encoding)
        return self.retention(query, key, key, state, starts, self.chunk_steps)

    def step(
        self, query: jax.Array, key: jax.Array, state: jax.Array, position: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """[c, d] tokens of one timestep at `position` []; `state` already decayed."""
        encoding = sinusoidal_encoding(position, self.n_embd)
        query, key = self.encode(query, encoding), self.encode(key, encoding)
        return self.retention.step(query, key, key, state)

    def decay(self, state: jax.Array, start: jax.Array) -> jax.Array:
        return self.retention.decay(state, start)


class SableEncodeBlock(nn.Module):
    """x = RMSNorm(x + Retention(x)); out = RMSNorm(x + SwiGLU(x)); retention over all agents."""

    n_embd: int
    n_head: int
    decay_scale: float
    timestep_encoding: bool
    chunk_steps: int | None = None

    def setup(self) -> None:
        self.retention = Retention(
            self.n_embd, self.n_head, False, self.decay_scale, self.timestep_encoding,
            self.chunk_steps,
        )
        self.norms = [nn.RMSNorm() for _ in range(2)]
        self.feed_forward = SwiGLU(self.n_embd)

    def finish(self, x: jax.Array, retained: jax.Array) -> jax.Array:
        x = self.norms[0](x + retained)
        out: jax.Array = self.norms[1](x + self.feed_forward(x))
        return out

    def __call__(
        self, x: jax.Array, state: jax.Array, starts: jax.Array, positions: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        retained, state = self.retention(x, x, state, starts, positions)
        return self.finish(x, retained), state

    def step(
        self, x: jax.Array, state: jax.Array, position: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        retained, state = self.retention.step(x, x, state, position)
        return self.finish(x, retained), state


class SableDecodeBlock(nn.Module):
    """x = RMSNorm(t + Retention(t)) causal over the action tokens t;
    y = RMSNorm(ô + Retention(query=ô, key=value=x)) causal; out = RMSNorm(y + SwiGLU(y))."""

    n_embd: int
    n_head: int
    decay_scale: float
    timestep_encoding: bool
    chunk_steps: int | None = None

    def setup(self) -> None:
        self.token_retention = Retention(
            self.n_embd, self.n_head, True, self.decay_scale, self.timestep_encoding,
            self.chunk_steps,
        )
        self.agent_retention = Retention(
            self.n_embd, self.n_head, True, self.decay_scale, self.timestep_encoding,
            self.chunk_steps,
        )
        self.norms = [nn.RMSNorm() for _ in range(3)]
        self.feed_forward = SwiGLU(self.n_embd)

    def __call__(
        self, tokens: jax.Array, agents: jax.Array, states: tuple[jax.Array, jax.Array],
        starts: jax.Array, positions: jax.Array,
    ) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
        retained, token_state = self.token_retention(
            tokens, tokens, states[0], starts, positions
        )
        x = self.norms[0](tokens + retained)
        crossed, cross_state = self.agent_retention(agents, x, states[1], starts, positions)
        y = self.norms[1](agents + crossed)
        return self.norms[2](y + self.feed_forward(y)), (token_state, cross_state)

    def step(
        self, token: jax.Array, agent: jax.Array, states: tuple[jax.Array, jax.Array],
        position: jax.Array,
    ) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
        """One agent: token and agent [1, d], the states after the agents before it."""
        retained, token_state = self.token_retention.step(token, token, states[0], position)
        x = self.norms[0](token + retained)
        crossed, cross_state = self.agent_retention.step(agent, x, states[1], position)
        y = self.norms[1](agent + crossed)
        return self.norms[2](y + self.feed_forward(y)), (token_state, cross_state)

    def decay(
        self, states: tuple[jax.Array, jax.Array], start: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        return (self.token_retention.decay(states[0], start),
                self.agent_retention.decay(states[1], start))


class SableNetwork(nn.Module):
    """Sable's actor-critic over one team (mava/networks/sable_network.py)."""

    config: NetworkConfig
    num_agents: int
    action_dim: int
    discrete: bool
    memory: bool = False
    """Carry retention states across timesteps (rec_sable); False: ff_sable."""
    decay_scale: float = 0.8
    """Sable's `decay_scaling_factor` (memory only: without it no decay is ever applied)."""
    chunk_steps: int | None = None
    """Timesteps per chunk of the training pass over a sequence (None: all at once)."""

    def setup(self) -> None:
        cfg = self.config
        d = cfg.n_embd
        self.obs_norm = nn.RMSNorm()
        self.obs_embedding = nn.Dense(
            d, use_bias=False, kernel_init=nn.initializers.orthogonal(jnp.sqrt(2.0))
        )
        self.encoder_norm = nn.RMSNorm()
        self.encoder_blocks = [
            SableEncodeBlock(d, cfg.n_head, self.decay_scale, self.memory, self.chunk_steps)
            for _ in range(cfg.n_block)
        ]
        self.value_hidden = dense(d)
        self.value_norm = nn.RMSNorm()
        self.value_out = dense(1, SMALL_GAIN)
        self.action_embedding = nn.Dense(
            d, use_bias=not self.discrete, kernel_init=nn.initializers.orthogonal(jnp.sqrt(2.0))
        )
        self.token_norm = nn.RMSNorm()
        self.decoder_blocks = [
            SableDecodeBlock(d, cfg.n_head, self.decay_scale, self.memory, self.chunk_steps)
            for _ in range(cfg.n_block)
        ]
        self.head_hidden = dense(d)
        self.head_norm = nn.RMSNorm()
        self.head_out = dense(self.action_dim, SMALL_GAIN)
        self.log_std = self.param(
            "log_std", nn.initializers.constant(cfg.log_std_init),
            (0 if self.discrete else self.action_dim,),
        )

    def initial_memory(self) -> SableMemory:
        """Empty states, [n_block, H, hs, hs] each."""
        return empty_memory(self.config)

    def embed_obs(self, obs: jax.Array) -> jax.Array:
        return nn.gelu(self.obs_embedding(self.obs_norm(obs)))

    def agent_values(self, encoded: jax.Array) -> jax.Array:
        hidden = self.value_norm(nn.gelu(self.value_hidden(encoded)))
        return self.value_out(hidden)[..., 0]

    def start_action(self) -> jax.Array:
        """The first agent of a timestep's token (`start_action`)."""
        return start_action(self.action_dim, self.discrete)

    def embed_actions(self, actions: jax.Array) -> jax.Array:
        features = previous_action_features(actions, self.action_dim, self.discrete)
        tokens: jax.Array = self.token_norm(nn.gelu(self.action_embedding(features)))
        return tokens

    def policy_params(
        self, features: jax.Array, action_mask: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        params = self.head_out(self.head_norm(nn.gelu(self.head_hidden(features))))
        return mask_unavailable(params, action_mask, self.discrete), self.log_std

    def encode_sequence(
        self, obs: jax.Array, memory: SableMemory, starts: jax.Array, positions: jax.Array
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Ô [T, n, d], V(ô_i) [T, n] and the encoder states after T timesteps of obs
        [T, n, obs_dim] (starts, positions [T])."""
        x = self.embed_obs(obs)
        states = []
        for layer, block in enumerate(self.encoder_blocks):
            x, state = block(self.encoder_norm(x), memory.encoder[layer], starts, positions)
            states.append(state)
        return x, self.agent_values(x), jnp.stack(states)

    def decode_sequence(
        self, encoded: jax.Array, action_mask: jax.Array, actions: jax.Array,
        memory: SableMemory, starts: jax.Array, positions: jax.Array,
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Teacher forcing over T timesteps, agents in index order: the policy parameters
        [T, n, A] of every agent given the actions [T, n(, A)] of the agents before it, and the
        decoder's token and cross states after the last timestep."""
        start = jnp.broadcast_to(self.start_action(), (actions.shape[0], 1, *actions.shape[2:]))
        x = self.embed_actions(jnp.concatenate([start, actions[:, :-1]], axis=1))
        token_states, cross_states = [], []
        for layer, block in enumerate(self.decoder_blocks):
            x, (token_state, cross_state) = block(
                x, encoded, (memory.tokens[layer], memory.cross[layer]), starts, positions
            )
            token_states.append(token_state)
            cross_states.append(cross_state)
        params, _ = self.policy_params(x, action_mask)
        return params, jnp.stack(token_states), jnp.stack(cross_states)

    def sequence(
        self, obs: jax.Array, action_mask: jax.Array, actions: jax.Array, memory: SableMemory,
        starts: jax.Array, positions: jax.Array,
    ) -> tuple[MATOutput, SableMemory]:
        """The training pass over T timesteps, agents in index order: outputs with a leading
        [T] axis (policy parameters [T, n, A], values [T, n], encodings [T, n, d]) and the
        memory after the last timestep."""
        encoded, values, encoder_states = self.encode_sequence(obs, memory, starts, positions)
        params, token_states, cross_states = self.decode_sequence(
            encoded, action_mask, actions, memory, starts, positions
        )
        output = MATOutput(params, self.log_std, values, encoded)
        return output, SableMemory(encoder_states, token_states, cross_states)

    def act_step(
        self, obs: jax.Array, action_mask: jax.Array, order: jax.Array, key: jax.Array | None,
        memory: SableMemory, start: jax.Array, position: jax.Array,
    ) -> tuple[jax.Array, jax.Array, jax.Array, SableMemory]:
        """One timestep acted agent by agent along `order` (sampled, or the most likely action
        when `key` is None), from `memory` after the previous timestep. Returns the actions
        and log-probs [n] in agent order, the per-agent values [n] and the new memory."""
        encoder_states = []
        x = self.embed_obs(obs)
        for layer, block in enumerate(self.encoder_blocks):
            state = block.retention.decay(memory.encoder[layer], start)
            x, state = block.step(self.encoder_norm(x), state, position)
            encoder_states.append(state)
        encoded = x
        values = self.agent_values(encoded)
        decoder_states = [
            block.decay((memory.tokens[layer], memory.cross[layer]), start)
            for layer, block in enumerate(self.decoder_blocks)
        ]
        actions, log_probs, decoder_states = self.decode_agents(
            encoded, action_mask, order, key, decoder_states, position
        )
        new_memory = SableMemory(
            jnp.stack(encoder_states),
            jnp.stack([states[0] for states in decoder_states]),
            jnp.stack([states[1] for states in decoder_states]),
        )
        return actions, log_probs, values, new_memory

    def decode_agents(
        self, encoded: jax.Array, action_mask: jax.Array, order: jax.Array,
        key: jax.Array | None, states: list[tuple[jax.Array, jax.Array]], position: jax.Array,
    ) -> tuple[jax.Array, jax.Array, list[tuple[jax.Array, jax.Array]]]:
        """The agents of one timestep act one after another along `order`, each action fed
        back (sampled, or the most likely one when `key` is None), from the decoder blocks'
        (token, cross) `states`. Returns actions and log-probs [n] in agent order and the
        states after the last agent."""
        actions, log_probs, states = decode_in_order(
            self, (encoded[order], position), states, action_mask, order, key,
            self.start_action(), self.discrete,
        )
        return actions, log_probs, states

    def decode_step(
        self, context: tuple[jax.Array, jax.Array], k: int | jax.Array, previous: jax.Array,
        states: list[tuple[jax.Array, jax.Array]],
    ) -> tuple[jax.Array, list[tuple[jax.Array, jax.Array]]]:
        """The decoder features [d] of the k-th agent to act, context = (encodings [n, d] in
        decision order, the timestep's position), given the previous agent's action and the
        decoder blocks' (token, cross) states after it."""
        agents, position = context
        x = self.embed_actions(previous[None])
        written = []
        for block, state in zip(self.decoder_blocks, states, strict=True):
            x, state = block.step(x, jax.lax.dynamic_slice_in_dim(agents, k, 1), state, position)
            written.append(state)
        return x[0], written

    def one_step(self) -> tuple[jax.Array, jax.Array]:
        """starts and positions of a lone timestep: [True] and [0]."""
        return jnp.ones((1,), bool), jnp.zeros((1,), jnp.int32)

    def encode(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Ô [n, d] and V(ô_i) [n] of one timestep from empty states."""
        encoded, values, _ = self.encode_sequence(
            obs[None], self.initial_memory(), *self.one_step()
        )
        return encoded[0], values[0]

    def value(self, obs: jax.Array) -> jax.Array:
        """The team value mean_i V(ô_i)."""
        return jnp.mean(self.encode(obs)[1], axis=-1)

    def decode(
        self, encoded: jax.Array, action_mask: jax.Array, order: jax.Array, key: jax.Array | None
    ) -> tuple[jax.Array, jax.Array]:
        """One timestep's actions and log-probs [n] along `order` from empty decoder states
        (`encoded` is `encode`'s)."""
        empty = self.initial_memory().tokens[0]
        actions, log_probs, _ = self.decode_agents(
            encoded, action_mask, order, key, [(empty, empty)] * len(self.decoder_blocks),
            jnp.zeros((), jnp.int32),
        )
        return actions, log_probs

    def __call__(
        self, obs: jax.Array, action_mask: jax.Array, actions: jax.Array, order: jax.Array
    ) -> MATOutput:
        """Teacher forcing over one timestep along `order`: every agent's distribution given
        the actions of those before it. The encoder is permutation-equivariant, so the agents
        are permuted into `order`, decoded in index order and permuted back."""
        inverse = jnp.argsort(order)
        encoded, values, _ = self.encode_sequence(
            obs[order][None], self.initial_memory(), *self.one_step()
        )
        params, _, _ = self.decode_sequence(
            encoded, action_mask[order][None], actions[order][None], self.initial_memory(),
            *self.one_step(),
        )
        return MATOutput(params[0][inverse], self.log_std, values[0][inverse],
                         encoded[0][inverse])
