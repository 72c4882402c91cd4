"""Multi-scale retention (Sun et al. 2023, RetNet) as Sable uses it (Mahjoub et al. 2025).

A sequence is T timesteps of N agent tokens each. Retention from token (t, i) to (s, j) weighs
q_(t,i)·k_(s,j) by κ^(t−s), where κ is the head's decay, and by 0 when (s, j) comes after
(t, i): a later timestep, a later agent of the same timestep in the causal (decoder) form, or an
earlier episode (`starts[t]` says timestep t begins a new one). No softmax, so the same output has
three forms, equal up to floating-point order (tests/test_sable.py):

- parallel: one [T·N, T·N] weighted product (`retention_parallel`; training, one chunk);
- chunkwise: the parallel form per chunk of timesteps, a [hs, hs] state carried between chunks
  (`retention_chunkwise`; training with bounded memory);
- recurrent: per timestep, decay the state by κ (reset it at an episode start), then add the
  agents' k^T v one by one (causal) or all at once (`MultiScaleRetention.decay` and `step`;
  acting).

As in Sable's reference (mava/networks/retention.py), the state carried into a sequence enters
timestep t as κ^(t+1)·S (the state is decayed once at every timestep before it is read), and
neither queries nor keys are scaled by 1/√d.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np


def head_decays(n_head: int, decay_scale: float) -> np.ndarray:
    """κ per head: 1 − exp(linspace(log 1/32, log 1/512, H)) · `decay_scale` (RetNet's decays,
    Sable's `decay_scaling_factor`; mava/networks/retention.py). [H] float32."""
    return ((1.0 - np.exp(np.linspace(np.log(1 / 32), np.log(1 / 512), n_head)))
            * decay_scale).astype(np.float32)


def _powers(kappa: jax.Array, exponents: jax.Array) -> jax.Array:
    """κ^e for integer e ≥ 0 (0 where e < 0, which callers mask anyway)."""
    return jnp.where(exponents >= 0, kappa ** jnp.maximum(exponents, 0), 0.0)


def retention_parallel(
    q: jax.Array, k: jax.Array, v: jax.Array, state: jax.Array, kappa: jax.Array,
    starts: jax.Array, causal: bool,
) -> tuple[jax.Array, jax.Array]:
    """One head over T timesteps at once.

    q, k, v [T, N, hs]; state [hs, hs] carried in; kappa []; starts [T] bool. Returns the
    outputs [T, N, hs] and the state after the last timestep [hs, hs].
    """
    num_steps, num_agents, _ = q.shape
    steps = jnp.arange(num_steps)
    episode = jnp.cumsum(starts.astype(jnp.int32))
    gap = steps[:, None] - steps[None, :]
    time_weights = _powers(kappa, gap) * (episode[:, None] == episode[None, :])
    agent_mask = (jnp.tril(jnp.ones((num_agents, num_agents))) if causal
                  else jnp.ones((num_agents, num_agents)))
    same_step = jnp.eye(num_steps)[:, None, :, None]
    weights = time_weights[:, None, :, None] * jnp.where(
        same_step > 0, agent_mask[None, :, None, :], 1.0
    )
    scores = jnp.einsum("tih,sjh->tisj", q, k) * weights
    inner = jnp.einsum("tisj,sjh->tih", scores, v)
    untouched = jnp.cumsum(starts.astype(jnp.int32)) == 0
    carried = (_powers(kappa, steps + 1) * untouched)[:, None, None]
    outputs = inner + carried * jnp.einsum("tih,hg->tig", q, state)
    last = num_steps - 1
    to_end = _powers(kappa, last - steps) * (episode == episode[last])
    new_state = jnp.einsum("tjh,tjg->hg", k * to_end[:, None, None], v)
    keep = _powers(kappa, jnp.asarray(num_steps)) * ~jnp.any(starts)
    return outputs, new_state + keep * state


def retention_chunkwise(
    q: jax.Array, k: jax.Array, v: jax.Array, state: jax.Array, kappa: jax.Array,
    starts: jax.Array, causal: bool, chunk_steps: int,
) -> tuple[jax.Array, jax.Array]:
    """`retention_parallel` over chunks of `chunk_steps` timesteps, the last one shorter where
    `chunk_steps` does not divide T (a value pass covers a rollout's T + 1 steps), the state
    carried from chunk to chunk: memory O(chunk²) instead of O(T²). Same shapes."""
    full = q.shape[0] // chunk_steps * chunk_steps

    def chunk(
        state: jax.Array, xs: tuple[jax.Array, jax.Array, jax.Array, jax.Array]
    ) -> tuple[jax.Array, jax.Array]:
        q_c, k_c, v_c, starts_c = xs
        out, state = retention_parallel(q_c, k_c, v_c, state, kappa, starts_c, causal)
        return state, out

    def split(x: jax.Array) -> jax.Array:
        return x[:full].reshape(full // chunk_steps, chunk_steps, *x.shape[1:])

    parts = []
    if full:
        state, outputs = jax.lax.scan(chunk, state, (split(q), split(k), split(v), split(starts)))
        parts.append(outputs.reshape(full, *outputs.shape[2:]))
    if full < q.shape[0]:
        rest, state = retention_parallel(q[full:], k[full:], v[full:], state, kappa,
                                         starts[full:], causal)
        parts.append(rest)
    return jnp.concatenate(parts), state


def decay_state(state: jax.Array, kappa: jax.Array, start: jax.Array) -> jax.Array:
    """The state entering a timestep: κ·S, or zeros when the timestep starts an episode."""
    return jnp.where(start, 0.0, kappa * state)


def retention_step(state: jax.Array, k: jax.Array, v: jax.Array) -> jax.Array:
    """S + K^T V for the tokens k, v [c, hs] added at once."""
    return state + k.T @ v


def sinusoidal_encoding(positions: jax.Array, n_embd: int) -> jax.Array:
    """The Transformer's sine/cosine encoding of integer positions [...] -> [..., n_embd] (Sable's
    timestep encoding, mava/networks/utils/sable/positional_encoding.py)."""
    rates = np.exp(np.arange(0, n_embd, 2) * (-np.log(10000.0) / n_embd))
    angles = positions[..., None].astype(jnp.float32) * rates
    encoding = jnp.zeros((*positions.shape, n_embd))
    encoding = encoding.at[..., 0::2].set(jnp.sin(angles))
    return encoding.at[..., 1::2].set(jnp.cos(angles[..., : n_embd // 2]))


class MultiScaleRetention(nn.Module):
    """Sable's multi-scale retention block: H heads with decays `head_decays(H, decay_scale)`,
    a per-head GroupNorm, the swish gate of the key input and the output projection:
    out = (swish(X_key W_g) ⊙ GroupNorm(retention)) W_o (mava/networks/retention.py).

    Projections are [d, d] (the reference's per-head [d, d/H] side by side) initialised
    N(0, 1/d²) as the reference. The GroupNorm normalises each head's d/H channels (RetNet's
    definition; the reference's flax GroupNorm equals it at its default of one head).
    """

    n_embd: int
    n_head: int
    causal: bool
    decay_scale: float = 1.0

    def setup(self) -> None:
        init = nn.initializers.normal(stddev=1.0 / self.n_embd)
        shape = (self.n_embd, self.n_embd)
        self.w_q, self.w_k, self.w_v, self.w_g, self.w_o = (
            self.param(name, init, shape) for name in ("w_q", "w_k", "w_v", "w_g", "w_o")
        )
        self.group_norm = nn.LayerNorm(reduction_axes=-1, feature_axes=(-2, -1))
        self.kappas = jnp.asarray(head_decays(self.n_head, self.decay_scale))

    @property
    def head_size(self) -> int:
        return self.n_embd // self.n_head

    def heads(self, x: jax.Array, weight: jax.Array) -> jax.Array:
        """[..., d] -> [H, ..., hs]."""
        projected = (x @ weight).reshape(*x.shape[:-1], self.n_head, self.head_size)
        return jnp.moveaxis(projected, -2, 0)

    def finish(self, key: jax.Array, retained: jax.Array) -> jax.Array:
        """Heads [H, ..., hs] -> the gated, normalised, projected output [..., d]."""
        normed = self.group_norm(jnp.moveaxis(retained, 0, -2))
        merged = normed.reshape(*normed.shape[:-2], self.n_embd)
        out: jax.Array = (jax.nn.swish(key @ self.w_g) * merged) @ self.w_o
        return out

    def initial_state(self) -> jax.Array:
        """The empty state [H, hs, hs]."""
        return jnp.zeros((self.n_head, self.head_size, self.head_size))

    def __call__(
        self, query: jax.Array, key: jax.Array, value: jax.Array, state: jax.Array,
        starts: jax.Array, chunk_steps: int | None = None,
    ) -> tuple[jax.Array, jax.Array]:
        """Training form over T timesteps: tokens [T, N, d], state [H, hs, hs], starts [T] ->
        (outputs [T, N, d], state after them). `chunk_steps` bounds memory by the chunkwise
        form; None computes all T at once."""
        q, k, v = (self.heads(x, w) for x, w in ((query, self.w_q), (key, self.w_k),
                                                  (value, self.w_v)))
        if chunk_steps is None or chunk_steps >= query.shape[0]:
            retained, state = jax.vmap(
                retention_parallel, in_axes=(0, 0, 0, 0, 0, None, None)
            )(q, k, v, state, self.kappas, starts, self.causal)
        else:
            retained, state = jax.vmap(
                retention_chunkwise, in_axes=(0, 0, 0, 0, 0, None, None, None)
            )(q, k, v, state, self.kappas, starts, self.causal, chunk_steps)
        return self.finish(key, retained), state

    def step(
        self, query: jax.Array, key: jax.Array, value: jax.Array, state: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """Acting form: c tokens [c, d] of one timestep added to the (already decayed) state
        [H, hs, hs] at once; each token reads the state after its own addition, and in the
        causal form c must be 1 (agents are added one by one)."""
        q, k, v = (self.heads(x, w) for x, w in ((query, self.w_q), (key, self.w_k),
                                                  (value, self.w_v)))
        state = jax.vmap(retention_step)(state, k, v)
        return self.finish(key, jnp.einsum("hcx,hxg->hcg", q, state)), state

    def decay(self, state: jax.Array, start: jax.Array) -> jax.Array:
        """The state entering a new timestep: per head κ·S, or zeros at an episode start."""
        return jax.vmap(decay_state, in_axes=(0, 0, None))(state, self.kappas, start)
