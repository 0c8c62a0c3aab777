"""Import of HumanML3D `new_joints` motion (T, 22, 3), Y-up, as an activity clip for our world.

.npy file or array -> validated -> Z-up, floor at z=0, root's first xy at the origin, initial
facing turned to +x -> resampled from the source fps to the control rate -> (n, 22, 3) float32,
ready for `conav_jax.motion.compose_episode_motion(..., clip_a=...)`.
"""

from __future__ import annotations

import os

import numpy as np

from conav_jax.motion.skeleton import NUM_JOINTS, J

_FOOT_JOINTS = [J["left_ankle"], J["right_ankle"], J["left_foot"], J["right_foot"]]


def _facing_yaw(frame: np.ndarray) -> float:
    """Facing direction (rad, Z-up frame) of one pose: perpendicular to the left-minus-right
    hip and shoulder vectors, which point to the body's left (+y when facing +x)."""
    hips = frame[J["left_hip"]] - frame[J["right_hip"]]
    across = hips + frame[J["left_shoulder"]] - frame[J["right_shoulder"]]
    return float(np.arctan2(-across[0], across[1]))


def load_humanml3d_joints(
    source: str | os.PathLike | np.ndarray, fps: float = 20.0, dt_s: float = 0.1
) -> np.ndarray:
    """HumanML3D joint positions -> our local clip frames (n, 22, 3) float32, one every dt_s.

    source: a `.npy` path or an array (T, 22, 3) in HumanML3D's convention (metres, Y up, the
    body initially facing +Z, its left at +X); fps: its frame rate (HumanML3D: 20). Raises
    ValueError on a missing file, a wrong shape, fewer than 2 frames, non-finite values, or a
    non-positive fps or dt_s.
    """
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    if not (np.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"dt_s must be positive, got {dt_s}")
    if isinstance(source, (str, os.PathLike)):
        if not os.path.isfile(source):
            raise ValueError(f"HumanML3D joints file not found: {os.fspath(source)!r}")
        data = np.load(source, allow_pickle=False)
    else:
        data = np.asarray(source)
    if data.ndim != 3 or data.shape[1:] != (NUM_JOINTS, 3):
        raise ValueError(f"HumanML3D joints must have shape (T, {NUM_JOINTS}, 3), got {data.shape}")
    if len(data) < 2:
        raise ValueError(f"HumanML3D joints need at least 2 frames, got {len(data)}")
    data = data.astype(np.float64)
    bad = ~np.isfinite(data)
    if bad.any():
        first = int(np.argmax(bad.any(axis=(1, 2))))
        count = int(bad.sum())
        raise ValueError(f"HumanML3D joints hold {count} non-finite values, the first in frame {first}")

    # Y-up (x left, y up, z forward) -> Z-up (x forward, y left, z up): a cyclic permutation,
    # so handedness is kept.
    joints = data[..., [2, 0, 1]]
    joints[..., 2] -= joints[:, _FOOT_JOINTS, 2].min()
    joints[..., :2] -= joints[0, 0, :2]
    yaw = -_facing_yaw(joints[0])
    c, s = np.cos(yaw), np.sin(yaw)
    x, y = joints[..., 0].copy(), joints[..., 1].copy()
    joints[..., 0], joints[..., 1] = c * x - s * y, s * x + c * y

    # Resample by linear interpolation onto 0, dt_s, 2 dt_s, ... within the source's duration.
    duration_s = (len(joints) - 1) / fps
    t = np.arange(int(np.floor(duration_s / dt_s + 1e-9)) + 1) * dt_s
    src = t * fps
    i = np.minimum(src.astype(int), len(joints) - 2)
    w = (src - i)[:, None, None]
    return ((1 - w) * joints[i] + w * joints[i + 1]).astype(np.float32)
