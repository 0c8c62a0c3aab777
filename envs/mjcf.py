"""The MJCF model of a CoNav world, built once per slot layout and shared by every episode.

Geom order (ids are what the sensors report): the floor (0), render slots for every scene box
(`col_slots` blocking then `vis_slots` visual-only; seen only by the mjx.ray reference sensor),
`physics_slots` collision boxes (geom group 3, invisible to rays), the robot capsule, then the
humanoid's capsules. Per step the physics slots hold the blocking boxes nearest the robot; the
render slots hold the whole scene. Both are set by replacing `geom_pos` / `geom_size` in the MJX
model (batched under vmap); the humanoid's capsules are mocap bodies posed from the keyframes.
Collision filtering keeps only robot-vs-box and robot-vs-human pairs:
    physics slots: contype 1, conaffinity 0   robot: contype 2, conaffinity 1|4
    humanoid:      contype 4, conaffinity 0   render slots, floor: no collisions
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from mujoco import mjx

from conav_jax.config import TaskConfig
from envs.bank import PAD_Z_M
from envs.config import PhysicsConfig
from envs.humanoid import CAPSULE_HALF_LENGTHS, CAPSULE_RADII, NUM_CAPSULES

USERDATA_FIELDS = (
    "t",  # control steps taken
    "done",  # 1 once the episode has ended (reached, or t reached t_end)
    "reached",  # 1 once the robot has been within the success radius
    "t_reach",  # first step within the success radius, -1 before
    "collided",  # 1 once the robot has touched the human at or before its first reach
    "collided_before_reach",  # 1 if that happened before t_reach (the reaching step excluded)
    "collided_full",  # 1 once the robot has touched the human at any step (up to t_end)
    "path_length_m",  # robot path length up to t_reach
    "prev_geodesic_m",  # geodesic distance to the goal after the previous step
    "human_contact_steps",
    "wall_contact_steps",
    "nan_actions",  # steps whose action had a NaN (treated as a zero action)
    "human_touch",  # 1 if the robot touched the human in the last step (rollout traces)
    "wall_touch",  # 1 if it touched a wall or furniture in the last step
)
UD = {name: i for i, name in enumerate(USERDATA_FIELDS)}


@dataclass(frozen=True)
class GeomLayout:
    col_slots: int  # render slots for blocking boxes
    vis_slots: int  # render slots for visual-only boxes
    physics_slots: int  # collision boxes near the robot

    @property
    def floor(self) -> int:
        return 0

    @property
    def col_start(self) -> int:
        return 1

    @property
    def vis_start(self) -> int:
        return 1 + self.col_slots

    @property
    def physics_start(self) -> int:
        return 1 + self.col_slots + self.vis_slots

    @property
    def robot(self) -> int:
        return self.physics_start + self.physics_slots

    @property
    def human_start(self) -> int:
        return self.robot + 1

    @property
    def ngeom(self) -> int:
        return self.human_start + NUM_CAPSULES


PHYSICS_GROUP = 3  # geom group of the collision slots; rays exclude it
RAY_GEOMGROUP = tuple(0 if g == PHYSICS_GROUP else 1 for g in range(6))


def build_mjcf(layout: GeomLayout, task: TaskConfig, physics: PhysicsConfig) -> str:
    r, h = task.robot_radius_m, task.robot_height_m
    pad = f'pos="0 0 {PAD_Z_M}" size=".01 .01 .01"'
    lines = [
        '<mujoco model="conav">',
        f'  <option timestep="{physics.timestep_s}" integrator="implicitfast" gravity="0 0 0"'
        f' iterations="{physics.solver_iterations}" ls_iterations="{physics.ls_iterations}"/>',
        f'  <size nuserdata="{len(USERDATA_FIELDS)}"/>',
        # mjx.ray (mujoco-mjx 3.17) fails on a model without materials.
        '  <asset><material name="flat" rgba="1 1 1 1"/></asset>',
        "  <worldbody>",
        '    <geom name="floor" type="plane" size="500 500 0.1" contype="0" conaffinity="0" material="flat"/>',
    ]
    lines += [f'    <geom name="col{k}" type="box" {pad} contype="0" conaffinity="0" material="flat"/>' for k in range(layout.col_slots)]
    lines += [f'    <geom name="vis{k}" type="box" {pad} contype="0" conaffinity="0" material="flat"/>' for k in range(layout.vis_slots)]
    lines += [
        f'    <geom name="phys{k}" type="box" {pad} contype="1" conaffinity="0" condim="{physics.contact_condim}" group="{PHYSICS_GROUP}" material="flat"/>'
        for k in range(layout.physics_slots)
    ]
    lines += [
        '    <body name="robot">',
        '      <joint name="robot_x" type="slide" axis="1 0 0"/>',
        '      <joint name="robot_y" type="slide" axis="0 1 0"/>',
        '      <joint name="robot_yaw" type="hinge" axis="0 0 1"/>',
        f'      <geom name="robot" type="capsule" fromto="0 0 {r} 0 0 {h - r}" size="{r}" mass="{physics.robot_mass_kg}"'
        f' contype="2" conaffinity="5" condim="{physics.contact_condim}" material="flat"/>',
        "    </body>",
    ]
    for k in range(NUM_CAPSULES):
        lines.append(
            f'    <body name="human{k}" mocap="true" pos="0 0 {PAD_Z_M}"><geom name="human{k}" type="capsule"'
            f' size="{CAPSULE_RADII[k]:.4f} {CAPSULE_HALF_LENGTHS[k]:.4f}" contype="4" conaffinity="0" condim="{physics.contact_condim}" material="flat"/></body>'
        )
    lines += [
        "  </worldbody>",
        "  <actuator>",
        f'    <velocity name="vx" joint="robot_x" kv="{physics.kv_linear}" forcelimited="true"'
        f' forcerange="-{physics.force_limit_n} {physics.force_limit_n}"/>',
        f'    <velocity name="vy" joint="robot_y" kv="{physics.kv_linear}" forcelimited="true"'
        f' forcerange="-{physics.force_limit_n} {physics.force_limit_n}"/>',
        f'    <velocity name="wz" joint="robot_yaw" kv="{physics.kv_angular}" forcelimited="true"'
        f' forcerange="-{physics.torque_limit_nm} {physics.torque_limit_nm}"/>',
        "  </actuator>",
        "</mujoco>",
    ]
    return "\n".join(lines)


def build_model(layout: GeomLayout, task: TaskConfig, physics: PhysicsConfig) -> tuple[mujoco.MjModel, mjx.Model]:
    if layout.ngeom > 255:
        raise ValueError(f"{layout.ngeom} geoms: the sensors' packed ids allow at most 255; lower max boxes per scene")
    m = mujoco.MjModel.from_xml_string(build_mjcf(layout, task, physics))
    assert m.ngeom == layout.ngeom and m.geom("robot").id == layout.robot
    return m, mjx.put_model(m)


def robot_body_id(m: mujoco.MjModel) -> int:
    return int(m.body("robot").id)


def box_geometry(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MJX geom_pos / geom_size (half-extents) of boxes from their corners."""
    return (lo + hi) / 2.0, (hi - lo) / 2.0
