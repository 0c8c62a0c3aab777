"""The rig: pose parameters -> 22 joint positions on the HumanML3D skeleton, bones at rest length.

Clips (clips.py) and the gait (gait.py) fill a pose dict per frame (pelvis, spine, neck, ankle and
wrist targets); `build_joints` sets the torso by forward kinematics and the limbs by two-bone IK.
numpy only, vectorised over time.
"""

from __future__ import annotations

import numpy as np

from conav_jax.motion.skeleton import NUM_JOINTS, PARENTS, REST_POSE, J

# ---------------------------------------------------------------------------------------------
# Skeleton constants (from the rest pose, so every generated pose keeps its bone lengths)

REST = REST_POSE.astype(np.float64)  # joint positions (22, 3) m, standing at the origin facing +x
_OFF = REST - REST[np.maximum(np.asarray(PARENTS), 0)]  # bone vector from the parent


def _pair(name: str) -> list[int]:
    """[left, right] joint indices of a limb joint."""
    return [J[f"left_{name}"], J[f"right_{name}"]]


_HIP, _KNEE, _ANKLE, _FOOT = _pair("hip"), _pair("knee"), _pair("ankle"), _pair("foot")
_COLLAR, _SHOULDER, _ELBOW, WRIST = _pair("collar"), _pair("shoulder"), _pair("elbow"), _pair("wrist")
PELVIS, _SPINE1, _SPINE2, _SPINE3 = J["pelvis"], J["spine1"], J["spine2"], J["spine3"]
_NECK, _HEAD = J["neck"], J["head"]
SIDE = np.array([1.0, -1.0])  # left, right: sign of +y
_L_THIGH = float(np.linalg.norm(_OFF[_KNEE[0]]))
_L_SHIN = float(np.linalg.norm(_OFF[_ANKLE[0]]))
_L_UPPER = float(np.linalg.norm(_OFF[_ELBOW[0]]))
_L_FORE = float(np.linalg.norm(_OFF[WRIST[0]]))
FOOT_OFFSET_M = _OFF[_FOOT]  # (2, 3) ankle -> toe base, foot flat, facing +x
ARM_HANG_M = REST[WRIST] - REST[_SHOULDER]  # (2, 3) wrist offset from the shoulder, hanging
ANKLE_HEIGHT_M = float(REST[_ANKLE[0], 2])  # ankle height with the foot flat
# Preferred elbow direction in the heading frame, the IK bends towards it: back, out and down
# for hands below the shoulder, forward, out and down for hands above it (hand to the face,
# arms overhead), blended on the hand's height so the elbow never flips between frames.
_ARM_POLE_LOW = np.array([[-0.3, 0.6, -0.75], [-0.3, -0.6, -0.75]])
_ARM_POLE_HIGH = np.array([[0.5, 0.7, -0.5], [0.5, -0.7, -0.5]])
_KNEE_POLE = np.array([[1.0, 0.25, 0.0], [1.0, -0.25, 0.0]])

# ---------------------------------------------------------------------------------------------
# Small vectorised helpers


def lerp(a, b, w):
    """a + (b - a) * w, with w (n,) broadcast over the trailing axes of a and b."""
    w = np.asarray(w)
    return a + (b - a) * w.reshape(w.shape + (1,) * (max(np.ndim(a), np.ndim(b)) - w.ndim))


def smoothstep(x):
    """Smoothstep on [0, 1], clamped outside."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def rotate_z(v, yaw):
    """Vectors (..., 3) rotated about +z by yaw (rad, broadcast against v[..., 0])."""
    c, s = np.cos(yaw), np.sin(yaw)
    x = c * v[..., 0] - s * v[..., 1]
    out = np.empty(x.shape + (3,))
    out[..., 0] = x
    out[..., 1] = s * v[..., 0] + c * v[..., 1]
    out[..., 2] = v[..., 2]
    return out


def rotate_y(v, pitch):
    """Vectors (..., 3) rotated about +y by pitch (rad); positive tips +z towards +x (bend
    forward, toe down)."""
    c, s = np.cos(pitch), np.sin(pitch)
    x = c * v[..., 0] + s * v[..., 2]
    out = np.empty(x.shape + (3,))
    out[..., 0] = x
    out[..., 1] = v[..., 1]
    out[..., 2] = -s * v[..., 0] + c * v[..., 2]
    return out


# Rotation matrices inside the builder are component-first, (3, 3, n): products and
# matrix-vector applications are then a few n-long ufunc calls, ~5x faster than stacked matmuls.


def _rot(yaw, pitch, roll):
    """Rz(yaw) Ry(pitch) Rx(roll) as (3, 3, n); roll positive tips +z towards -y."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _mm(a, b):
    """Product of (3, 3, n) rotations."""
    return (a[:, :, None] * b[None]).sum(1)


