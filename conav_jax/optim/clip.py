"""Gradient clipping by the global L2 norm over every leaf of a pytree."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

PyTree = Any


def global_norm(tree: PyTree) -> jax.Array:
    """`sqrt(sum of squares of every element of every leaf)`, a scalar (computed in float32
    or wider, whatever the leaves' dtype)."""
    leaves = jax.tree_util.tree_leaves(tree)
    sq = [jnp.sum(jnp.square(jnp.asarray(x, jnp.promote_types(x.dtype, jnp.float32)))) for x in leaves]
    return jnp.sqrt(sum(sq, jnp.zeros((), jnp.float32)))


def clip_by_global_norm(grads: PyTree, max_norm: float) -> tuple[PyTree, jax.Array]:
    """Scale all of `grads` by `min(1, max_norm / norm)` -> `(clipped, norm)`; `norm` is the
    norm before clipping (log it). The direction of the update is kept."""
    norm = global_norm(grads)
    # max(norm, max_norm) as denominator: scale is exactly 1 under the limit, never 0/0.
    scale = max_norm / jnp.maximum(norm, max_norm)
    return jax.tree_util.tree_map(lambda g: (g * scale).astype(g.dtype), grads), norm
