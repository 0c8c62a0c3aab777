"""An episode's human: activity A at its standing point, walk along the path, activity B at the goal.

Clips (clips.py, or imported ones) and the gait (gait.py) are placed in the world and joined by
in-place turns that blend the poses -> HumanMotion: joints, root pose and phase per control step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from conav_jax.config import MotionConfig
from conav_jax.geometry import wrap_angle_np
from conav_jax.motion.clips import activity_clip
from conav_jax.motion.gait import walk_along
from conav_jax.motion.phases import PHASE_ACTIVITY_A, PHASE_ACTIVITY_B, PHASE_WALK
from conav_jax.motion.rig import PELVIS, lerp, rotate_z, smoothstep
from conav_jax.motion.skeleton import NUM_JOINTS


@dataclass(frozen=True)
class HumanMotion:
    """The human of one episode, one frame per control step.

    joints (T, 22, 3) float32 world (m); root_xy (T, 2) float32, the pelvis on the floor plane;
    root_yaw (T,) float32, the body frame's heading (rad: the activity's facing, or the smoothed
    walking direction); phase (T,) int8: PHASE_ACTIVITY_A during activity A, PHASE_WALK walking
    (from the turn away from A), PHASE_ACTIVITY_B at the goal (turning to B, then activity B).
    t_walk_start: first PHASE_WALK step; t_arrive: first step standing at the goal (= first
    PHASE_ACTIVITY_B step); t_end = T - 1.
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
    return rotate_z(local, yaw) + np.array([x, y, 0.0])


def _turn_blend(local_from, local_to, xy_from, xy_to, yaw_from, yaw_to, cfg: MotionConfig):
    """Transition frames: the pose blends local_from -> local_to (22, 3) while the body turns
    yaw_from -> yaw_to the shorter way, standing at xy_from -> xy_to (the same point unless a
    path does not start or end exactly at its standing point). Both end poses are excluded.
    It lasts cfg.transition_s, or longer where the turn needs it at cfg.turn_in_place_max_radps."""
    dt_s = cfg.control_dt_s
    n_min = max(1, round(cfg.transition_s / dt_s))
    dyaw = float(wrap_angle_np(yaw_to - yaw_from))
    n = max(n_min, math.ceil(abs(dyaw) / (cfg.turn_in_place_max_radps * dt_s)))
    w = smoothstep(np.arange(1, n + 1) / (n + 1))
    local = lerp(local_from[None], local_to[None], w)
    yaw = yaw_from + dyaw * w
    xy = lerp(np.asarray(xy_from, np.float64)[None, :2], np.asarray(xy_to, np.float64)[None, :2], w)
    return rotate_z(local, yaw[:, None]) + np.concatenate([xy, np.zeros((n, 1))], -1)[:, None], yaw


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
    local_a = _activity(rng, activity_a, clip_a, cfg)
    local_b = _activity(rng, activity_b, clip_b, cfg)
    speed = rng.uniform(*cfg.walk_speed_mps)
    walk, walk_xy, walk_yaw = walk_along(path_xy, speed, dt, rng, ease_s=cfg.transition_s, cfg=cfg)
    walk = walk.astype(np.float64)
    walk_yaw = walk_yaw.astype(np.float64)
    xa, ya, yaw_a = stand_a
    xb, yb, yaw_b = stand_b
    start = np.array([walk_xy[0, 0], walk_xy[0, 1], 0.0])
    end = np.array([walk_xy[-1, 0], walk_xy[-1, 1], 0.0])
    # Gait end frames in their own heading frame, to blend with the activities' local frames.
    gait_first = rotate_z(walk[0] - start, -walk_yaw[0])
    gait_last = rotate_z(walk[-1] - end, -walk_yaw[-1])

    a = _place(local_a, xa, ya, yaw_a)
    t1, yaw_t1 = _turn_blend(local_a[-1], gait_first, (xa, ya), start, yaw_a, walk_yaw[0], cfg)
    t2, yaw_t2 = _turn_blend(gait_last, local_b[0], end, (xb, yb), walk_yaw[-1], yaw_b, cfg)
    b = _place(local_b, xb, yb, yaw_b)
    joints = np.concatenate([a, t1, walk, t2, b]).astype(np.float32)
    yaw = np.concatenate([np.full(len(a), yaw_a), yaw_t1, walk_yaw, yaw_t2, np.full(len(b), yaw_b)])

    t_walk_start = len(a)
    t_arrive = t_walk_start + len(t1) + len(walk) - 1  # the walk's last frame is at the goal
    phase = np.full(len(joints), PHASE_WALK, np.int8)
    phase[:t_walk_start] = PHASE_ACTIVITY_A
    phase[t_arrive:] = PHASE_ACTIVITY_B
    return HumanMotion(
        joints=joints,
        root_xy=joints[:, PELVIS, :2].copy(),
        root_yaw=wrap_angle_np(yaw).astype(np.float32),
        phase=phase,
        t_walk_start=t_walk_start,
        t_arrive=t_arrive,
        t_end=len(joints) - 1,
    )
