"""Procedural activity clips: (activity id, primitive) -> keyframes (n, 22, 3) in the local frame.

The activity id fixes a signature (tempo, amplitude, leading hand, posture, style variant); the
primitive turns it and time into a pose (rig.py) that `activity_clip` eases in from standing and
back out, so one activity always looks like itself and clips loop and blend.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from conav_jax.motion.primitives import MOTION_PRIMITIVES
from conav_jax.motion.rig import (
    ARM_HANG_M,
    REST,
    SIDE,
    WRIST,
    arc_lerp,
    build_joints,
    hands_to_arm,
    keyframed,
    keyframed_hand,
    lerp,
    neutral_pose,
    rotate_y,
    slerp,
    smoothstep,
    tiptoe,
)


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
        return float(SIDE[self.side])


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
    return np.tile(REST[WRIST[side]], (n, 1))


# A primitive is f(t (n,) s, signature, p) -> {side: wrist target (n, 3)}: it edits p, a neutral
# pose (local frame, object ahead at +x), into the activity's full pose, and returns absolute
# targets for the wrists it moves. activity_clip then eases from neutral into it and back.


def _seated(p, s: _Signature) -> None:
    """Lower body sitting on a seat-height surface behind the standing point."""
    p["pelvis"][:] = (-0.22, 0.0, 0.52)
    p["ankle"][:, :, 0] = 0.12 + 0.03 * s.variant
    p["ankle"][:, :, 1] = SIDE * 0.12
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
        return {k: np.tile((-0.02, SIDE[k] * 0.2, 0.98), (n, 1)) for k in (0, 1)}
    if s.variant == 2:  # arms crossed
        return {k: np.tile((0.2, -SIDE[k] * 0.1, 1.2 + 0.03 * k), (n, 1)) for k in (0, 1)}
    return {}


def _reach_up(t, s, p):
    n = len(t)
    r = keyframed(_cycle(t, s, 0.2), [0, 0.3, 0.6, 0.95], [0, 1, 1, 0])
    hands = {}
    for k in (0, 1) if s.both else (s.side,):
        top = np.array([0.2 + s.reach_m, SIDE[k] * (0.22 + s.lateral_m), 1.85 + 0.5 * s.height_m])
        top = top + 0.03 * s.amp * _wave(t, s, 1.3, 0.25 * k)[:, None] * np.array([1.0, 0.0, 0.5])
        hands[k] = arc_lerp(_hang(n, k), top, r, k)
    p["spine"][:, 1] -= 0.1 * r
    p["neck"][:, 1] = -0.35 * r
    if s.variant == 1:
        tiptoe(p, 0.35 * r)
    return hands


def _reach_forward(t, s, p):
    n = len(t)
    r = keyframed(_cycle(t, s, 0.25), [0, 0.3, 0.6, 0.85], [0, 1, 1, 0])
    push = 0.05 * s.amp * _wave(t, s, 0.9)
    hands = {}
    for i, k in enumerate((s.side, 1 - s.side) if s.both else (s.side,)):
        y, z = SIDE[k] * (0.15 + s.lateral_m), 1.2 + s.height_m - 0.1 * i
        goal = np.stack([0.55 + s.reach_m + push, np.full(n, y), np.full(n, z)], -1)
        hands[k] = arc_lerp(_hang(n, k), goal, r, k)
    p["spine"][:, 1] += 0.25 * r
    p["pelvis"][:, 0] -= 0.03 * r
    return hands


def _bend_down(t, s, p):
    n = len(t)
    b = keyframed(_cycle(t, s, 0.15), [0, 0.35, 0.6, 0.9], [0, 1, 1, 0]) * min(s.amp, 1.1)
    p["pelvis"][:, 0] -= 0.13 * b
    p["pelvis"][:, 2] -= 0.15 * b
    p["pelvis_rot"][:, 1] = 0.55 * b
    p["spine"][:, 1] += 0.75 * b
    p["neck"][:, 1] = -0.3 * b
    hands = {}
    for k in (0, 1) if s.both or s.variant == 0 else (s.side,):
        low = (0.35 + s.reach_m, SIDE[k] * 0.12 + s.lateral_m, 0.25 + max(s.height_m, 0.0))
        hands[k] = arc_lerp(_hang(n, k), np.array(low), b, k)
    return hands


def _crouch(t, s, p):
    n = len(t)
    bob = 0.02 * _wave(t, s, 0.2)
    p["pelvis"][:] = np.stack([np.full(n, -0.12), np.zeros(n), 0.5 + bob + 0.5 * s.height_m * 0.3], -1)
    p["pelvis_rot"][:, 1] = 0.45
    p["spine"][:, 1] += 0.35
    p["neck"][:, 1] = -0.2
    p["ankle"][:, :, 1] = SIDE * 0.14
    p["foot_yaw"][:] = SIDE * 0.3
    if s.variant == 1:
        tiptoe(p, np.full(n, 0.35))
    work = 0.06 * s.amp * np.stack([_wave(t, s, 0.5), _wave(t, s, 0.5, 0.25), np.zeros(n)], -1)
    hands = {}
    for k in (0, 1):
        base = np.array([0.3 + s.reach_m, SIDE[k] * 0.15 + s.lateral_m, 0.25])
        hands[k] = base + (work if (k == s.side or s.both) else 0.0)
    return hands


def _sit(t, s, p):
    n = len(t)
    _seated(p, s)
    p["neck"][:, 0] = 0.4 * s.amp * _wave(t, s, 0.08)
    p["spine"][:, 1] += 0.02 * _wave(t, s, 0.25)  # breathing
    thigh = {k: np.tile((0.05, SIDE[k] * 0.16, 0.62), (n, 1)) for k in (0, 1)}
    if s.variant == 1:  # holding something to read; the leading hand turns pages
        u = _cycle(t, s, 0.12)
        page = keyframed(u, [0, 0.1, 0.2], [[0, 0, 0], [0.02, -SIDE[s.side] * 0.12, 0.05], [0, 0, 0]])
        p["neck"][:, 1] = 0.35
        return {k: np.array((0.25, SIDE[k] * 0.1, 0.85)) + (page if k == s.side else 0.0) for k in (0, 1)}
    if s.variant == 2:  # talking, the leading hand gesturing
        g = 0.08 * s.amp * np.stack([_wave(t, s, 0.6), _wave(t, s, 0.45, 0.3), _wave(t, s, 0.7, 0.6)], -1)
        thigh[s.side] = np.array((0.25, SIDE[s.side] * 0.28, 0.95)) + g
    return thigh


def _lie_down(t, s, p):
    n = len(t)
    p["pelvis"][:] = (0.1, 0.0, 0.8)
    p["pelvis_rot"][:, 1] = 0.9
    p["spine"][:, 1] = 0.75 + 0.03 * _wave(t, s, 0.25)  # breathing
    p["ankle"][:, :, 0] = -0.2
    p["neck"][:, 0] = SIDE[s.side] * 0.6
    p["neck"][:, 1] = -0.5
    if s.variant == 0:  # hands under the head
        return {k: np.tile((0.72, SIDE[k] * 0.12, 0.72), (n, 1)) for k in (0, 1)}
    spread = 0.05 * s.amp * _wave(t, s, 0.1)
    return {k: np.stack([np.full(n, 0.55), SIDE[k] * (0.35 + spread), np.full(n, 0.64)], -1) for k in (0, 1)}


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
            [np.full(n, 0.30 + 0.5 * s.reach_m), SIDE[k] * 0.13 + shift, 0.74 + 0.3 * s.height_m + tap], -1
        )
    if s.variant == 1:  # the leading hand on a mouse
        mouse = 0.03 * s.amp * np.stack([_wave(t, s, 0.4), _wave(t, s, 0.3, 0.2), np.zeros(n)], -1)
        hands[s.side] = np.array((0.3, s.sgn * 0.33, 0.74)) + mouse
    return hands


def _pick_and_place(t, s, p):
    u = _cycle(t, s, 0.2)
    k0 = s.side
    hang = REST[WRIST[k0]]
    a = (0.45 + s.reach_m, s.sgn * (0.2 + s.lateral_m), 0.85 + s.height_m)
    b = (0.45 + s.reach_m, -s.sgn * 0.05 + s.lateral_m, 0.85 + s.height_m)
    mid = (0.4, s.sgn * 0.08, 1.1 + s.height_m)
    knots = [0, 0.2, 0.3, 0.5, 0.65, 0.75, 0.9]
    path = keyframed_hand(u, knots, [hang, a, a, mid, b, b, hang], k0)
    low = keyframed(u, knots, [0, 1, 1, 0.4, 1, 1, 0])
    p["spine"][:, 1] += 0.3 * low * s.amp
    turn = 0.25 if s.variant == 2 else 0.5  # the torso turns towards the hand
    p["spine"][:, 0] = turn * np.arctan2(path[:, 1], np.maximum(path[:, 0], 0.1))
    hands = {k0: path}
    if s.both:  # a box: both hands on it
        box_width_m = np.array((0.0, -s.sgn * 0.3, 0.0))
        hands[1 - k0] = path + box_width_m * smoothstep(4 * np.minimum(u, 1 - u))[:, None]
    return hands


def _carry(t, s, p):
    n = len(t)
    h = (1.12, 1.0, 1.25)[s.variant] + 0.5 * s.height_m
    p["pelvis"][:, 2] -= 0.02 + 0.01 * _wave(t, s, 0.8)
    p["pelvis"][:, 1] += 0.025 * _wave(t, s, 0.4)
    p["spine"][:, 1] -= 0.08
    p["spine"][:, 0] = 0.25 * s.amp * _wave(t, s, 0.12)
    p["neck"][:, 0] = 0.3 * s.amp * _wave(t, s, 0.12, 0.1)
    return {k: np.tile((0.32 + s.reach_m, SIDE[k] * 0.16, h), (n, 1)) for k in (0, 1)}


def _open_door(t, s, p):
    u = _cycle(t, s, 0.18)
    k0 = s.side
    hang = REST[WRIST[k0]]
    handle = (0.55 + s.reach_m, s.sgn * (0.25 + s.lateral_m), 1.0 + s.height_m)
    mid = (0.38, s.sgn * 0.45, 1.0 + s.height_m)
    pulled = (0.15, s.sgn * 0.52, 1.0 + s.height_m)
    knots = [0, 0.2, 0.3, 0.45, 0.6, 0.8]
    hand = keyframed_hand(u, knots, [hang, handle, handle, mid, pulled, pulled], k0)
    back = keyframed(u, [0, 0.35, 0.55, 0.8, 0.99], [0, 0, -0.15, -0.15, 0.0])
    p["pelvis"][:, 0] += back
    p["spine"][:, 0] = s.sgn * 0.3 * keyframed(u, knots, [0, 0, 0, 1, 1, 0])
    p["spine"][:, 1] += 0.15 * keyframed(u, knots, [0, 1, 1, 0, 0, 0])
    # The feet step back one after the other while pulling, and forward again after.
    for k, (t0, t1) in enumerate(((0.35, 0.45), (0.45, 0.55))):
        side = k0 if k == 0 else 1 - k0
        go = smoothstep((u - t0) / (t1 - t0)) - smoothstep((u - (t0 + 0.45)) / (t1 - t0))
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
    r = keyframed(u, [0, 0.25, 0.75, 0.95], [0, 1, 1, 0])
    bend = s.amp * np.sin(2 * np.pi * 2 * u) * r
    if s.variant == 2:
        p["spine"][:, 0] = 0.4 * bend  # twists instead of side bends
    else:
        p["spine"][:, 2] = 0.3 * bend
        p["pelvis"][:, 1] += 0.03 * bend
    p["neck"][:, 1] = -0.2 * r
    if s.variant == 1:
        tiptoe(p, 0.3 * r)
    return {k: arc_lerp(_hang(n, k), np.array((0.05, SIDE[k] * 0.12, 1.95)), r, k) for k in (0, 1)}


def _wash_body(t, s, p):
    u = _cycle(t, s, 0.2)
    rub = 0.03 * np.stack([np.zeros_like(t), _wave(t, s, 1.5), _wave(t, s, 1.5, 0.25)], -1)
    knots = [0, 0.2, 0.4, 0.6, 0.8]
    hands = {}
    for k in (0, 1):
        sg = SIDE[k]
        # head, chest, belly, thigh, then back up in front of the body
        spots = [
            (0.08, sg * 0.08, 1.65),
            (0.17, sg * 0.05, 1.30),
            (0.17, -sg * 0.05, 1.05),
            (0.14, sg * 0.1, 0.75),
            (0.3, sg * 0.2, 1.2),
        ]
        hands[k] = keyframed_hand((u + 0.5 * k * (s.variant != 0)) % 1.0, knots, spots, k) + rub
    low = keyframed(u, knots, [0, 0, 0.3, 1, 0.2])
    p["spine"][:, 1] += 0.45 * low
    p["pelvis"][:, 0] -= 0.06 * low
    p["neck"][:, 1] = -0.25 * keyframed(u, knots, [1, 0, 0, 0, 0])
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
    arm = ARM_HANG_M * (0.6 if s.variant == 2 else 1.0)  # jogging: elbows bent
    for k, sg in ((0, -1.0), (1, 1.0)):
        p["arm"][:, k] = rotate_y(arm[k], sg * swing)
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
        y = SIDE[k] * 0.17 + 0.1 * s.amp * _wave(t, s, 0.3, 0.2 * k)
        tap = 0.015 * _wave(t, s, 2.0, 0.5 * k)
        hands[k] = np.stack([np.full(n, 0.32 + s.reach_m), y, height + 0.3 * s.height_m + tap], -1)
    return hands


def _drink(t, s, p):
    n = len(t)
    u = _cycle(t, s, 0.2)
    held = (0.25, s.sgn * 0.18, 1.0 + 0.3 * s.height_m)
    mouth = (0.14, s.sgn * 0.04, 1.52)
    knots = [0, 0.3, 0.55, 0.75]
    hand = keyframed_hand(u, knots, [held, mouth, mouth, held], s.side)
    p["neck"][:, 1] = -0.35 * keyframed(u, knots, [0, 1, 1, 0])
    p["spine"][:, 1] -= 0.05
    hands = {s.side: hand}
    if s.variant == 1:  # the other hand holds a plate
        hands[1 - s.side] = np.tile((0.28, -s.sgn * 0.15, 1.0), (n, 1))
    return hands


def _hang_on_wall(t, s, p):
    n = len(t)
    r = keyframed(_cycle(t, s, 0.15), [0, 0.35, 0.7, 0.9], [0, 1, 1, 0])
    adjust = 0.04 * s.amp * _wave(t, s, 0.7) * r
    hands = {}
    for k in (0, 1):
        low = np.array((0.3, SIDE[k] * 0.2, 1.0))
        wall_x, wall_z = np.full(n, 0.5 + s.reach_m), np.full(n, 1.65 + s.height_m)
        wall = np.stack([wall_x, SIDE[k] * 0.25 + adjust, wall_z], -1)
        hands[k] = arc_lerp(low, wall, r, k)
    p["neck"][:, 1] = -0.25 * r
    p["spine"][:, 1] -= 0.05
    if s.variant == 1:
        tiptoe(p, 0.3 * r)
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
assert set(_PRIMITIVES) == set(MOTION_PRIMITIVES), "motion/clips.py must animate every primitive"

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
    active = neutral_pose(n_steps)
    hands = _PRIMITIVES[primitive](t, sig, active)
    active["spine"][:, 0] += sig.twist_rad
    active["spine"][:, 1] += sig.lean_rad
    active["neck"][:, 0] += sig.head_yaw_rad
    hands_to_arm(active, hands)
    # Envelope: 0 at both ends (neutral pose), 1 once the activity pose is reached.
    end = t[-1]
    ramp = max(min(_RAMP_S, end / 3.0), 1e-9)
    env = smoothstep(t / ramp) * smoothstep((end - t) / ramp)
    neutral = neutral_pose(n_steps)
    pose = {k: lerp(neutral[k], active[k], env) for k in neutral if k != "arm"}
    pose["arm"] = slerp(neutral["arm"], active["arm"], env)
    return build_joints(pose).astype(np.float32)

