"""The humanoid in the simulator: capsule body parts posed from keyframe joints, in JAX.

Keyframes (22 HumanML3D joints) -> capsule segments (conav_jax.motion.skeleton.capsule_segments) ->
mocap body poses for MJX and segment ends for the fast caster and the contact test. A capsule
keeps the length of its rest-pose segment (an MJX geom's size is fixed), centred on the
segment's midpoint and aligned with it, so sensors, contacts and physics see the same shape.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from conav_jax.motion.skeleton import (
    CAPSULE_BONES,
    HEAD_CAPSULE,
    JOINT_NAMES,
    REST_POSE,
    capsule_segments,
)

_SKIN, _SHIRT, _TROUSERS = (0.87, 0.68, 0.55), (0.85, 0.25, 0.2), (0.18, 0.22, 0.45)

_P0, _P1, _R = capsule_segments(np.asarray(REST_POSE, np.float32))
CAPSULE_RADII = np.asarray(_R, np.float32)
CAPSULE_HALF_LENGTHS = np.maximum(np.linalg.norm(_P1 - _P0, axis=-1) / 2.0, 0.01).astype(np.float32)
NUM_CAPSULES = len(CAPSULE_BONES)


def capsule_groups() -> np.ndarray:
    """(C,) int: which clothing each capsule wears, 0 skin (head and forearms), 1 shirt (torso
    and upper arms), 2 trousers (the legs)."""
    out = []
    for k, (i, j, _) in enumerate(CAPSULE_BONES):
        names = JOINT_NAMES[i] + JOINT_NAMES[j]
        if "hip" in names or "knee" in names or "ankle" in names:
            out.append(2)
        elif k == HEAD_CAPSULE or "wrist" in names:
            out.append(0)
        else:
            out.append(1)
    return np.asarray(out, np.int32)


def capsule_colours() -> np.ndarray:
    """(C, 3) RGB in [0, 1] of the flat colours (capsule_groups: skin, shirt, trousers), so a
    person reads as a person in the RGB panorama."""
    return np.asarray((_SKIN, _SHIRT, _TROUSERS), np.float32)[capsule_groups()]


def capsule_poses(joints: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(centres (C, 3), unit axes (C, 3), ends (2, C, 3)) for world joints (22, 3)."""
    a, b, _ = capsule_segments(joints)
    centre = (a + b) / 2.0
    d = b - a
    n = jnp.linalg.norm(d, axis=-1, keepdims=True)
    axis = jnp.where(n > 1e-6, d / jnp.maximum(n, 1e-6), jnp.array([0.0, 0.0, 1.0]))
    half = jnp.asarray(CAPSULE_HALF_LENGTHS)[:, None]
    return centre, axis, jnp.stack([centre - half * axis, centre + half * axis])


def quat_z_to(axis: jax.Array) -> jax.Array:
    """Quaternions (w, x, y, z) (C, 4) rotating +z onto unit `axis` (C, 3)."""
    w = 1.0 + axis[:, 2]
    q = jnp.stack([w, -axis[:, 1], axis[:, 0], jnp.zeros_like(w)], axis=-1)
    flipped = w < 1e-6  # axis = -z: rotate by pi about x
    q = jnp.where(flipped[:, None], jnp.array([0.0, 1.0, 0.0, 0.0]), q)
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)
