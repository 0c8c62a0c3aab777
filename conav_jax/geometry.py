"""Planar geometry shared by the simulator, the agents and the viewer (jax.numpy, jittable).

Poses are (x m, y m, yaw rad) in the world; yaw 0 faces +x, counter-clockwise positive. A
robot frame has +x ahead and +y to the robot's left. Functions take numpy or jax arrays and
broadcast over leading dimensions.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def wrap_angle(angle_rad: jax.Array) -> jax.Array:
    """Angles wrapped to [-pi, pi] radians."""
    return jnp.arctan2(jnp.sin(angle_rad), jnp.cos(angle_rad))


def to_frame(xy: jax.Array, origin_xy: jax.Array, yaw: jax.Array) -> jax.Array:
    """World points (..., 2) expressed in the frame at `origin_xy` rotated by `yaw`."""
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    d = xy - origin_xy
    return jnp.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def to_world(p_frame: jax.Array, pose: jax.Array) -> jax.Array:
    """Points (..., 2) of the frame at `pose` (x, y, yaw) back in the world: inverse of `to_frame`."""
    c, s = jnp.cos(pose[..., 2]), jnp.sin(pose[..., 2])
    x, y = p_frame[..., 0], p_frame[..., 1]
    return jnp.stack([c * x - s * y, s * x + c * y], axis=-1) + pose[..., :2]


def unit(v: jax.Array) -> jax.Array:
    """`v` (..., 2) scaled to length 1; zero where it is (nearly) zero."""
    n = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return jnp.where(n > 1e-6, v / jnp.maximum(n, 1e-6), 0.0)


def wrap_angle_np(angle_rad: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi) radians, in numpy: the twin of `wrap_angle` that offline data
    generation (conav_jax.motion) uses. A modulo rather than arctan2: the recorded episode
    datasets were generated with exactly this formula, and must keep their bytes."""
    return (np.asarray(angle_rad) + np.pi) % (2 * np.pi) - np.pi
