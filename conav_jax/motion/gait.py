"""Walking gait along a path: polyline (K, 2) + speed -> joints (n, 22, 3) world, one per frame.

The path is parametrised by arc length; footprints sit beside it one step apart, each foot is
planted on its footprint (heel strike, flat, roll onto the toe) then swings to the next, and the
pose is built by the rig (rig.py). Every tunable number is a `walk_*` field of MotionConfig.
"""

from __future__ import annotations

import numpy as np

from conav_jax.config import MotionConfig
from conav_jax.geometry import wrap_angle_np
from conav_jax.motion.rig import (
    ANKLE_HEIGHT_M,
    ARM_HANG_M,
    FOOT_OFFSET_M,
    PELVIS,
    SIDE,
    build_joints,
    neutral_pose,
    rotate_y,
    smoothstep,
)


class _Polyline:
    """Arc-length parametrised path, extrapolated straight past both ends."""

    def __init__(self, path_xy, turn_half_arc_m: float):
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

        # Heading: the segments' directions, each corner's turn spread over +-turn_half_arc_m of
        # arc per right angle (angles are smoothed, not vectors: a U-turn stays defined).
        angles = np.arctan2(self.dirs[:, 1], self.dirs[:, 0])
        self._yaw0 = float(angles[0])
        self._turns = wrap_angle_np(np.diff(angles))
        self._half_m = turn_half_arc_m * np.maximum(1.0, np.abs(self._turns) / (np.pi / 2))
        self._corners = self.cum[1:-1]

    def _seg(self, s):
        return np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.dirs) - 1)

    def point(self, s):
        i = self._seg(s)
        return self.pts[i] + (s - self.cum[i])[..., None] * self.dirs[i]

    def heading(self, s):
        """Smoothed path direction (rad, continuous along the path) at arc lengths s."""
        s = np.asarray(s, np.float64)
        ramp = smoothstep((s[..., None] - self._corners + self._half_m) / (2 * self._half_m))
        return self._yaw0 + (ramp * self._turns).sum(-1)


def _step_length_m(speed_mps: float, cfg: MotionConfig) -> float:
    """Step length for a walking speed (longer steps when faster, as people do)."""
    slowest_mps = max(speed_mps, cfg.walk_step_min_speed_mps)
    ratio = slowest_mps / cfg.walk_step_ref_speed_mps
    return cfg.walk_step_length_m * ratio**cfg.walk_step_speed_exponent