def _mv(a, v):
    """(3, 3, n) rotation applied to a constant vector v (3,) -> (n, 3)."""
    return (a * v[None, :, None]).sum(1).T


def _kf_segment(u, knots, values):
    """Periodic keyframes at cycle phase u in [0, 1): (from values, to values, eased weight).
    Knots increase from 0; the last segment eases back to values[0] at u = 1."""
    k = np.append(np.asarray(knots, np.float64), 1.0)
    v = np.asarray(values, np.float64)
    v = np.concatenate([v, v[:1]])
    i = np.clip(np.searchsorted(k, u, side="right") - 1, 0, len(k) - 2)
    return v[i], v[i + 1], smoothstep((u - k[i]) / (k[i + 1] - k[i]))


def keyframed(u, knots, values):
    """Keyframed values, smoothstep-eased between knots (see _kf_segment)."""
    a, b, w = _kf_segment(u, knots, values)
    return lerp(a, b, w)


def slerp(a, b, w):
    """Vectors (..., 3) turned from a to b along the great circle, lengths interpolated: an arm
    offset moved this way keeps the hand away from the shoulder (the IK stays well posed)."""
    la = np.linalg.norm(a, axis=-1, keepdims=True)
    lb = np.linalg.norm(b, axis=-1, keepdims=True)
    ua, ub = a / np.maximum(la, 1e-9), b / np.maximum(lb, 1e-9)
    w = np.asarray(w)
    w = w.reshape(w.shape + (1,) * (max(np.ndim(a), np.ndim(b)) - w.ndim))
    om = np.arccos(np.clip(np.sum(ua * ub, -1, keepdims=True), -1.0, 1.0))
    so = np.sin(om)
    ok = so > 1e-3
    ka = np.where(ok, np.sin((1 - w) * om) / np.where(ok, so, 1.0), 1 - w)
    kb = np.where(ok, np.sin(w * om) / np.where(ok, so, 1.0), w)
    u = ka * ua + kb * ub
    return u / np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-9) * ((1 - w) * la + w * lb)


def arc_lerp(a, b, w, side):
    """Wrist targets moving from a to b (absolute, (3,) or (n, 3)) on an arc around the side's
    rest shoulder rather than on a straight line through it."""
    sh = REST[_SHOULDER[side]]
    return sh + slerp(a - sh, b - sh, w)


def keyframed_hand(u, knots, points, side):
    """Keyframed wrist targets (absolute) moving on arcs around the rest shoulder."""
    a, b, w = _kf_segment(u, knots, points)
    return arc_lerp(a, b, w, side)


def _two_bone(root, target, l1, l2, pole):
    """Analytic two-bone IK: (mid, end) joints, bone lengths exactly l1 and l2; the end is
    pulled back along root -> target when out of reach, and the mid joint bends towards pole."""
    d = target - root
    dist = np.linalg.norm(d, axis=-1, keepdims=True)
    u = d / np.maximum(dist, 1e-9)
    dist = np.clip(dist, abs(l1 - l2) + 1e-4, l1 + l2 - 1e-4)
    cos_a = (l1 * l1 + dist * dist - l2 * l2) / (2 * l1 * dist)
    n = pole - np.sum(pole * u, -1, keepdims=True) * u
    n_len = np.linalg.norm(n, axis=-1, keepdims=True)
    # Pole along the limb: bend towards u x +y, a perpendicular (rare; keeps the IK defined).
    alt = np.stack([-u[..., 2], np.zeros_like(u[..., 0]), u[..., 0]], -1)
    alt = alt / np.maximum(np.linalg.norm(alt, axis=-1, keepdims=True), 1e-9)
    n = np.where(n_len > 1e-6, n / np.maximum(n_len, 1e-9), alt)
    mid = root + l1 * (cos_a * u + np.sqrt(1.0 - cos_a * cos_a) * n)
    return mid, root + dist * u


# ---------------------------------------------------------------------------------------------
# Pose parameters -> joints. A pose is a dict of per-frame arrays (time first):
#   heading (n,)        frame yaw: arms, poles and the pelvis are turned by it (rad)
#   pelvis (n, 3)       pelvis position (m)
#   pelvis_rot (n, 3)   twist (yaw on top of heading), pitch (forward +), roll (right +) (rad)
#   spine (n, 3)        yaw, pitch, roll summed over spine1..spine3 (rad)
#   neck (n, 3)         yaw, pitch, roll of the head (rad)
#   ankle (n, 2, 3)     ankle targets, left / right (m); the leg IK reaches for them
#   foot_pitch (n, 2)   toe down + (rad); foot_yaw (n, 2) absolute foot yaw (rad)
#   arm (n, 2, 3)       wrist target relative to the shoulder, in the heading frame (m)


