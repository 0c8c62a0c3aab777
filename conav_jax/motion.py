"""Procedural humanoid motion on the 22-joint HumanML3D skeleton, at the control rate.

(activity id, primitive) -> `activity_clip` (local frame, object ahead at +x); path polyline ->
`walk_along` (world frame gait); both + standing poses -> `compose_episode_motion` -> HumanMotion
(activity A, walk, activity B). numpy only: offline data generation, vectorised over time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from conav_jax.config import MotionConfig
from conav_jax.primitives import MOTION_PRIMITIVES
from conav_jax.skeleton import J, NUM_JOINTS, PARENTS, REST_POSE

PHASE_A, PHASE_WALK, PHASE_B = 0, 1, 2

# ---------------------------------------------------------------------------------------------
# Skeleton constants (from the rest pose, so every generated pose keeps its bone lengths)

_REST = REST_POSE.astype(np.float64)
_OFF = _REST - _REST[np.maximum(np.asarray(PARENTS), 0)]  # bone vector from the parent


def _pair(name: str) -> list[int]:
    """[left, right] joint indices of a limb joint."""
    return [J[f"left_{name}"], J[f"right_{name}"]]


_HIP, _KNEE, _ANKLE, _FOOT = _pair("hip"), _pair("knee"), _pair("ankle"), _pair("foot")
_COLLAR, _SHOULDER, _ELBOW, _WRIST = _pair("collar"), _pair("shoulder"), _pair("elbow"), _pair("wrist")
_PELVIS, _SPINE1, _SPINE2, _SPINE3 = J["pelvis"], J["spine1"], J["spine2"], J["spine3"]
_NECK, _HEAD = J["neck"], J["head"]
_SIDE = np.array([1.0, -1.0])  # left, right: sign of +y
_L_THIGH = float(np.linalg.norm(_OFF[_KNEE[0]]))
_L_SHIN = float(np.linalg.norm(_OFF[_ANKLE[0]]))
_L_UPPER = float(np.linalg.norm(_OFF[_ELBOW[0]]))
_L_FORE = float(np.linalg.norm(_OFF[_WRIST[0]]))
_FOOT_OFF = _OFF[_FOOT]  # (2, 3) ankle -> toe base, foot flat, facing +x
_ARM_HANG = _REST[_WRIST] - _REST[_SHOULDER]  # (2, 3) wrist offset from the shoulder, hanging
_ANKLE_H = float(_REST[_ANKLE[0], 2])  # ankle height with the foot flat
# Preferred elbow direction in the heading frame, the IK bends towards it: back, out and down
# for hands below the shoulder, forward, out and down for hands above it (hand to the face,
# arms overhead), blended on the hand's height so the elbow never flips between frames.
_ARM_POLE_LOW = np.array([[-0.3, 0.6, -0.75], [-0.3, -0.6, -0.75]])
_ARM_POLE_HIGH = np.array([[0.5, 0.7, -0.5], [0.5, -0.7, -0.5]])
_KNEE_POLE = np.array([[1.0, 0.25, 0.0], [1.0, -0.25, 0.0]])

# Gait: stance share of a stride, heel-strike dorsiflexion and toe-off plantarflexion (rad),
# ankle ahead of the hip at heel strike (share of a step), swing clearance (m). The stance share
# is on the short side, so that the swinging foot (whose speed is speed / (1 - stance)) moves
# at most ~0.3 m per 0.1 s frame at 1.3 m/s.
_STANCE = 0.5
_HEEL_STRIKE_PITCH = -0.25
_TOE_OFF_PITCH = 0.9
_HEEL_OFF_AT = 0.33  # stance share after which the heel lifts and the foot rolls on the toe
_FLAT_AT = 0.12  # stance share by which the foot is flat after heel strike
_AHEAD = 0.4
_CLEARANCE_M = 0.06
_PELVIS_WALK_M = 0.93
_BOB_M = 0.015
_STEP_WIDTH_M = 0.105
_MAX_TURN_RADPS = 4.0  # fastest in-place turn during transitions
_TURN_HALF_M = 0.6  # the walking heading turns a right-angle corner over +-this much arc

# ---------------------------------------------------------------------------------------------
# Small vectorised helpers


def _lerp(a, b, w):
    """a + (b - a) * w, with w (n,) broadcast over the trailing axes of a and b."""
    w = np.asarray(w)
    return a + (b - a) * w.reshape(w.shape + (1,) * (max(np.ndim(a), np.ndim(b)) - w.ndim))


def _smooth(x):
    """Smoothstep on [0, 1], clamped outside."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _wrap(a):
    """Angle(s) to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _turn(v, yaw):
    """Vectors (..., 3) rotated about +z by yaw (rad, broadcast against v[..., 0])."""
    c, s = np.cos(yaw), np.sin(yaw)
    x = c * v[..., 0] - s * v[..., 1]
    out = np.empty(x.shape + (3,))
    out[..., 0] = x
    out[..., 1] = s * v[..., 0] + c * v[..., 1]
    out[..., 2] = v[..., 2]
    return out


def _tilt(v, pitch):
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
    return v[i], v[i + 1], _smooth((u - k[i]) / (k[i + 1] - k[i]))


def _kf(u, knots, values):
    """Keyframed values, smoothstep-eased between knots (see _kf_segment)."""
    a, b, w = _kf_segment(u, knots, values)
    return _lerp(a, b, w)


def _slerp(a, b, w):
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


def _arc_lerp(a, b, w, side):
    """Wrist targets moving from a to b (absolute, (3,) or (n, 3)) on an arc around the side's
    rest shoulder rather than on a straight line through it."""
    sh = _REST[_SHOULDER[side]]
    return sh + _slerp(a - sh, b - sh, w)


def _kf_hand(u, knots, points, side):
    """Keyframed wrist targets (absolute) moving on arcs around the rest shoulder."""
    a, b, w = _kf_segment(u, knots, points)
    return _arc_lerp(a, b, w, side)


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


def _neutral(n: int) -> dict[str, np.ndarray]:
    z = np.zeros
    return {
        "heading": z(n),
        "pelvis": np.tile(_REST[_PELVIS], (n, 1)),
        "pelvis_rot": z((n, 3)),
        "spine": z((n, 3)),
        "neck": z((n, 3)),
        "ankle": np.tile(_REST[_ANKLE], (n, 1, 1)),
        "foot_pitch": z((n, 2)),
        "foot_yaw": z((n, 2)),
        "arm": np.tile(_ARM_HANG, (n, 1, 1)),
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
    out[:, _PELVIS] = p["pelvis"]
    for j in _HIP + [_SPINE1]:
        out[:, j] = out[:, _PELVIS] + _mv(r_p, _OFF[j])
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
    return _turn(_tilt(_FOOT_OFF[side], pitch), yaw)


def _build(p) -> np.ndarray:
    """Pose parameters -> joints (n, 22, 3) float64, every bone at its rest length."""
    out = _torso(p)
    heading = p["heading"][:, None]
    arm_target = out[:, _SHOULDER] + _turn(p["arm"], heading)
    up = p["arm"][..., 2] / np.maximum(np.linalg.norm(p["arm"], axis=-1), 1e-9)
    pole = _ARM_POLE_LOW + (_ARM_POLE_HIGH - _ARM_POLE_LOW) * _smooth((up + 0.3) / 1.1)[..., None]
    elbow_pole = _turn(pole, heading)
    out[:, _ELBOW], out[:, _WRIST] = _two_bone(out[:, _SHOULDER], arm_target, _L_UPPER, _L_FORE, elbow_pole)
    # Knees bend forward and a little outward, whatever the pelvis pitch (sitting, lying).
    knee_pole = _turn(_KNEE_POLE, (p["heading"] + p["pelvis_rot"][:, 0])[:, None])
    out[:, _KNEE], out[:, _ANKLE] = _two_bone(out[:, _HIP], p["ankle"], _L_THIGH, _L_SHIN, knee_pole)
    for side in (0, 1):
        foot = _foot_vec(p["foot_yaw"][:, side], p["foot_pitch"][:, side], side)
        out[:, _FOOT[side]] = out[:, _ANKLE[side]] + foot
    return out


def _hands_to_arm(p, hands: dict[int, np.ndarray]) -> None:
    """Set p["arm"] so the wrists reach the absolute targets `hands` {side: (n, 3)}."""
    if not hands:
        return
    shoulders = _torso(p)[:, _SHOULDER]
    for side, target in hands.items():
        p["arm"][:, side] = _turn(target - shoulders[:, side], -p["heading"])


def _tiptoe(p, pitch, sides=(0, 1)) -> None:
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


# ---------------------------------------------------------------------------------------------
# Activity signatures and primitives


@dataclass(frozen=True)
class _Signature:
    """What makes one activity's clip its own; drawn from the activity id (+ small per-episode
    jitter)."""

    tempo: float  # multiplies the primitive's base frequency
    amp: float  # multiplies movement amplitudes
    side: int  # leading hand: 0 left, 1 right
    both: bool  # both hands act where the primitive allows
    height_m: float  # offset of the working height
    reach_m: float  # offset of the working distance ahead
    lateral_m: float  # offset of the working point sideways
    lean_rad: float  # posture: extra forward lean of the spine
    head_yaw_rad: float  # posture: head turned
    twist_rad: float  # posture: torso turned
    variant: int  # 0..2: a discrete style choice per primitive
    phase: float  # 0..1: where in its cycle the movement starts

    @property
    def sgn(self) -> float:
        return float(_SIDE[self.side])


_SIGNATURE_SALT = 0xC0DA  # keeps activity signatures independent of other seeded draws


def _signature(activity_id: int, rng: np.random.Generator) -> _Signature:
    """The activity's signature: fixed by its id, jittered a little by the episode's rng."""
    a = np.random.default_rng([_SIGNATURE_SALT, int(activity_id)])
    base = dict(
        tempo=a.uniform(0.75, 1.35),
        amp=a.uniform(0.7, 1.3),
        side=int(a.integers(2)),
        both=bool(a.random() < 0.35),
        height_m=a.uniform(-0.1, 0.1),
        reach_m=a.uniform(-0.06, 0.06),
        lateral_m=a.uniform(-0.08, 0.08),
        lean_rad=a.uniform(-0.06, 0.1),
        head_yaw_rad=a.uniform(-0.25, 0.25),
        twist_rad=a.uniform(-0.12, 0.12),
        variant=int(a.integers(3)),
        phase=a.uniform(0.0, 1.0),
    )
    # Per-episode variation: small enough that the activity stays recognisable.
    j = rng.normal(size=4)
    base["tempo"] *= math.exp(0.05 * j[0])
    base["amp"] *= math.exp(0.05 * j[1])
    base["height_m"] += 0.01 * j[2]
    base["phase"] = (base["phase"] + 0.05 * j[3]) % 1.0
    return _Signature(**base)


def _cycle(t, s: _Signature, base_hz: float):
    """Cycle phase u in [0, 1) of a movement at base_hz scaled by the activity's tempo."""
    return (t * base_hz * s.tempo + s.phase) % 1.0