def _gait(
    line: _Polyline,
    s: np.ndarray,
    stride_m: float,
    cfg: MotionConfig,
    arm_swing_rad: float,
    step_width_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Walking joints (n, 22, 3) world and heading (n,) for the pelvis at arc lengths s (n,).

    The gait is parametrised by arc length, so any speed profile works: each foot is planted on
    its footprint for the stance share of a stride (heel strike, flat, roll onto the toe), then
    swings to the next footprint. The left foot is at mid-stance at s = 0.
    """
    stance = cfg.walk_stance_share
    heel_strike_rad, toe_off_rad = cfg.walk_heel_strike_pitch_rad, cfg.walk_toe_off_pitch_rad
    heel_off = cfg.walk_heel_off_share
    n = len(s)
    ahead = cfg.walk_ankle_ahead_share * stride_m / 2
    g0 = ahead / stride_m  # left mid-stance at s = 0
    g = g0 + s / stride_m
    heading = line.heading(s)
    p = neutral_pose(n)
    p["heading"] = heading
    xy = line.point(s)
    bob = np.cos(4 * np.pi * (g - g0))  # pelvis highest at either foot's mid-stance
    p["pelvis"] = np.concatenate([xy, (cfg.walk_pelvis_height_m + cfg.walk_pelvis_bob_m * bob)[:, None]], -1)
    # The hip of the leading leg forward, and the shoulders counter-rotating.
    p["pelvis_rot"][:, 0] = -cfg.walk_pelvis_twist_rad * np.cos(2 * np.pi * g)
    p["pelvis_rot"][:, 2] = cfg.walk_pelvis_roll_rad * np.sin(2 * np.pi * g)
    p["spine"][:, 0] = cfg.walk_spine_twist_rad * np.cos(2 * np.pi * g)
    p["spine"][:, 1] = cfg.walk_spine_lean_rad
    p["neck"][:, 1] = cfg.walk_head_pitch_rad
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
    fp_xy = line.point(arc) + (SIDE * step_width_m)[:, None] * normal
    i = (k - k0).astype(int)
    cols = np.arange(2)
    base_k, yaw_k = fp_xy[i, cols], fp_yaw[i, cols]
    base_n, yaw_n = fp_xy[i + 1, cols], fp_yaw[i + 1, cols]

    # Stance: heel strike (toe up), foot flat, then the heel lifts and the foot rolls on the toe.
    us = np.minimum(u, stance)
    pitch_st = np.where(
        us < heel_off,
        heel_strike_rad * (1 - smoothstep(us / cfg.walk_foot_flat_share)),
        toe_off_rad * smoothstep((us - heel_off) / (stance - heel_off)),
    )
    fx, fz = FOOT_OFFSET_M[0, 0], FOOT_OFFSET_M[0, 2]
    rolling = pitch_st > 0  # heel off: the toe stays put and the ankle rises around it
    fwd = np.where(rolling, fx - (fx * np.cos(pitch_st) + fz * np.sin(pitch_st)), 0.0)
    up = np.where(rolling, fz - (-fx * np.sin(pitch_st) + fz * np.cos(pitch_st)), 0.0)
    toward = np.stack([np.cos(yaw_k), np.sin(yaw_k)], -1)
    ank_st = np.concatenate([base_k + fwd[..., None] * toward, (ANKLE_HEIGHT_M + up)[..., None]], -1)
    # Swing from this footprint's toe-off to the next footprint's heel strike (ankle on it).
    ank_n = np.concatenate([base_n, np.full(base_n.shape[:-1] + (1,), ANKLE_HEIGHT_M)], -1)
    q = np.clip((u - stance) / (1 - stance), 0.0, 1.0)
    sw = 0.8 * q + 0.2 * smoothstep(q)  # mostly constant foot speed: a smoothstep peaks at 1.5x
    ank_sw = ank_st + (ank_n - ank_st) * sw[..., None]
    ank_sw[..., 2] += cfg.walk_clearance_m * np.sin(np.pi * q)
    swing = u >= stance
    p["ankle"] = np.where(swing[..., None], ank_sw, ank_st)
    p["foot_pitch"] = np.where(swing, toe_off_rad + (heel_strike_rad - toe_off_rad) * sw, pitch_st)
    p["foot_yaw"] = np.where(swing, yaw_k + wrap_angle_np(yaw_n - yaw_k) * sw, yaw_k)
    # Elbows a little bent while walking; each arm swings opposite its own leg.
    p["arm"] = rotate_y(cfg.walk_arm_hang_scale * ARM_HANG_M, np.array([-1.0, 1.0]) * arm_swing[:, None])
    return build_joints(p), heading


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
    cfg: MotionConfig | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Walk the polyline path_xy (K, 2) at speed_mps, one frame every dt_s.

    Returns joints (n, 22, 3) float32 world, root_xy (n, 2) float32 (on the path, first frame at
    its start and last frame exactly at its end) and yaw (n,) float32 (smoothed path heading).
    The speed is constant, nudged so a whole number of frames fits the path; with ease_s > 0 it
    ramps up from and down to standing over ease_s at either end. `rng`, when given, varies the
    walker's style a little (step length, step width, arm swing within cfg's `walk_*_range`
    fields); without it the gait is the average one. cfg: the gait's numbers (default
    MotionConfig()).
    """
    if speed_mps <= 0 or dt_s <= 0:
        raise ValueError(f"speed_mps and dt_s must be positive, got {speed_mps}, {dt_s}")
    cfg = MotionConfig() if cfg is None else cfg
    line = _Polyline(path_xy, cfg.walk_turn_half_arc_m)
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
    step_m = _step_length_m(speed_mps, cfg)
    arm_swing_rad, step_width_m = cfg.walk_arm_swing_rad, cfg.walk_step_width_m
    if rng is not None:
        # Drawn in this order (step, arm swing, step width): the episodes' bytes depend on it.
        step_m *= rng.uniform(*cfg.walk_step_length_scale_range)
        arm_swing_rad = rng.uniform(*cfg.walk_arm_swing_range_rad)
        step_width_m = rng.uniform(*cfg.walk_step_width_range_m)
    joints, yaw = _gait(line, s, _snap_stride(length, step_m), cfg, arm_swing_rad, step_width_m)
    root_xy = joints[:, PELVIS, :2].astype(np.float32)
    return joints.astype(np.float32), root_xy, wrap_angle_np(yaw).astype(np.float32)


def walk_cycle(speed_mps: float, dt_s: float = 0.1, cfg: MotionConfig | None = None) -> np.ndarray:
    """One stride of walking straight along +x, root-relative (pelvis xy at the origin):
    (n, 22, 3) float32, looping cleanly (frame n would equal frame 0). cfg: the gait's numbers
    (default MotionConfig()); the average walker, no style variation."""
    if speed_mps <= 0 or dt_s <= 0:
        raise ValueError(f"speed_mps and dt_s must be positive, got {speed_mps}, {dt_s}")
    cfg = MotionConfig() if cfg is None else cfg
    stride = 2 * _step_length_m(speed_mps, cfg)
    n = max(2, round(stride / (speed_mps * dt_s)))
    s = np.arange(n) * stride / n
    line = _Polyline([[0.0, 0.0], [stride, 0.0]], cfg.walk_turn_half_arc_m)
    joints, _ = _gait(line, s, stride, cfg, cfg.walk_arm_swing_rad, cfg.walk_step_width_m)
    joints[..., :2] -= joints[:, PELVIS, None, :2]
    return joints.astype(np.float32)
