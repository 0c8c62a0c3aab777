"""Layer normalisation over the last axis: `x (..., D) -> (..., D)` with learned `scale`, `bias (D,)`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

Params = dict[str, jax.Array]


def init(key: jax.Array | None, dim: int, *, dtype: jnp.dtype = jnp.float32) -> Params:
    """Unit scale, zero bias. `key` is unused; it keeps the `init(key, ...)` shape of every layer."""
    del key
    return {"scale": jnp.ones((dim,), dtype), "bias": jnp.zeros((dim,), dtype)}


def apply(params: Params, x: jax.Array, *, eps: float = 1e-5) -> jax.Array:
    """Normalise each vector along the last axis to zero mean, unit variance, then affine."""
    mean = jnp.mean(x, axis=-1, keepdims=True)
    var = jnp.mean(jnp.square(x - mean), axis=-1, keepdims=True)
    return (x - mean) * jax.lax.rsqrt(var + eps) * params["scale"] + params["bias"]