def _wave(t, s: _Signature, base_hz: float, offset: float = 0.0):
    """Sine at base_hz scaled by the activity's tempo, shifted by `offset` cycles."""
    return np.sin(2 * np.pi * (t * base_hz * s.tempo + s.phase + offset))


def _hang(n, side):
    """Wrist targets (n, 3) of an arm hanging at rest."""
    return np.tile(_REST[_WRIST[side]], (n, 1))


# A primitive is f(t (n,) s, signature, p) -> {side: wrist target (n, 3)}: it edits p, a neutral
# pose (local frame, object ahead at +x), into the activity's full pose, and returns absolute
# targets for the wrists it moves. activity_clip then eases from neutral into it and back.


def _seated(p, s: _Signature) -> None:
    """Lower body sitting on a seat-height surface behind the standing point."""
    p["pelvis"][:] = (-0.22, 0.0, 0.52)
    p["ankle"][:, :, 0] = 0.12 + 0.03 * s.variant
    p["ankle"][:, :, 1] = _SIDE * 0.12
    p["spine"][:, 1] -= 0.05


def _stand_idle(t, s, p):
    sway = _wave(t, s, 0.25)
    p["pelvis"][:, 1] += 0.03 * s.amp * sway
    p["pelvis_rot"][:, 2] = -0.04 * s.amp * sway
    p["spine"][:, 2] = 0.03 * s.amp * sway
    p["neck"][:, 0] = 0.45 * s.amp * _wave(t, s, 0.11, 0.3)
    p["neck"][:, 1] = 0.08 * _wave(t, s, 0.07)
    n = len(t)
    if s.variant == 1:  # hands on the hips
        return {k: np.tile((-0.02, _SIDE[k] * 0.2, 0.98), (n, 1)) for k in (0, 1)}
    if s.variant == 2:  # arms crossed
        return {k: np.tile((0.2, -_SIDE[k] * 0.1, 1.2 + 0.03 * k), (n, 1)) for k in (0, 1)}
    return {}


