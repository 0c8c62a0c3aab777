"""Analytic robot contacts, for counting (MJX resolves the same contacts physically).

The robot is a vertical capsule (radius r, from the floor to its height); the human is a set
of capsules; walls and furniture are axis-aligned boxes standing on the floor. A contact is a
gap below `tol` metres: MJX's soft contacts let bodies interpenetrate slightly, so a touch shows
as a gap at or below zero.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def segment_distance(p1: jax.Array, q1: jax.Array, p2: jax.Array, q2: jax.Array) -> jax.Array:
    """Closest distance between segments p1-q1 and p2-q2 (..., 3), clamped closed form."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = jnp.sum(d1 * d1, -1)
    e = jnp.sum(d2 * d2, -1)
    f = jnp.sum(d2 * r, -1)
    c = jnp.sum(d1 * r, -1)
    b = jnp.sum(d1 * d2, -1)
    denom = a * e - b * b
    eps = 1e-12
    s = jnp.where(denom > eps, jnp.clip((b * f - c * e) / jnp.maximum(denom, eps), 0.0, 1.0), 0.0)
    t = (b * s + f) / jnp.maximum(e, eps)
    # t outside [0, 1]: clamp it and recompute s for the clamped t.
    t_c = jnp.clip(t, 0.0, 1.0)
    s = jnp.where(t != t_c, jnp.clip((t_c * b - c) / jnp.maximum(a, eps), 0.0, 1.0), s)
    t = t_c
    c1 = p1 + s[..., None] * d1
    c2 = p2 + t[..., None] * d2
    return jnp.linalg.norm(c1 - c2, axis=-1)


def robot_touches_capsules(xy, radius, height, cap_p0, cap_p1, cap_r, tol) -> jax.Array:
    """Whether the robot capsule at xy touches any capsule (C) given by ends and radii."""
    bottom = jnp.array([xy[0], xy[1], radius])
    top = jnp.array([xy[0], xy[1], height - radius])
    n = cap_p0.shape[0]
    dist = segment_distance(jnp.broadcast_to(bottom, (n, 3)), jnp.broadcast_to(top, (n, 3)), cap_p0, cap_p1)
    return jnp.any(dist - radius - cap_r < tol)


def robot_touches_boxes(xy, radius, box_lo, box_hi, box_valid, tol) -> jax.Array:
    """Whether the robot's footprint circle at xy touches any valid box's footprint (G)."""
    gap = jnp.maximum(jnp.maximum(box_lo[:, :2] - xy, xy - box_hi[:, :2]), 0.0)
    dist = jnp.linalg.norm(gap, axis=-1)
    return jnp.any(box_valid & (dist - radius < tol))
