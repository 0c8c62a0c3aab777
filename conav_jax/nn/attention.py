"""Multi-head dot-product attention; queries from one input, keys/values from another.

`q_in (..., Lq, Dq)`, `kv_in (..., Lk, Dkv)`, `key_mask (..., Lk)` bool -> `(..., Lq, Dout)`.
Self-attention is `apply(p, x, x)`. Projections are stored per head (`wq (Dq, H, Dh)`, ...),
so the head count is read from the params' shapes, never passed again.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

Params = dict[str, jax.Array]


def init(
    key: jax.Array,
    q_dim: int,
    kv_dim: int,
    num_heads: int,
    head_dim: int,
    out_dim: int | None = None,
    *,
    dtype: jnp.dtype = jnp.float32,
) -> Params:
    """LeCun-normal projections (fan-in = input width; for the output, H * Dh); zero biases.
    `out_dim` defaults to `q_dim` so the result can be added back onto the queries.

    No output bias: attention weights sum to 1, so `bv` already passes through `wo` as one;
    leaving it out also makes a fully masked query return exact zeros."""
    out_dim = q_dim if out_dim is None else out_dim
    kq, kk, kv, ko = jax.random.split(key, 4)

    def proj(k: jax.Array, shape: tuple[int, ...], fan_in: int) -> jax.Array:
        return jax.random.normal(k, shape, dtype) / math.sqrt(fan_in)

    return {
        "wq": proj(kq, (q_dim, num_heads, head_dim), q_dim),
        "wk": proj(kk, (kv_dim, num_heads, head_dim), kv_dim),
        "wv": proj(kv, (kv_dim, num_heads, head_dim), kv_dim),
        "wo": proj(ko, (num_heads, head_dim, out_dim), num_heads * head_dim),
        "bq": jnp.zeros((num_heads, head_dim), dtype),
        "bk": jnp.zeros((num_heads, head_dim), dtype),
        "bv": jnp.zeros((num_heads, head_dim), dtype),
    }


def masked_softmax(logits: jax.Array, mask: jax.Array | None) -> jax.Array:
    """Softmax over the last axis where `mask` False entries get weight exactly 0.

    A row with no True entry gets all-zero weights (not NaN, not uniform), so a query that
    sees nothing contributes nothing. Finite sentinel instead of -inf keeps gradients finite.
    """
    if mask is None:
        return jax.nn.softmax(logits, axis=-1)
    logits = jnp.where(mask, logits, jnp.finfo(logits.dtype).min)
    # The max only stabilises exp; its gradient cancels analytically, so stop it.
    shift = jax.lax.stop_gradient(jnp.max(logits, axis=-1, keepdims=True))
    e = jnp.where(mask, jnp.exp(logits - shift), 0.0)
    denom = jnp.sum(e, axis=-1, keepdims=True)
    return e / jnp.where(denom > 0, denom, 1.0)


def apply(
    params: Params,
    q_in: jax.Array,
    kv_in: jax.Array,
    key_mask: jax.Array | None = None,
) -> jax.Array:
    """Attend from `q_in (..., Lq, Dq)` to `kv_in (..., Lk, Dkv)` -> `(..., Lq, Dout)`.

    `key_mask (..., Lk)` bool: False keys are ignored exactly (their values may be anything
    finite). A query whose keys are all masked returns exact zeros.
    """
    q = jnp.einsum("...qd,dhe->...hqe", q_in, params["wq"]) + params["bq"][:, None, :]
    k = jnp.einsum("...kd,dhe->...hke", kv_in, params["wk"]) + params["bk"][:, None, :]
    v = jnp.einsum("...kd,dhe->...hke", kv_in, params["wv"]) + params["bv"][:, None, :]
    logits = jnp.einsum("...hqe,...hke->...hqk", q, k) / math.sqrt(q.shape[-1])
    mask = None if key_mask is None else key_mask[..., None, None, :]
    weights = masked_softmax(logits, mask)
    heads = jnp.einsum("...hqk,...hke->...hqe", weights, v)
    return jnp.einsum("...hqe,hed->...qd", heads, params["wo"])