def _reach_up(t, s, p):
    n = len(t)
    r = _kf(_cycle(t, s, 0.2), [0, 0.3, 0.6, 0.95], [0, 1, 1, 0])
    hands = {}
    for k in (0, 1) if s.both else (s.side,):
        top = np.array([0.2 + s.reach_m, _SIDE[k] * (0.22 + s.lateral_m), 1.85 + 0.5 * s.height_m])
        top = top + 0.03 * s.amp * _wave(t, s, 1.3, 0.25 * k)[:, None] * np.array([1.0, 0.0, 0.5])
        hands[k] = _arc_lerp(_hang(n, k), top, r, k)
    p["spine"][:, 1] -= 0.1 * r
    p["neck"][:, 1] = -0.35 * r
    if s.variant == 1:
        _tiptoe(p, 0.35 * r)
    return hands


def _reach_forward(t, s, p):
    n = len(t)
    r = _kf(_cycle(t, s, 0.25), [0, 0.3, 0.6, 0.85], [0, 1, 1, 0])
    push = 0.05 * s.amp * _wave(t, s, 0.9)
    hands = {}
    for i, k in enumerate((s.side, 1 - s.side) if s.both else (s.side,)):
        y, z = _SIDE[k] * (0.15 + s.lateral_m), 1.2 + s.height_m - 0.1 * i
        goal = np.stack([0.55 + s.reach_m + push, np.full(n, y), np.full(n, z)], -1)
        hands[k] = _arc_lerp(_hang(n, k), goal, r, k)
    p["spine"][:, 1] += 0.25 * r
    p["pelvis"][:, 0] -= 0.03 * r
    return hands


def _bend_down(t, s, p):
    n = len(t)
    b = _kf(_cycle(t, s, 0.15), [0, 0.35, 0.6, 0.9], [0, 1, 1, 0]) * min(s.amp, 1.1)
    p["pelvis"][:, 0] -= 0.13 * b
    p["pelvis"][:, 2] -= 0.15 * b
    p["pelvis_rot"][:, 1] = 0.55 * b
    p["spine"][:, 1] += 0.75 * b
    p["neck"][:, 1] = -0.3 * b
    hands = {}
    for k in (0, 1) if s.both or s.variant == 0 else (s.side,):
        low = (0.35 + s.reach_m, _SIDE[k] * 0.12 + s.lateral_m, 0.25 + max(s.height_m, 0.0))
        hands[k] = _arc_lerp(_hang(n, k), np.array(low), b, k)
    return hands


def _crouch(t, s, p):
    n = len(t)
    bob = 0.02 * _wave(t, s, 0.2)
    p["pelvis"][:] = np.stack([np.full(n, -0.12), np.zeros(n), 0.5 + bob + 0.5 * s.height_m * 0.3], -1)
    p["pelvis_rot"][:, 1] = 0.45
    p["spine"][:, 1] += 0.35
    p["neck"][:, 1] = -0.2
    p["ankle"][:, :, 1] = _SIDE * 0.14
    p["foot_yaw"][:] = _SIDE * 0.3
    if s.variant == 1:
        _tiptoe(p, np.full(n, 0.35))
    work = 0.06 * s.amp * np.stack([_wave(t, s, 0.5), _wave(t, s, 0.5, 0.25), np.zeros(n)], -1)
    hands = {}
    for k in (0, 1):
        base = np.array([0.3 + s.reach_m, _SIDE[k] * 0.15 + s.lateral_m, 0.25])
        hands[k] = base + (work if (k == s.side or s.both) else 0.0)
    return hands


def _sit(t, s, p):
    n = len(t)
    _seated(p, s)
    p["neck"][:, 0] = 0.4 * s.amp * _wave(t, s, 0.08)
    p["spine"][:, 1] += 0.02 * _wave(t, s, 0.25)  # breathing
    thigh = {k: np.tile((0.05, _SIDE[k] * 0.16, 0.62), (n, 1)) for k in (0, 1)}
    if s.variant == 1:  # holding something to read; the leading hand turns pages
        u = _cycle(t, s, 0.12)
        page = _kf(u, [0, 0.1, 0.2], [[0, 0, 0], [0.02, -_SIDE[s.side] * 0.12, 0.05], [0, 0, 0]])
        p["neck"][:, 1] = 0.35
        return {k: np.array((0.25, _SIDE[k] * 0.1, 0.85)) + (page if k == s.side else 0.0) for k in (0, 1)}
    if s.variant == 2:  # talking, the leading hand gesturing
        g = 0.08 * s.amp * np.stack([_wave(t, s, 0.6), _wave(t, s, 0.45, 0.3), _wave(t, s, 0.7, 0.6)], -1)
        thigh[s.side] = np.array((0.25, _SIDE[s.side] * 0.28, 0.95)) + g
    return thigh


def _lie_down(t, s, p):
    n = len(t)
    p["pelvis"][:] = (0.1, 0.0, 0.8)
    p["pelvis_rot"][:, 1] = 0.9
    p["spine"][:, 1] = 0.75 + 0.03 * _wave(t, s, 0.25)  # breathing
    p["ankle"][:, :, 0] = -0.2
    p["neck"][:, 0] = _SIDE[s.side] * 0.6
    p["neck"][:, 1] = -0.5
    if s.variant == 0:  # hands under the head
        return {k: np.tile((0.72, _SIDE[k] * 0.12, 0.72), (n, 1)) for k in (0, 1)}
    spread = 0.05 * s.amp * _wave(t, s, 0.1)
    return {k: np.stack([np.full(n, 0.55), _SIDE[k] * (0.35 + spread), np.full(n, 0.64)], -1) for k in (0, 1)}


