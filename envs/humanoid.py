"""The humanoid in the simulator: capsule body parts posed from keyframe joints, in JAX.

Keyframes (22 HumanML3D joints) -> capsule segments (conav_jax.skeleton.CAPSULE_BONES) ->
mocap body poses for MJX and segment ends for the fast caster. A capsule keeps the length of
its rest-pose bone (the MJX model's geom size is fixed), centred on the bone's midpoint and
aligned with it, so both sensors and the physics see the same shape.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from conav_jax.skeleton import CAPSULE_BONES, REST_POSE, capsule_segments

# Colours per capsule: skin for the head and forearms, shirt for torso and upper arms, trousers
# for the legs; distinct enough that a person reads as a person in the RGB panorama.
_SKIN, _SHIRT, _TROUSERS = (0.87, 0.68, 0.55), (0.85, 0.25, 0.2), (0.18, 0.22, 0.45)


def _rest_segments() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p0, p1, r = capsule_segments(REST_POSE[None])
    return np.asarray(p0[0]), np.asarray(p1[0]), np.asarray(r)


_P0, _P1, CAPSULE_RADII = _rest_segments()
NUM_CAPSULES = len(CAPSULE_RADII)
CAPSULE_HALF_LENGTHS = np.maximum(np.linalg.norm(_P1 - _P0, axis=-1) / 2.0, 0.01).astype(np.float32)


def capsule_colours() -> np.ndarray:
    """(C, 3) RGB in [0, 1] per capsule, chosen by where the capsule sits on the body."""
    out = []
    mid_z = (_P0[:, 2] + _P1[:, 2]) / 2
    for k in range(NUM_CAPSULES):
        i, j = CAPSULE_BONES[k][0], CAPSULE_BONES[k][1]
        if mid_z[k] < 1.0 and max(_P0[k, 2], _P1[k, 2]) < 1.05:
            out.append(_TROUSERS)
        elif mid_z[k] > 1.5 or (abs(_P0[k, 1]) > 0.25 and min(_P0[k, 2], _P1[k, 2]) < 1.2):
            out.append(_SKIN)
        else:
            out.append(_SHIRT)
        del i, j
    return np.asarray(out, np.float32)


def capsule_poses(joints: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(centres (C, 3), unit axes (C, 3), ends (2, C, 3)) for world joints (22, 3)."""
    idx0 = np.asarray([b[0] for b in CAPSULE_BONES])
    idx1 = np.asarray([b[1] for b in CAPSULE_BONES])
    a, b = joints[idx0], joints[idx1]
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