def neutral_pose(n: int) -> dict[str, np.ndarray]:
    """Pose parameters of n frames standing still at the rest pose, at the origin facing +x."""
    z = np.zeros
    return {
        "heading": z(n),
        "pelvis": np.tile(REST[PELVIS], (n, 1)),
        "pelvis_rot": z((n, 3)),
        "spine": z((n, 3)),
        "neck": z((n, 3)),
        "ankle": np.tile(REST[_ANKLE], (n, 1, 1)),
        "foot_pitch": z((n, 2)),
        "foot_yaw": z((n, 2)),
        "arm": np.tile(ARM_HANG_M, (n, 1, 1)),
    }


def _torso(p) -> np.ndarray:
    """Joints (n, 22, 3) with the pelvis, hips, spine, neck, head, collars and shoulders set."""
    n = len(p["heading"])
    out = np.zeros((n, NUM_JOINTS, 3))
    rot = p["pelvis_rot"].T
    r_p = _rot(p["heading"] + rot[0], rot[1], rot[2])
    r_s = _rot(*(p["spine"].T / 3.0))  # the bend is spread evenly over the three spine joints
    r1 = _mm(r_p, r_s)
    r2 = _mm(r1, r_s)
    r3 = _mm(r2, r_s)
    out[:, PELVIS] = p["pelvis"]
    for j in _HIP + [_SPINE1]:
        out[:, j] = out[:, PELVIS] + _mv(r_p, _OFF[j])
    out[:, _SPINE2] = out[:, _SPINE1] + _mv(r1, _OFF[_SPINE2])
    out[:, _SPINE3] = out[:, _SPINE2] + _mv(r2, _OFF[_SPINE3])
    for j in [_NECK] + _COLLAR:
        out[:, j] = out[:, _SPINE3] + _mv(r3, _OFF[j])
    out[:, _HEAD] = out[:, _NECK] + _mv(_mm(r3, _rot(*p["neck"].T)), _OFF[_HEAD])
    for c, j in zip(_COLLAR, _SHOULDER):
        out[:, j] = out[:, c] + _mv(r3, _OFF[j])
    return out


def _foot_vec(yaw, pitch, side):
    """Ankle -> toe vector for the foot turned to yaw and pitched (toe down +), rad."""
    return rotate_z(rotate_y(FOOT_OFFSET_M[side], pitch), yaw)


def build_joints(p) -> np.ndarray:
    """Pose parameters -> joints (n, 22, 3) float64, every bone at its rest length."""
    out = _torso(p)
    heading = p["heading"][:, None]
    arm_target = out[:, _SHOULDER] + rotate_z(p["arm"], heading)
    up = p["arm"][..., 2] / np.maximum(np.linalg.norm(p["arm"], axis=-1), 1e-9)
    pole = _ARM_POLE_LOW + (_ARM_POLE_HIGH - _ARM_POLE_LOW) * smoothstep((up + 0.3) / 1.1)[..., None]
    elbow_pole = rotate_z(pole, heading)
    out[:, _ELBOW], out[:, WRIST] = _two_bone(out[:, _SHOULDER], arm_target, _L_UPPER, _L_FORE, elbow_pole)
    # Knees bend forward and a little outward, whatever the pelvis pitch (sitting, lying).
    knee_pole = rotate_z(_KNEE_POLE, (p["heading"] + p["pelvis_rot"][:, 0])[:, None])
    out[:, _KNEE], out[:, _ANKLE] = _two_bone(out[:, _HIP], p["ankle"], _L_THIGH, _L_SHIN, knee_pole)
    for side in (0, 1):
        foot = _foot_vec(p["foot_yaw"][:, side], p["foot_pitch"][:, side], side)
        out[:, _FOOT[side]] = out[:, _ANKLE[side]] + foot
    return out


def hands_to_arm(p, hands: dict[int, np.ndarray]) -> None:
    """Set p["arm"] so the wrists reach the absolute targets `hands` {side: (n, 3)}."""
    if not hands:
        return
    shoulders = _torso(p)[:, _SHOULDER]
    for side, target in hands.items():
        p["arm"][:, side] = rotate_z(target - shoulders[:, side], -p["heading"])


def tiptoe(p, pitch, sides=(0, 1)) -> None:
    """Raise the heels by rolling the feet `pitch` (n,) rad about the toes; lifts the pelvis."""
    rise = []
    for side in sides:
        yaw = p["foot_yaw"][:, side]
        toe = p["ankle"][:, side] + _foot_vec(yaw, 0.0, side)
        ankle = toe - _foot_vec(yaw, pitch, side)
        rise.append(ankle[:, 2] - p["ankle"][:, side, 2])
        p["ankle"][:, side] = ankle
        p["foot_pitch"][:, side] = pitch
    p["pelvis"][:, 2] += np.mean(rise, axis=0)