def _wipe(t, s, p):
    n = len(t)
    a, b = 0.12 * s.amp * _wave(t, s, 0.8), 0.12 * s.amp * _wave(t, s, 0.8, 0.25)
    zero = np.zeros(n)
    if s.variant == 0:  # table: horizontal circles
        centre, path, lean = (0.5, 0.2, 0.92), np.stack([a, b, zero], -1), 0.3
    elif s.variant == 1:  # window or mirror: vertical circles
        centre, path, lean = (0.55, 0.2, 1.3), np.stack([zero, a, b], -1), 0.05
    else:  # long strokes sideways
        centre, path, lean = (0.5, 0.15, 0.92), np.stack([zero, 1.6 * a, zero], -1), 0.3
    centre = (centre[0] + s.reach_m, centre[1] + s.lateral_m, centre[2] + s.height_m)
    p["spine"][:, 1] += lean
    p["spine"][:, 0] = 0.8 * path[:, 1] * s.sgn
    p["pelvis"][:, 1] += 0.2 * path[:, 1]
    hands = {s.side: np.array((centre[0], s.sgn * centre[1], centre[2])) + path * np.array([1.0, s.sgn, 1.0])}
    other = 1 - s.side
    if s.both:
        mirrored = np.array((centre[0], -s.sgn * centre[1], centre[2]))
        hands[other] = mirrored - path * np.array([1.0, s.sgn, 1.0])
    elif s.variant != 1:  # rest the other hand on the surface
        hands[other] = np.tile((0.38, -s.sgn * 0.25, 0.93 + s.height_m), (n, 1))
    return hands


def _stir(t, s, p):
    n = len(t)
    r = 0.05 * s.amp
    a, b = _wave(t, s, 1.2), _wave(t, s, 1.2, 0.25 if s.variant != 1 else -0.25)
    if s.variant == 2:  # figure of eight
        b = _wave(t, s, 2.4, 0.25) * 0.6
    centre = np.array((0.42 + s.reach_m, s.sgn * (0.12 + s.lateral_m), 1.0 + 0.5 * s.height_m))
    p["spine"][:, 1] += 0.2
    p["neck"][:, 1] = 0.45
    pot = np.array((0.42 + s.reach_m, -s.sgn * 0.15, 0.98 + 0.5 * s.height_m))
    return {s.side: centre + r * np.stack([a, b, np.zeros(n)], -1), 1 - s.side: np.tile(pot, (n, 1))}


def _type(t, s, p):
    n = len(t)
    _seated(p, s)
    p["spine"][:, 1] += 0.15
    p["neck"][:, 1] = 0.25
    p["neck"][:, 0] = 0.15 * _wave(t, s, 0.1)
    shift = 0.04 * _wave(t, s, 0.15)
    hands = {}
    for k in (0, 1):
        tap = 0.012 * s.amp * _wave(t, s, 2.3, 0.37 * k)
        hands[k] = np.stack(
            [np.full(n, 0.30 + 0.5 * s.reach_m), _SIDE[k] * 0.13 + shift, 0.74 + 0.3 * s.height_m + tap], -1
        )
    if s.variant == 1:  # the leading hand on a mouse
        mouse = 0.03 * s.amp * np.stack([_wave(t, s, 0.4), _wave(t, s, 0.3, 0.2), np.zeros(n)], -1)
        hands[s.side] = np.array((0.3, s.sgn * 0.33, 0.74)) + mouse
    return hands


def _pick_and_place(t, s, p):
    u = _cycle(t, s, 0.2)
    k0 = s.side
    hang = _REST[_WRIST[k0]]
    a = (0.45 + s.reach_m, s.sgn * (0.2 + s.lateral_m), 0.85 + s.height_m)
    b = (0.45 + s.reach_m, -s.sgn * 0.05 + s.lateral_m, 0.85 + s.height_m)
    mid = (0.4, s.sgn * 0.08, 1.1 + s.height_m)
    knots = [0, 0.2, 0.3, 0.5, 0.65, 0.75, 0.9]
    path = _kf_hand(u, knots, [hang, a, a, mid, b, b, hang], k0)
    low = _kf(u, knots, [0, 1, 1, 0.4, 1, 1, 0])
    p["spine"][:, 1] += 0.3 * low * s.amp
    turn = 0.25 if s.variant == 2 else 0.5  # the torso turns towards the hand
    p["spine"][:, 0] = turn * np.arctan2(path[:, 1], np.maximum(path[:, 0], 0.1))
    hands = {k0: path}
    if s.both:  # a box: both hands on it
        hands[1 - k0] = path + np.array((0.0, -s.sgn * 0.3, 0.0)) * _smooth(4 * np.minimum(u, 1 - u))[:, None]
    return hands


def _carry(t, s, p):
    n = len(t)
    h = (1.12, 1.0, 1.25)[s.variant] + 0.5 * s.height_m
    p["pelvis"][:, 2] -= 0.02 + 0.01 * _wave(t, s, 0.8)
    p["pelvis"][:, 1] += 0.025 * _wave(t, s, 0.4)
    p["spine"][:, 1] -= 0.08
    p["spine"][:, 0] = 0.25 * s.amp * _wave(t, s, 0.12)
    p["neck"][:, 0] = 0.3 * s.amp * _wave(t, s, 0.12, 0.1)
    return {k: np.tile((0.32 + s.reach_m, _SIDE[k] * 0.16, h), (n, 1)) for k in (0, 1)}


def _open_door(t, s, p):
    u = _cycle(t, s, 0.18)
    k0 = s.side
    hang = _REST[_WRIST[k0]]
    handle = (0.55 + s.reach_m, s.sgn * (0.25 + s.lateral_m), 1.0 + s.height_m)
    mid = (0.38, s.sgn * 0.45, 1.0 + s.height_m)
    pulled = (0.15, s.sgn * 0.52, 1.0 + s.height_m)
    knots = [0, 0.2, 0.3, 0.45, 0.6, 0.8]
    hand = _kf_hand(u, knots, [hang, handle, handle, mid, pulled, pulled], k0)
    back = _kf(u, [0, 0.35, 0.55, 0.8, 0.99], [0, 0, -0.15, -0.15, 0.0])
    p["pelvis"][:, 0] += back
    p["spine"][:, 0] = s.sgn * 0.3 * _kf(u, knots, [0, 0, 0, 1, 1, 0])
    p["spine"][:, 1] += 0.15 * _kf(u, knots, [0, 1, 1, 0, 0, 0])
    # The feet step back one after the other while pulling, and forward again after.
    for k, (t0, t1) in enumerate(((0.35, 0.45), (0.45, 0.55))):
        side = k0 if k == 0 else 1 - k0
        go = _smooth((u - t0) / (t1 - t0)) - _smooth((u - (t0 + 0.45)) / (t1 - t0))
        lift = sum(np.sin(np.pi * np.clip((u - a) / (t1 - t0), 0, 1)) for a in (t0, t0 + 0.45))
        p["ankle"][:, side, 0] -= 0.15 * go
        p["ankle"][:, side, 2] += 0.06 * lift
    return {k0: hand}


