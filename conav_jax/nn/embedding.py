"""Embeddings: a learned lookup table `ids (...) int -> (..., dim)`, and fixed sinusoidal
features of a (possibly fractional) position `(...) -> (..., dim)`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Params = dict[str, jax.Array]


def init(
    key: jax.Array,
    num_embeddings: int,
    dim: int,
    *,
    std: float = 0.02,
    dtype: jnp.dtype = jnp.float32,
) -> Params:
    """Table `(num_embeddings, dim)` drawn from N(0, std^2) (small, like token embeddings)."""
    return {"table": std * jax.random.normal(key, (num_embeddings, dim), dtype)}


def apply(params: Params, ids: jax.Array) -> jax.Array:
    """Rows of the table: `ids (...)` int in [0, num_embeddings) -> `(..., dim)`."""
    return jnp.take(params["table"], ids, axis=0)


def sinusoidal(
    positions: jax.Array, dim: int, *, max_period: float = 10_000.0, dtype=jnp.float32
) -> jax.Array:
    """Transformer position features: `positions (...)` -> `(..., dim)`, `dim` even.

    First half sin, second half cos, of `positions * max_period ** (-i / (dim / 2))`; wavelengths
    from 2 pi to `2 pi max_period` positions, so nearby positions get similar features.
    """
    if dim % 2:
        raise ValueError(f"sinusoidal embedding needs an even dim, got {dim}")
    half = dim // 2
    freqs = jnp.exp(-jnp.log(max_period) * jnp.arange(half, dtype=dtype) / half)
    angles = jnp.asarray(positions, dtype)[..., None] * freqs
    return jnp.concatenate([jnp.sin(angles), jnp.cos(angles)], axis=-1)
