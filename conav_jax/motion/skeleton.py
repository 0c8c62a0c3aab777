"""The 22-joint HumanML3D skeleton: joint names, kinematic tree, rest pose and body capsules.

Motion (rig, clips, gait and humanml3d in conav_jax.motion) produces joint positions in this
layout; the simulator (envs.humanoid) turns them into capsules via `CAPSULE_BONES` /
`capsule_segments`.
World convention: Z-up, metres, floor at z=0, the rest pose faces +x with its left side at +y.
"""

from __future__ import annotations

import numpy as np

JOINT_NAMES: tuple[str, ...] = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
)
NUM_JOINTS = len(JOINT_NAMES)
JOINT_INDEX: dict[str, int] = {name: i for i, name in enumerate(JOINT_NAMES)}
J = JOINT_INDEX  # short alias for index tables below

# Parent of each joint (HumanML3D / SMPL kinematic chain); -1 marks the root (pelvis).
PARENTS: tuple[int, ...] = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)


def _rest_pose() -> np.ndarray:
    """Standing, facing +x, arms hanging slightly away from the body, ~1.75 m to the crown.

    Foot joints (toe bases) sit 2 cm above the floor and ankles 8 cm: joint centres, not soles.
    """
    left = {
        "left_hip": (0.0, 0.09, 0.86),
        "left_knee": (0.015, 0.10, 0.48),
        "left_ankle": (-0.03, 0.105, 0.08),
        "left_foot": (0.10, 0.115, 0.02),
        "left_collar": (0.0, 0.075, 1.42),
        "left_shoulder": (0.0, 0.19, 1.43),
        "left_elbow": (-0.02, 0.26, 1.15),
        "left_wrist": (0.02, 0.30, 0.90),
    }
    centre = {
        "pelvis": (0.0, 0.0, 0.95),
        "spine1": (-0.01, 0.0, 1.07),
        "spine2": (-0.005, 0.0, 1.20),
        "spine3": (0.0, 0.0, 1.26),
        "neck": (0.0, 0.0, 1.50),
        "head": (0.03, 0.0, 1.62),
    }
    pose = np.zeros((NUM_JOINTS, 3), np.float64)
    for name, xyz in centre.items():
        pose[J[name]] = xyz
    for name, (x, y, z) in left.items():
        pose[J[name]] = (x, y, z)
        pose[J[name.replace("left_", "right_")]] = (x, -y, z)
    return pose.astype(np.float32)


REST_POSE: np.ndarray = _rest_pose()
REST_POSE.setflags(write=False)

# (joint_i, joint_j, radius_m): the body as capsules between joint pairs, for contacts and the
# renderer. The head capsule runs neck -> head and is extended past the head joint (see below).
CAPSULE_BONES: tuple[tuple[int, int, float], ...] = (
    (J["pelvis"], J["neck"], 0.14),  # torso
    (J["neck"], J["head"], 0.09),  # head (extended)
    (J["left_shoulder"], J["right_shoulder"], 0.06),  # shoulder girdle: the torso's width
    (J["left_shoulder"], J["left_elbow"], 0.05),
    (J["right_shoulder"], J["right_elbow"], 0.05),
    (J["left_elbow"], J["left_wrist"], 0.04),
    (J["right_elbow"], J["right_wrist"], 0.04),
    (J["left_hip"], J["left_knee"], 0.075),
    (J["right_hip"], J["right_knee"], 0.075),
    (J["left_knee"], J["left_ankle"], 0.055),
    (J["right_knee"], J["right_ankle"], 0.055),
)
HEAD_CAPSULE = 1  # index into CAPSULE_BONES
# The head joint sits near the middle of the skull; the capsule's far end goes this far beyond
# it along neck -> head so the crown (end + radius) reaches ~1.75 m in the rest pose.
HEAD_EXTENSION_M = 0.05

_CAP_I = np.asarray([b[0] for b in CAPSULE_BONES])
_CAP_J = np.asarray([b[1] for b in CAPSULE_BONES])
_CAP_R = np.asarray([b[2] for b in CAPSULE_BONES], np.float32)


def capsule_segments(joints):
    """Capsule end points and radii for joint positions.

    joints (..., 22, 3) metres -> (p0 (..., C, 3), p1 (..., C, 3), radius_m (C,)), C =
    len(CAPSULE_BONES). Uses only array methods and operators, so numpy and jax arrays both work.
    """
    p0 = joints[..., _CAP_I, :]
    p1 = joints[..., _CAP_J, :]
    d = p1[..., HEAD_CAPSULE, :] - p0[..., HEAD_CAPSULE, :]
    length = (d * d).sum(-1, keepdims=True) ** 0.5
    head_end = p1[..., HEAD_CAPSULE, :] + d * (HEAD_EXTENSION_M / (length + 1e-9))
    mask = (np.arange(len(CAPSULE_BONES)) == HEAD_CAPSULE).astype(np.float32)[:, None]
    p1 = p1 * (1 - mask) + head_end[..., None, :] * mask
    return p0, p1, _CAP_R