def _look_in_mirror(t, s, p):
    n = len(t)
    p["neck"][:, 0] = 0.35 * s.amp * _wave(t, s, 0.15)
    p["neck"][:, 2] = 0.2 * s.amp * _wave(t, s, 0.23, 0.4)
    p["neck"][:, 1] = -0.05
    p["spine"][:, 1] += 0.1
    stroke = np.stack([np.zeros(n), 0.02 * _wave(t, s, 1.2), 0.04 * _wave(t, s, 1.2, 0.25)], -1)
    face = np.array((0.15, s.sgn * 0.08, 1.55 + 0.3 * s.height_m))
    hands = {s.side: face + stroke}
    if s.variant == 1:  # both hands at the hair
        hands[1 - s.side] = np.array((0.1, -s.sgn * 0.1, 1.62)) - stroke
    elif s.variant == 2:  # the other hand on the sink
        hands[1 - s.side] = np.tile((0.4, -s.sgn * 0.2, 0.9), (n, 1))
    return hands


def _arms_overhead_stretch(t, s, p):
    n = len(t)
    u = _cycle(t, s, 0.12)
    r = _kf(u, [0, 0.25, 0.75, 0.95], [0, 1, 1, 0])
    bend = s.amp * np.sin(2 * np.pi * 2 * u) * r
    if s.variant == 2:
        p["spine"][:, 0] = 0.4 * bend  # twists instead of side bends
    else:
        p["spine"][:, 2] = 0.3 * bend
        p["pelvis"][:, 1] += 0.03 * bend
    p["neck"][:, 1] = -0.2 * r
    if s.variant == 1:
        _tiptoe(p, 0.3 * r)
    return {k: _arc_lerp(_hang(n, k), np.array((0.05, _SIDE[k] * 0.12, 1.95)), r, k) for k in (0, 1)}


def _wash_body(t, s, p):
    u = _cycle(t, s, 0.2)
    rub = 0.03 * np.stack([np.zeros_like(t), _wave(t, s, 1.5), _wave(t, s, 1.5, 0.25)], -1)
    knots = [0, 0.2, 0.4, 0.6, 0.8]
    hands = {}
    for k in (0, 1):
        sg = _SIDE[k]
        # head, chest, belly, thigh, then back up in front of the body
        spots = [
            (0.08, sg * 0.08, 1.65),
            (0.17, sg * 0.05, 1.30),
            (0.17, -sg * 0.05, 1.05),
            (0.14, sg * 0.1, 0.75),
            (0.3, sg * 0.2, 1.2),
        ]
        hands[k] = _kf_hand((u + 0.5 * k * (s.variant != 0)) % 1.0, knots, spots, k) + rub
    low = _kf(u, knots, [0, 0, 0.3, 1, 0.2])
    p["spine"][:, 1] += 0.45 * low
    p["pelvis"][:, 0] -= 0.06 * low
    p["neck"][:, 1] = -0.25 * _kf(u, knots, [1, 0, 0, 0, 0])
    return hands


def _walk_in_place(t, s, p):
    w = _wave(t, s, 0.9)
    lift_m = (0.12, 0.25, 0.1)[s.variant] * s.amp
    for k, sg in ((0, 1.0), (1, -1.0)):
        up = np.maximum(0.0, sg * w) ** 2
        p["ankle"][:, k, 2] += lift_m * up
        p["ankle"][:, k, 0] += 0.03 * up
        p["foot_pitch"][:, k] = 0.3 * up
    p["pelvis"][:, 2] -= 0.015 * w * w
    p["pelvis_rot"][:, 2] = 0.03 * w
    swing = 0.4 * s.amp * w
    arm = _ARM_HANG * (0.6 if s.variant == 2 else 1.0)  # jogging: elbows bent
    for k, sg in ((0, -1.0), (1, 1.0)):
        p["arm"][:, k] = _tilt(arm[k], sg * swing)
    return {}


def _play_instrument(t, s, p):
    n = len(t)
    if s.variant == 1:  # guitar, standing: fretting hand out front, strumming hand at the belly
        fret = np.stack([np.full(n, 0.3), s.sgn * (0.4 + 0.04 * _wave(t, s, 0.3)), np.full(n, 1.2)], -1)
        strum_z = 1.05 + 0.08 * s.amp * _wave(t, s, 2.0)
        strum = np.stack([np.full(n, 0.2), np.full(n, -s.sgn * 0.05), strum_z], -1)
        p["neck"][:, 1] = 0.3
        p["pelvis"][:, 1] += 0.02 * _wave(t, s, 0.5)
        return {s.side: fret, 1 - s.side: strum}
    if s.variant == 0:
        _seated(p, s)
        height = 0.78
    else:  # keyboard at standing height
        height = 0.95
        p["spine"][:, 1] += 0.2
    p["spine"][:, 2] = 0.08 * s.amp * _wave(t, s, 0.4)
    p["neck"][:, 1] = 0.1 + 0.08 * _wave(t, s, 1.0)
    hands = {}
    for k in (0, 1):
        y = _SIDE[k] * 0.17 + 0.1 * s.amp * _wave(t, s, 0.3, 0.2 * k)
        tap = 0.015 * _wave(t, s, 2.0, 0.5 * k)
        hands[k] = np.stack([np.full(n, 0.32 + s.reach_m), y, height + 0.3 * s.height_m + tap], -1)
    return hands


def _drink(t, s, p):
    n = len(t)
    u = _cycle(t, s, 0.2)
    held = (0.25, s.sgn * 0.18, 1.0 + 0.3 * s.height_m)
    mouth = (0.14, s.sgn * 0.04, 1.52)
    knots = [0, 0.3, 0.55, 0.75]
    hand = _kf_hand(u, knots, [held, mouth, mouth, held], s.side)
    p["neck"][:, 1] = -0.35 * _kf(u, knots, [0, 1, 1, 0])
    p["spine"][:, 1] -= 0.05
    hands = {s.side: hand}
    if s.variant == 1:  # the other hand holds a plate
        hands[1 - s.side] = np.tile((0.28, -s.sgn * 0.15, 1.0), (n, 1))
    return hands


