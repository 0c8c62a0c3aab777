"""The episode bank: a dataset split as stacked device arrays the jitted env indexes into.

Scenes differ in how many boxes they have; the bank pads every scene to common slot counts
(blocking boxes, which the robot collides with, and visual-only boxes such as carpets and
ceiling lamps). Padding slots sit below the floor with a tiny size and are masked out of the
fast caster, so they cost a few collision tests per step but change nothing. Grouping batches
by scene would avoid that cost; padding keeps one compiled step for any mix of scenes.
Geodesic fields are padded to the largest grid and extended into blocked cells near free space.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from conav_jax.data.activities import NUM_ACTIVITIES
from conav_jax.data.categories import FLOOR_RGB, NUM_CATEGORIES
from conav_jax.data.episodes import EpisodeSplit
from conav_jax.data.materials import MATERIAL_WIDTH, clothing_rgb
from conav_jax.data.scene import scene_boxes
from conav_jax.nav.expert import clearance_map
from conav_jax.nav.planning import fill_blocked
from conav_jax.envs.metrics import shortest_path_steps

PAD_Z_M = -10.0  # padding boxes live here, below the floor


@dataclass(frozen=True)
class EpisodeBank:
    """Device arrays. S scenes, N episodes, T steps, Gc blocking and Gv visual box slots."""

    # per scene
    col_lo: jax.Array  # (S, Gc, 3) blocking box min corners (m)
    col_hi: jax.Array  # (S, Gc, 3)
    col_valid: jax.Array  # (S, Gc) bool
    col_rgb: jax.Array  # (S, Gc, 3) float in [0, 1]: flat colours (SensorConfig.materials "flat")
    col_material: jax.Array  # (S, Gc, MATERIAL_WIDTH) material rows (conav_jax.data.materials)
    col_category: jax.Array  # (S, Gc) int32 object category, -1 for walls and padding
    vis_lo: jax.Array  # (S, Gv, 3) visual-only boxes
    vis_hi: jax.Array
    vis_valid: jax.Array
    vis_rgb: jax.Array
    vis_material: jax.Array
    vis_category: jax.Array
    floor_material: jax.Array  # (S, MATERIAL_WIDTH)
    fields: jax.Array  # (S, K, ny, nx) float16 geodesic metres to each usable object
    field_origin: jax.Array  # (S, 2) grid origin (m)
    field_category: jax.Array  # (S, K) category id of each field's object, -1 for padding
    field_stand: jax.Array  # (S, K, 3) standing pose (x, y, facing yaw) of each field's object
    clearance: jax.Array  # (S, ny, nx) float32 signed wall clearance (m) on the field grid (the expert's)
    # per episode
    scene_index: jax.Array  # (N,)
    activity_b: jax.Array
    object_b: jax.Array
    field_a: jax.Array
    field_b: jax.Array
    goal_xy: jax.Array  # (N, 2)
    robot_start: jax.Array  # (N, 3)
    geodesic_start_goal_m: jax.Array  # (N,)
    shortest_path_steps: jax.Array  # (N,) float32: SPL's l, the fewest control steps to the goal radius
    t_arrive: jax.Array
    t_end: jax.Array
    root_xy: jax.Array  # (N, T, 2)
    root_yaw: jax.Array  # (N, T)
    joints_local: jax.Array  # (N, T, 22, 3) float16
    phase: jax.Array  # (N, T) int8
    clothing_rgb: jax.Array  # (N, 3, 3) float in [0, 1]: the humanoid's skin, shirt, trousers
    cell_m: float = 0.1

    @property
    def num_episodes(self) -> int:
        return int(self.t_end.shape[0])

    @property
    def max_steps(self) -> int:
        return int(self.phase.shape[1])

    @property
    def col_slots(self) -> int:
        return int(self.col_lo.shape[1])

    @property
    def vis_slots(self) -> int:
        return int(self.vis_lo.shape[1])


# `cell_m` is a static python float, not an array leaf.
jax.tree_util.register_dataclass(
    EpisodeBank,
    data_fields=[f for f in EpisodeBank.__dataclass_fields__ if f != "cell_m"],
    meta_fields=["cell_m"],
)


def _pad_boxes(boxes: list[tuple[np.ndarray, ...]], slots: int):
    """Per scene (centres, half-extents, rgb, material rows, categories) -> padded (lo, hi,
    rgb, valid, material, category) arrays of `slots` boxes per scene."""
    lo = np.zeros((len(boxes), slots, 3), np.float32)
    hi = np.zeros((len(boxes), slots, 3), np.float32)
    rgb = np.zeros((len(boxes), slots, 3), np.float32)
    valid = np.zeros((len(boxes), slots), bool)
    material = np.zeros((len(boxes), slots, MATERIAL_WIDTH), np.float32)
    cat = np.full((len(boxes), slots), -1, np.int32)
    lo[..., 2] = PAD_Z_M - 0.01
    hi[..., 2] = PAD_Z_M + 0.01
    lo[..., :2] = -0.01
    hi[..., :2] = 0.01
    for s, (c, h, col, mat, category) in enumerate(boxes):
        n = len(c)
        lo[s, :n], hi[s, :n], rgb[s, :n], valid[s, :n] = c - h, c + h, col, True
        material[s, :n], cat[s, :n] = mat, category
    return lo, hi, rgb, valid, material, cat


def build_bank(split: EpisodeSplit, min_col_slots: int = 0, min_vis_slots: int = 1) -> EpisodeBank:
    """Stack a loaded split (all of the dataset's scenes, this split's episodes) for the device."""
    task = split.config.task
    robot_h = task.robot_height_m
    col, vis = [], []
    for scene in split.scenes:
        b = scene_boxes(scene, robot_h)
        arrays = (b.center, b.half_extents, b.rgb.astype(np.float32) / 255.0, b.material,
                  b.category)  # STRUCTURE_WALL is -1: no category
        m = b.blocks_robot
        col.append(tuple(a[m] for a in arrays))
        vis.append(tuple(a[~m] for a in arrays))
    gc = max(min_col_slots, max(len(c[0]) for c in col))
    gv = max(min_vis_slots, max(len(v[0]) for v in vis))
    col_lo, col_hi, col_rgb, col_valid, col_material, col_category = _pad_boxes(col, gc)
    vis_lo, vis_hi, vis_rgb, vis_valid, vis_material, vis_category = _pad_boxes(vis, gv)

    cell = float(split.navs[0].grid.cell_m)
    k = max(1, max(n.fields.shape[0] for n in split.navs))
    ny = max(n.grid.shape[0] for n in split.navs)
    nx = max(n.grid.shape[1] for n in split.navs)
    fields = np.full((len(split.navs), k, ny, nx), np.inf, np.float16)
    clearance = np.full((len(split.navs), ny, nx), -cell, np.float32)  # padding reads as blocked
    origin = np.zeros((len(split.navs), 2), np.float32)
    field_cat = np.full((len(split.navs), k), -1, np.int32)
    field_stand = np.zeros((len(split.navs), k, 3), np.float32)
    for s, (scene, nav) in enumerate(zip(split.scenes, split.navs)):
        gy, gx = nav.grid.shape
        for j in range(nav.fields.shape[0]):
            fields[s, j, :gy, :gx] = fill_blocked(nav.fields[j], nav.grid.free, cell)
            field_cat[s, j] = scene.objects[int(nav.field_object[j])].category_index
            field_stand[s, j] = nav.stand_poses[j]
        origin[s] = nav.grid.origin
        clearance[s, :gy, :gx] = clearance_map(nav.grid.free, cell)
    e = split.episodes
    return EpisodeBank(
        col_lo=jnp.asarray(col_lo),
        col_hi=jnp.asarray(col_hi),
        col_valid=jnp.asarray(col_valid),
        col_rgb=jnp.asarray(col_rgb),
        col_material=jnp.asarray(col_material),
        col_category=jnp.asarray(col_category),
        vis_lo=jnp.asarray(vis_lo),
        vis_hi=jnp.asarray(vis_hi),
        vis_valid=jnp.asarray(vis_valid),
        vis_rgb=jnp.asarray(vis_rgb),
        vis_material=jnp.asarray(vis_material),
        vis_category=jnp.asarray(vis_category),
        floor_material=jnp.asarray(np.stack([s.materials.floor.row() for s in split.scenes])),
        fields=jnp.asarray(fields),
        field_origin=jnp.asarray(origin),
        field_category=jnp.asarray(field_cat),
        field_stand=jnp.asarray(field_stand),
        clearance=jnp.asarray(clearance),
        scene_index=jnp.asarray(e["scene_index"]),
        activity_b=jnp.asarray(e["activity_b"]),
        object_b=jnp.asarray(e["object_b"]),
        field_a=jnp.asarray(e["field_a"]),
        field_b=jnp.asarray(e["field_b"]),
        goal_xy=jnp.asarray(e["goal_xy"]),
        robot_start=jnp.asarray(e["robot_start"]),
        geodesic_start_goal_m=jnp.asarray(e["geodesic_start_goal_m"]),
        shortest_path_steps=jnp.asarray(shortest_path_steps(
            e["geodesic_start_goal_m"], task.success_radius_m, task.v_max_mps * task.control_dt_s), jnp.float32),
        t_arrive=jnp.asarray(e["t_arrive"]),
        t_end=jnp.asarray(e["t_end"]),
        root_xy=jnp.asarray(e["root_xy"]),
        root_yaw=jnp.asarray(e["root_yaw"]),
        joints_local=jnp.asarray(e["joints_local"]),
        phase=jnp.asarray(e["phase"]),
        clothing_rgb=jnp.asarray(clothing_rgb(np.arange(len(e["t_end"]))).astype(np.float32) / 255.0),
        cell_m=cell,
    )


FLOOR_RGB_F = np.asarray(FLOOR_RGB, np.float32) / 255.0
__all__ = ["EpisodeBank", "build_bank", "NUM_ACTIVITIES", "NUM_CATEGORIES", "FLOOR_RGB_F", "PAD_Z_M"]
