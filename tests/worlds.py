"""Hand-built worlds for exact tests: a scene dict, a scripted human, a known robot start."""

from __future__ import annotations

import math

import numpy as np

from conav_jax.config import DatasetConfig
from conav_jax.data.episodes import EpisodeSplit, scene_nav, stack_episodes
from conav_jax.data.scene import scene_from_json_dict
from conav_jax.motion.phases import PHASE_ACTIVITY_A, PHASE_ACTIVITY_B, PHASE_WALK
from conav_jax.motion.skeleton import REST_POSE

# A 10 m x 4 m room: walls on all sides, a fridge at the west end (activity A) and a table
# at the east end (activity B, the goal).
ROOM = {
    "format": "conav-scene",
    "version": 1,
    "name": "hall",
    "bounds_m": [0, 0, 10, 4],
    "wall_height_m": 2.5,
    "rooms": [{"type": "kitchen", "rect_m": [0, 0, 10, 4]}],
    "walls": [
        {"center_m": [5, 0.05, 1.25], "half_extents_m": [5, 0.05, 1.25]},
        {"center_m": [5, 3.95, 1.25], "half_extents_m": [5, 0.05, 1.25]},
        {"center_m": [0.05, 2, 1.25], "half_extents_m": [0.05, 1.85, 1.25]},
        {"center_m": [9.95, 2, 1.25], "half_extents_m": [0.05, 1.85, 1.25]},
    ],
    "objects": [
        {"category": "fridge", "center_m": [0.45, 2, 0.9], "size_m": [0.8, 0.7, 1.8], "yaw_deg": 0, "room": 0},
        {"category": "table", "center_m": [9.4, 2, 0.375], "size_m": [1.4, 0.9, 0.75], "yaw_deg": 180, "room": 0},
    ],
}


def human_track(xy: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Local joints (T, 22, 3) of a rest-pose human at root positions xy (T, 2) facing yaw (T,)."""
    rest = REST_POSE - np.array([REST_POSE[0, 0], REST_POSE[0, 1], 0.0], np.float32)
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    x = c * rest[None, :, 0] - s * rest[None, :, 1]
    y = s * rest[None, :, 0] + c * rest[None, :, 1]
    return np.stack([x, y, np.broadcast_to(rest[None, :, 2], x.shape)], axis=-1).astype(np.float16)


def make_split(
    robot_starts: list[tuple[float, float, float]],
    human_xy: list[np.ndarray] | None = None,
    t_arrive: int = 20,
    t_end: int = 40,
    scene: dict | None = None,
) -> EpisodeSplit:
    """Episodes in one hand-made scene: the human walks from the fridge to the table along a
    straight line between t_arrive // 2 and t_arrive (or follows human_xy (T, 2) if given)."""
    cfg = DatasetConfig()
    sc = scene_from_json_dict(scene or ROOM)
    nav = scene_nav(sc, cfg)
    assert list(nav.field_object) == [0, 1], "both objects must be usable"
    stand_a, stand_b = nav.stand_poses[0], nav.stand_poses[1]
    T = t_end + 1
    eps = []
    for k, start in enumerate(robot_starts):
        if human_xy is not None:
            xy = np.asarray(human_xy[k], np.float32)
        else:
            frac = np.clip((np.arange(T) - t_arrive // 2) / (t_arrive - t_arrive // 2), 0.0, 1.0)
            xy = (stand_a[None, :2] + frac[:, None] * (stand_b[:2] - stand_a[:2])[None]).astype(np.float32)
        yaw = np.zeros(T, np.float32)
        phase = np.where(np.arange(T) < t_arrive // 2, PHASE_ACTIVITY_A, np.where(np.arange(T) < t_arrive, PHASE_WALK, PHASE_ACTIVITY_B))
        field_b = nav.fields[1]
        gy, gx = nav.grid.to_cell(start[:2])
        eps.append(
            {
                "scene_index": 0, "activity_a": 15, "activity_b": 4, "object_a": 11, "object_b": 4,
                "instance_a": 0, "instance_b": 1, "field_a": 0, "field_b": 1,
                "goal_xy": stand_b[:2].astype(np.float32),
                "robot_start": np.asarray(start, np.float32),
                "geodesic_start_goal_m": float(field_b[gy, gx]),
                "t_walk_start": t_arrive // 2, "t_arrive": t_arrive, "t_end": t_end,
                "root_xy": xy, "root_yaw": yaw, "joints_local": human_track(xy, yaw), "phase": phase.astype(np.int8),
            }
        )
    return EpisodeSplit("test", {}, (sc,), (nav,), stack_episodes(eps), cfg)


def goal_of(split: EpisodeSplit) -> np.ndarray:
    return split.episodes["goal_xy"][0]


def distance(a, b) -> float:
    return math.dist(tuple(a), tuple(b))