def _hang_on_wall(t, s, p):
    n = len(t)
    r = _kf(_cycle(t, s, 0.15), [0, 0.35, 0.7, 0.9], [0, 1, 1, 0])
    adjust = 0.04 * s.amp * _wave(t, s, 0.7) * r
    hands = {}
    for k in (0, 1):
        low = np.array((0.3, _SIDE[k] * 0.2, 1.0))
        wall_x, wall_z = np.full(n, 0.5 + s.reach_m), np.full(n, 1.65 + s.height_m)
        wall = np.stack([wall_x, _SIDE[k] * 0.25 + adjust, wall_z], -1)
        hands[k] = _arc_lerp(low, wall, r, k)
    p["neck"][:, 1] = -0.25 * r
    p["spine"][:, 1] -= 0.05
    if s.variant == 1:
        _tiptoe(p, 0.3 * r)
    return hands


_PRIMITIVES: dict[str, Callable] = {
    "stand_idle": _stand_idle,
    "reach_up": _reach_up,
    "reach_forward": _reach_forward,
    "bend_down": _bend_down,
    "crouch": _crouch,
    "sit": _sit,
    "lie_down": _lie_down,
    "wipe": _wipe,
    "stir": _stir,
    "type": _type,
    "pick_and_place": _pick_and_place,
    "carry": _carry,
    "open_door": _open_door,
    "look_in_mirror": _look_in_mirror,
    "arms_overhead_stretch": _arms_overhead_stretch,
    "wash_body": _wash_body,
    "walk_in_place": _walk_in_place,
    "play_instrument": _play_instrument,
    "drink": _drink,
    "hang_on_wall": _hang_on_wall,
}
assert set(_PRIMITIVES) == set(MOTION_PRIMITIVES), "motion.py must animate every primitive"

_RAMP_S = 1.0  # time to go from the neutral stance into the activity pose, and back


def activity_clip(
    activity_id: int, primitive: str, n_steps: int, rng: np.random.Generator, dt_s: float = 0.1
) -> np.ndarray:
    """An activity's keyframes (n_steps, 22, 3) float32 in the local frame: the human stands at
    the origin facing +x, the object in front at +x. Starts and ends in the neutral standing
    pose, so clips loop and blend; `rng` adds only small per-episode variation."""
    if primitive not in _PRIMITIVES:
        raise ValueError(f"unknown motion primitive {primitive!r}; expected one of {sorted(_PRIMITIVES)}")
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    sig = _signature(activity_id, rng)
    t = np.arange(n_steps) * dt_s
    active = _neutral(n_steps)
    hands = _PRIMITIVES[primitive](t, sig, active)
    active["spine"][:, 0] += sig.twist_rad
    active["spine"][:, 1] += sig.lean_rad
    active["neck"][:, 0] += sig.head_yaw_rad
    _hands_to_arm(active, hands)
    # Envelope: 0 at both ends (neutral pose), 1 once the activity pose is reached.
    end = t[-1]
    ramp = max(min(_RAMP_S, end / 3.0), 1e-9)
    env = _smooth(t / ramp) * _smooth((end - t) / ramp)
    neutral = _neutral(n_steps)
    pose = {k: _lerp(neutral[k], active[k], env) for k in neutral if k != "arm"}
    pose["arm"] = _slerp(neutral["arm"], active["arm"], env)
    return _build(pose).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Walking


class _Polyline:
    """Arc-length parametrised path, extrapolated straight past both ends."""

    def __init__(self, path_xy):
        pts = np.asarray(path_xy, np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) == 0 or not np.all(np.isfinite(pts)):
            raise ValueError(f"path_xy must be a finite (K, 2) array, K >= 1; got shape {pts.shape}")
        keep = np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9]
        pts = pts[keep]
        if len(pts) == 1:  # a standing "path": walk nowhere, facing +x
            pts = np.vstack([pts, pts + (1e-6, 0.0)])
        seg = np.diff(pts, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        self.pts = pts
        self.dirs = seg / seg_len[:, None]
        self.cum = np.r_[0.0, np.cumsum(seg_len)]
        self.length = float(self.cum[-1]) if keep.sum() > 1 else 0.0

        # Heading: the segments' directions, each corner's turn spread over +-_TURN_HALF_M of
        # arc per right angle (angles are smoothed, not vectors: a U-turn stays defined).
        angles = np.arctan2(self.dirs[:, 1], self.dirs[:, 0])
        self._yaw0 = float(angles[0])
        self._turns = _wrap(np.diff(angles))
        self._half_m = _TURN_HALF_M * np.maximum(1.0, np.abs(self._turns) / (np.pi / 2))
        self._corners = self.cum[1:-1]

    def _seg(self, s):
        return np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.dirs) - 1)

    def point(self, s):
        i = self._seg(s)
        return self.pts[i] + (s - self.cum[i])[..., None] * self.dirs[i]

    def heading(self, s):
        """Smoothed path direction (rad, continuous along the path) at arc lengths s."""
        s = np.asarray(s, np.float64)
        ramp = _smooth((s[..., None] - self._corners + self._half_m) / (2 * self._half_m))
        return self._yaw0 + (ramp * self._turns).sum(-1)


def _step_length_m(speed_mps: float) -> float:
    """Step length for a walking speed (longer steps when faster, as people do)."""
    return 0.56 * (max(speed_mps, 0.2) / 1.2) ** 0.6


