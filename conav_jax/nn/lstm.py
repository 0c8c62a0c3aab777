"""LSTM cell and its time scan: `x (..., in_dim)`, carry `(h, c)` each `(..., hidden)`.

`lstm_scan` runs the cell over a time-major sequence with `lax.scan`; a per-step reset flag
zeroes the carry before that step, so sequences that cross episode boundaries can be trained
with truncated BPTT without leaking memory from one episode into the next.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

Params = dict[str, jax.Array]


class LSTMState(NamedTuple):
    """Recurrent carry: hidden `h` and cell `c`, each `(..., hidden)`."""

    h: jax.Array
    c: jax.Array


def init(
    key: jax.Array, in_dim: int, hidden: int, *, dtype: jnp.dtype = jnp.float32
) -> Params:
    """Gate order (input, forget, cell, output) along the last axis of `wi (in_dim, 4h)`,
    `wh (hidden, 4h)`, `b (4h,)`. LeCun-normal input weights; recurrent weights with
    orthonormal rows (as Keras does), which keeps the recurrence from blowing up or dying at
    init; forget-gate bias 1 (so the untrained cell remembers rather than forgets)."""
    ki, kh = jax.random.split(key)
    wi = jax.random.normal(ki, (in_dim, 4 * hidden), dtype) / math.sqrt(in_dim)
    wh = jax.nn.initializers.orthogonal()(kh, (hidden, 4 * hidden), dtype)
    b = jnp.zeros((4 * hidden,), dtype).at[hidden : 2 * hidden].set(1.0)
    return {"wi": wi, "wh": wh, "b": b}


def initial_state(
    batch_shape: tuple[int, ...], hidden: int, dtype: jnp.dtype = jnp.float32
) -> LSTMState:
    """All-zero carry of shape `(*batch_shape, hidden)`."""
    zeros = jnp.zeros((*batch_shape, hidden), dtype)
    return LSTMState(zeros, zeros)


def apply(params: Params, carry: LSTMState, x: jax.Array) -> tuple[LSTMState, jax.Array]:
    """One step: `x (..., in_dim)` -> `(new_carry, h (..., hidden))`."""
    gates = x @ params["wi"] + carry.h @ params["wh"] + params["b"]
    i, f, g, o = jnp.split(gates, 4, axis=-1)
    c = jax.nn.sigmoid(f) * carry.c + jax.nn.sigmoid(i) * jnp.tanh(g)
    h = jax.nn.sigmoid(o) * jnp.tanh(c)
    return LSTMState(h, c), h


def reset_state(carry: LSTMState, reset: jax.Array) -> LSTMState:
    """Zero the carry where `reset (...)` bool is True (an episode starts at this step)."""
    keep = ~reset[..., None]
    return LSTMState(jnp.where(keep, carry.h, 0.0), jnp.where(keep, carry.c, 0.0))


def lstm_scan(
    params: Params,
    carry: LSTMState,
    xs: jax.Array,
    resets: jax.Array | None = None,
) -> tuple[LSTMState, jax.Array]:
    """Run the cell over time-major `xs (T, ..., in_dim)` -> `(final_carry, hs (T, ..., hidden))`.

    `resets (T, ...)` bool: where True at step t, the carry is zeroed before step t reads it.
    """

    def step(carry: LSTMState, inputs: tuple[jax.Array, jax.Array | None]):
        x, reset = inputs
        if reset is not None:
            carry = reset_state(carry, reset)
        return apply(params, carry, x)

    return lax.scan(step, carry, (xs, resets))
