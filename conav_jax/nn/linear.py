"""Dense layer: `x (..., in_dim) -> (..., out_dim)`, weights `w (in_dim, out_dim)`, bias `b (out_dim,)`.

Init is LeCun-normal (for ReLU/GELU stacks) or Glorot-uniform (for tanh/linear heads); bias zeros.
"""

from __future__ import annotations

import math
from typing import Literal

import jax
import jax.numpy as jnp

Params = dict[str, jax.Array]
Scheme = Literal["lecun", "glorot"]


def init(
    key: jax.Array,
    in_dim: int,
    out_dim: int,
    *,
    scheme: Scheme = "lecun",
    scale: float = 1.0,
    bias: bool = True,
    dtype: jnp.dtype = jnp.float32,
) -> Params:
    """Parameters of a dense layer. `scale` multiplies the initial weights (e.g. 0.01 for
    a policy's action head so that the untrained policy starts near zero action)."""
    if scheme == "lecun":
        w = jax.random.normal(key, (in_dim, out_dim), dtype) / math.sqrt(in_dim)
    elif scheme == "glorot":
        limit = math.sqrt(6.0 / (in_dim + out_dim))
        w = jax.random.uniform(key, (in_dim, out_dim), dtype, -limit, limit)
    else:
        raise ValueError(f"unknown init scheme {scheme!r}; expected 'lecun' or 'glorot'")
    params = {"w": scale * w}
    if bias:
        params["b"] = jnp.zeros((out_dim,), dtype)
    return params


def apply(params: Params, x: jax.Array) -> jax.Array:
    """`x (..., in_dim) -> (..., out_dim)`; any leading dims."""
    y = x @ params["w"]
    if "b" in params:
        y = y + params["b"]
    return y