def _gait(
    line: _Polyline,
    s: np.ndarray,
    stride_m: float,
    arm_swing_rad: float = 0.3,
    step_width_m: float = _STEP_WIDTH_M,
) -> tuple[np.ndarray, np.ndarray]:
    """Walking joints (n, 22, 3) world and heading (n,) for the pelvis at arc lengths s (n,).

    The gait is parametrised by arc length, so any speed profile works: each foot is planted on
    its footprint for the stance share of a stride (heel strike, flat, roll onto the toe), then
    swings to the next footprint. The left foot is at mid-stance at s = 0.
    """
    n = len(s)
    ahead = _AHEAD * stride_m / 2
    g0 = ahead / stride_m  # left mid-stance at s = 0
    g = g0 + s / stride_m
    heading = line.heading(s)
    p = _neutral(n)
    p["heading"] = heading
    xy = line.point(s)
    bob = np.cos(4 * np.pi * (g - g0))  # pelvis highest at either foot's mid-stance
    p["pelvis"] = np.concatenate([xy, (_PELVIS_WALK_M + _BOB_M * bob)[:, None]], -1)
    p["pelvis_rot"][:, 0] = -0.07 * np.cos(2 * np.pi * g)  # the hip of the leading leg forward
    p["pelvis_rot"][:, 2] = 0.03 * np.sin(2 * np.pi * g)
    p["spine"][:, 0] = 0.1 * np.cos(2 * np.pi * g)  # shoulders counter-rotate
    p["spine"][:, 1] = 0.06
    p["neck"][:, 1] = 0.05
    arm_swing = -arm_swing_rad * np.cos(2 * np.pi * (g - 0.5))  # left arm forward with the right leg

    # Both feet at once, (n, 2): the right foot runs half a stride behind the left.
    offset = np.array([0.0, 0.5])
    gf = g[:, None] - offset
    k = np.floor(gf)
    u = gf - k
    # Footprints k (planted now, or the swing's start) and k + 1 (the swing's end), from a
    # table over the few footprints this walk has.
    k0 = int(k.min())
    ks = np.arange(k0, int(k.max()) + 2)[:, None]
    arc = (ks + offset - g0) * stride_m + ahead
    fp_yaw = line.heading(arc)
    normal = np.stack([-np.sin(fp_yaw), np.cos(fp_yaw)], -1)
    fp_xy = line.point(arc) + (_SIDE * step_width_m)[:, None] * normal
    i = (k - k0).astype(int)
    cols = np.arange(2)
    base_k, yaw_k = fp_xy[i, cols], fp_yaw[i, cols]
    base_n, yaw_n = fp_xy[i + 1, cols], fp_yaw[i + 1, cols]

    # Stance: heel strike (toe up), foot flat, then the heel lifts and the foot rolls on the toe.
    us = np.minimum(u, _STANCE)
    pitch_st = np.where(
        us < _HEEL_OFF_AT,
        _HEEL_STRIKE_PITCH * (1 - _smooth(us / _FLAT_AT)),
        _TOE_OFF_PITCH * _smooth((us - _HEEL_OFF_AT) / (_STANCE - _HEEL_OFF_AT)),
    )
    fx, fz = _FOOT_OFF[0, 0], _FOOT_OFF[0, 2]
    rolling = pitch_st > 0  # heel off: the toe stays put and the ankle rises around it
    fwd = np.where(rolling, fx - (fx * np.cos(pitch_st) + fz * np.sin(pitch_st)), 0.0)
    up = np.where(rolling, fz - (-fx * np.sin(pitch_st) + fz * np.cos(pitch_st)), 0.0)
    toward = np.stack([np.cos(yaw_k), np.sin(yaw_k)], -1)
    ank_st = np.concatenate([base_k + fwd[..., None] * toward, (_ANKLE_H + up)[..., None]], -1)
    # Swing from this footprint's toe-off to the next footprint's heel strike (ankle on it).
    ank_n = np.concatenate([base_n, np.full(base_n.shape[:-1] + (1,), _ANKLE_H)], -1)
    q = np.clip((u - _STANCE) / (1 - _STANCE), 0.0, 1.0)
    sw = 0.8 * q + 0.2 * _smooth(q)  # mostly constant foot speed: a smoothstep peaks at 1.5x
    ank_sw = ank_st + (ank_n - ank_st) * sw[..., None]
    ank_sw[..., 2] += _CLEARANCE_M * np.sin(np.pi * q)
    swing = u >= _STANCE
    p["ankle"] = np.where(swing[..., None], ank_sw, ank_st)
    p["foot_pitch"] = np.where(swing, _TOE_OFF_PITCH + (_HEEL_STRIKE_PITCH - _TOE_OFF_PITCH) * sw, pitch_st)
    p["foot_yaw"] = np.where(swing, yaw_k + _wrap(yaw_n - yaw_k) * sw, yaw_k)
    p["arm"] = _tilt(0.97 * _ARM_HANG, np.array([-1.0, 1.0]) * arm_swing[:, None])
    return _build(p), heading


def _snap_stride(length_m: float, step_m: float) -> float:
    """Stride near 2 * step_m that fits a whole number of steps into the path, so the walk
    ends with one foot at mid-stance (close to standing)."""
    steps = max(1, round(length_m / step_m))
    return 2.0 * max(length_m, 1e-6) / steps


def walk_along(
    path_xy: np.ndarray,
    speed_mps: float,
    dt_s: float,
    rng: np.random.Generator | None = None,
    ease_s: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Walk the polyline path_xy (K, 2) at speed_mps, one frame every dt_s.

    Returns joints (n, 22, 3) float32 world, root_xy (n, 2) float32 (on the path, first frame at
    its start and last frame exactly at its end) and yaw (n,) float32 (smoothed path heading).
    The speed is constant, nudged so a whole number of frames fits the path; with ease_s > 0 it
    ramps up from and down to standing over ease_s at either end. `rng`, when given, varies the
    walker's style a little (step length, step width, arm swing); without it the gait is the
    average one.
    """
    if speed_mps <= 0 or dt_s <= 0:
        raise ValueError(f"speed_mps and dt_s must be positive, got {speed_mps}, {dt_s}")
    line = _Polyline(path_xy)
    length = line.length
    m = max(1, round((length / speed_mps + ease_s) / dt_s))  # frames after the first
    total_s = m * dt_s
    tau = min(ease_s, total_s / 2)
    cruise = length / (total_s - tau) if length > 0 else 0.0  # covers the path in total_s
    t = np.arange(m + 1) * dt_s
    if tau > 0:
        # Speed ramp v * smoothstep(t / tau); its integral is v * tau * (x^3 - x^4 / 2).
        def ramp(tt):
            x = np.clip(tt / tau, 0.0, 1.0)
            return cruise * tau * (x**3 - x**4 / 2) + cruise * np.maximum(tt - tau, 0.0)

        s = np.where(t <= total_s / 2, ramp(t), length - ramp(total_s - t))
    else:
        s = cruise * t
    s[-1] = length
    step_m, style = _step_length_m(speed_mps), {}
    if rng is not None:
        step_m *= rng.uniform(0.93, 1.07)
        style = dict(arm_swing_rad=rng.uniform(0.22, 0.38), step_width_m=rng.uniform(0.09, 0.12))
    joints, yaw = _gait(line, s, _snap_stride(length, step_m), **style)
    root_xy = joints[:, _PELVIS, :2].astype(np.float32)
    return joints.astype(np.float32), root_xy, _wrap(yaw).astype(np.float32)


def walk_cycle(speed_mps: float, dt_s: float = 0.1) -> np.ndarray:
    """One stride of walking straight along +x, root-relative (pelvis xy at the origin):
    (n, 22, 3) float32, looping cleanly (frame n would equal frame 0)."""
    if speed_mps <= 0 or dt_s <= 0:
        raise ValueError(f"speed_mps and dt_s must be positive, got {speed_mps}, {dt_s}")
    stride = 2 * _step_length_m(speed_mps)
    n = max(2, round(stride / (speed_mps * dt_s)))
    s = np.arange(n) * stride / n
    joints, _ = _gait(_Polyline([[0.0, 0.0], [stride, 0.0]]), s, stride)
    joints[..., :2] -= joints[:, _PELVIS, None, :2]
    return joints.astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Episodes


@dataclass(frozen=True)
class HumanMotion:
    """The human of one episode, one frame per control step.

    joints (T, 22, 3) float32 world (m); root_xy (T, 2) float32, the pelvis on the floor plane;
    root_yaw (T,) float32, the body frame's heading (rad: the activity's facing, or the smoothed
    walking direction); phase (T,) int8: 0 activity A, 1 walking (from the turn away from A),
    2 at the goal (turning to B, then activity B). t_walk_start: first phase-1 step; t_arrive:
    first step standing at the goal (= first phase-2 step); t_end = T - 1.
    """

    joints: np.ndarray
    root_xy: np.ndarray
    root_yaw: np.ndarray
    phase: np.ndarray
    t_walk_start: int
    t_arrive: int
    t_end: int


def _place(local, x, y, yaw):
    """Local frames (n, 22, 3) -> world, standing at (x, y) facing yaw; yaw may be (n,)."""
    yaw = np.broadcast_to(yaw, local.shape[:1])[:, None]
    return _turn(local, yaw) + np.array([x, y, 0.0])


def _turn_blend(local_from, local_to, xy_from, xy_to, yaw_from, yaw_to, n_min, dt_s):
    """Transition frames: the pose blends local_from -> local_to (22, 3) while the body turns
    yaw_from -> yaw_to the shorter way, standing at xy_from -> xy_to (the same point unless a
    path does not start or end exactly at its standing point). Both end poses are excluded."""
    dyaw = float(_wrap(yaw_to - yaw_from))
    n = max(n_min, math.ceil(abs(dyaw) / (_MAX_TURN_RADPS * dt_s)))
    w = _smooth(np.arange(1, n + 1) / (n + 1))
    local = _lerp(local_from[None], local_to[None], w)
    yaw = yaw_from + dyaw * w
    xy = _lerp(np.asarray(xy_from, np.float64)[None, :2], np.asarray(xy_to, np.float64)[None, :2], w)
    return _turn(local, yaw[:, None]) + np.concatenate([xy, np.zeros((n, 1))], -1)[:, None], yaw


def _activity(rng, activity, clip, cfg: MotionConfig) -> np.ndarray:
    """The activity's local frames: an imported clip as given, or a procedural one looped."""
    if clip is not None:
        clip = np.asarray(clip, np.float64)
        if clip.ndim != 3 or clip.shape[1:] != (NUM_JOINTS, 3) or len(clip) < 1:
            raise ValueError(f"an imported clip must have shape (n, {NUM_JOINTS}, 3), got {clip.shape}")
        return clip
    dt = cfg.control_dt_s
    n = max(1, round(rng.uniform(*cfg.activity_clip_s) / dt))
    loops = int(rng.integers(cfg.activity_loops[0], cfg.activity_loops[1] + 1))
    one = activity_clip(activity[0], activity[1], n, rng, dt).astype(np.float64)
    return np.tile(one, (loops, 1, 1))


def compose_episode_motion(
    rng: np.random.Generator,
    activity_a: tuple[int, str],
    activity_b: tuple[int, str],
    stand_a: tuple[float, float, float],
    stand_b: tuple[float, float, float],
    path_xy: np.ndarray,
    cfg: MotionConfig,
    clip_a: np.ndarray | None = None,
    clip_b: np.ndarray | None = None,
) -> HumanMotion:
    """Activity A at stand_a (x, y, facing yaw), walk along path_xy (K, 2) to stand_b, activity
    B there. activity_*: (activity id, primitive); clip_*: optional imported local clips
    (n, 22, 3) that replace the procedural ones. Transitions (cfg.transition_s, longer for big
    turns) blend poses and turn the body in place; the walk eases in and out of standing."""
    dt = cfg.control_dt_s
    n_tr = max(1, round(cfg.transition_s / dt))
    local_a = _activity(rng, activity_a, clip_a, cfg)
    local_b = _activity(rng, activity_b, clip_b, cfg)
    speed = rng.uniform(*cfg.walk_speed_mps)
    walk, walk_xy, walk_yaw = walk_along(path_xy, speed, dt, rng, ease_s=cfg.transition_s)
    walk = walk.astype(np.float64)
    walk_yaw = walk_yaw.astype(np.float64)
    xa, ya, yaw_a = stand_a
    xb, yb, yaw_b = stand_b
    start = np.array([walk_xy[0, 0], walk_xy[0, 1], 0.0])
    end = np.array([walk_xy[-1, 0], walk_xy[-1, 1], 0.0])
    # Gait end frames in their own heading frame, to blend with the activities' local frames.
    gait_first = _turn(walk[0] - start, -walk_yaw[0])
    gait_last = _turn(walk[-1] - end, -walk_yaw[-1])

    a = _place(local_a, xa, ya, yaw_a)
    t1, yaw_t1 = _turn_blend(local_a[-1], gait_first, (xa, ya), start, yaw_a, walk_yaw[0], n_tr, dt)
    t2, yaw_t2 = _turn_blend(gait_last, local_b[0], end, (xb, yb), walk_yaw[-1], yaw_b, n_tr, dt)
    b = _place(local_b, xb, yb, yaw_b)
    joints = np.concatenate([a, t1, walk, t2, b]).astype(np.float32)
    yaw = np.concatenate([np.full(len(a), yaw_a), yaw_t1, walk_yaw, yaw_t2, np.full(len(b), yaw_b)])

    t_walk_start = len(a)
    t_arrive = t_walk_start + len(t1) + len(walk) - 1  # the walk's last frame is at the goal
    phase = np.full(len(joints), PHASE_WALK, np.int8)
    phase[:t_walk_start] = PHASE_A
    phase[t_arrive:] = PHASE_B
    return HumanMotion(
        joints=joints,
        root_xy=joints[:, _PELVIS, :2].copy(),
        root_yaw=_wrap(yaw).astype(np.float32),
        phase=phase,
        t_walk_start=t_walk_start,
        t_arrive=t_arrive,
        t_end=len(joints) - 1,
    )
