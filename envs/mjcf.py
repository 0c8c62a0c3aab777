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

The MJX model and data are built for PhysicsConfig.impl ("jax" or "warp", already resolved).
MuJoCo Warp's data gets contact and constraint buffers sized by `warp_data_sizes`; Warp takes
world-body geoms for static, so the env also writes the physics slots' world positions into the
data (ConavEnv._mjx_data), and its velocity servos carry their force limits differently
(build_mjcf).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from mujoco import mjx

from conav_jax.config import TaskConfig
from conav_jax.envs.bank import PAD_Z_M
from conav_jax.envs.config import PhysicsConfig
from conav_jax.envs.humanoid import CAPSULE_HALF_LENGTHS, CAPSULE_RADII, NUM_CAPSULES

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


def build_mjcf(layout: GeomLayout, task: TaskConfig, physics: PhysicsConfig,
               render_cameras_fovy_deg: float | None = None) -> str:
    """The world's MJCF. `render_cameras_fovy_deg` (None: the model every env steps) adds the
    cameras MuJoCo Warp's batch renderer draws from (envs.mjwarp_render): four on the robot body
    at the camera height, cam0..cam3 at yaw offsets 0, 90, 180 and 270 degrees (forward, left,
    back, right), with that vertical field of view; and moves the robot's capsule to geom group
    4, which the renderer leaves out, since the cameras sit on its top. Geom ids are unchanged."""
    r, h = task.robot_radius_m, task.robot_height_m
    # The velocity servos' force limits. MJX's JAX implementation integrates a servo's damping
    # implicitly (implicitfast) even while the limit clips its force; MuJoCo Warp, as MuJoCo C,
    # then integrates it explicitly, and at these gains the yaw servo overshoots (timestep x
    # kv_angular / the robot's yaw inertia = 2.4 > 2). For Warp the servos are unlimited and the
    # env clips the commanded velocity error to force_limit / kv instead (servo_error_limits):
    # the same force, the damping kept implicit, the same motion as JAX's.
    if physics.impl == "warp":
        lin = ang = 'forcelimited="false"'
    else:
        lin = f'forcelimited="true" forcerange="-{physics.force_limit_n} {physics.force_limit_n}"'
        ang = f'forcelimited="true" forcerange="-{physics.torque_limit_nm} {physics.torque_limit_nm}"'
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
    robot_group = "" if render_cameras_fovy_deg is None else ' group="4"'
    lines += [
        '    <body name="robot">',
        '      <joint name="robot_x" type="slide" axis="1 0 0"/>',
        '      <joint name="robot_y" type="slide" axis="0 1 0"/>',
        '      <joint name="robot_yaw" type="hinge" axis="0 0 1"/>',
        f'      <geom name="robot" type="capsule" fromto="0 0 {r} 0 0 {h - r}" size="{r}" mass="{physics.robot_mass_kg}"'
        f' contype="2" conaffinity="5" condim="{physics.contact_condim}"{robot_group} material="flat"/>',
    ]
    if render_cameras_fovy_deg is not None:
        for k in range(4):
            # A camera looks along its -z with x to the right and y up: for yaw offset psi that
            # is x = (sin psi, -cos psi, 0), y = (0, 0, 1).
            psi = k * np.pi / 2
            lines.append(
                f'      <camera name="cam{k}" pos="0 0 {task.camera_height_m}" fovy="{render_cameras_fovy_deg:.9f}"'
                f' xyaxes="{np.sin(psi):.9f} {-np.cos(psi):.9f} 0 0 0 1"/>'
            )
    lines.append("    </body>")
    for k in range(NUM_CAPSULES):
        lines.append(
            f'    <body name="human{k}" mocap="true" pos="0 0 {PAD_Z_M}"><geom name="human{k}" type="capsule"'
            f' size="{CAPSULE_RADII[k]:.4f} {CAPSULE_HALF_LENGTHS[k]:.4f}" contype="4" conaffinity="0" condim="{physics.contact_condim}" material="flat"/></body>'
        )
    lines += [
        "  </worldbody>",
        "  <actuator>",
        f'    <velocity name="vx" joint="robot_x" kv="{physics.kv_linear}" {lin}/>',
        f'    <velocity name="vy" joint="robot_y" kv="{physics.kv_linear}" {lin}/>',
        f'    <velocity name="wz" joint="robot_yaw" kv="{physics.kv_angular}" {ang}/>',
        "  </actuator>",
        "</mujoco>",
    ]
    return "\n".join(lines)


def build_model(layout: GeomLayout, task: TaskConfig, physics: PhysicsConfig,
                render_cameras_fovy_deg: float | None = None) -> tuple[mujoco.MjModel, mjx.Model]:
    """(MjModel, MJX model for `physics.impl`, "jax" or "warp"); with `render_cameras_fovy_deg`,
    of the model with the renderer's cameras (build_mjcf)."""
    if layout.ngeom > 255:
        raise ValueError(f"{layout.ngeom} geoms: the sensors' packed ids allow at most 255; lower max boxes per scene")
    if physics.impl not in ("jax", "warp"):
        raise ValueError(f"build_model needs a resolved physics impl (jax or warp), got {physics.impl!r}")
    m = mujoco.MjModel.from_xml_string(build_mjcf(layout, task, physics, render_cameras_fovy_deg))
    assert m.ngeom == layout.ngeom and m.geom("robot").id == layout.robot
    if physics.impl == "jax":
        return m, mjx.put_model(m)
    mx = mjx.put_model(m, impl="warp")
    # The solver runs a fixed budget (PhysicsConfig.solver_iterations / ls_iterations) by design:
    # MuJoCo Warp's notices that it stopped there would print on most contact substeps of every
    # world. Notices of lost contacts or constraint rows stay on.
    from mujoco.mjx.third_party import mujoco_warp as mjw

    quiet = int(mjw.OverflowType.ALL) & ~int(mjw.OverflowType.ITERATIONS | mjw.OverflowType.LS_ITERATIONS)
    opt = mx.opt.replace(_impl=mx.opt._impl.replace(warn_overflow=quiet))
    return m, mx.replace(opt=opt)


def warp_lost_contact_bits() -> int:
    """MuJoCo Warp's overflow bits that mean contacts or constraint rows were dropped. Its data
    keeps them per world in `overflow` until the data is remade (for the env: the episode)."""
    from mujoco.mjx.third_party import mujoco_warp as mjw

    o = mjw.OverflowType
    return int(o.NEFC | o.NJMAX_NNZ | o.BROADPHASE | o.NARROWPHASE)


def warp_data_sizes(layout: GeomLayout, physics: PhysicsConfig) -> tuple[int, int]:
    """(naconmax, njmax) of MuJoCo Warp's data: contacts in the buffer all worlds share, and
    constraint rows per world. The robot is the only body that collides; each robot-box and
    robot-capsule pair gives at most 2 contacts, each of 1 row (condim 1) or 4 (condim 3,
    pyramidal friction cone)."""
    contacts_per_world = 2 * (layout.physics_slots + NUM_CAPSULES)
    rows_per_contact = 1 if physics.contact_condim == 1 else 2 * (physics.contact_condim - 1)
    return physics.warp_max_worlds * contacts_per_world, contacts_per_world * rows_per_contact


def make_data(mj_model: mujoco.MjModel, mjx_model: mjx.Model, layout: GeomLayout, physics: PhysicsConfig) -> mjx.Data:
    """Fresh MJX data for `build_model`'s model (qpos0, nothing moving)."""
    if physics.impl == "jax":
        return mjx.make_data(mjx_model)
    naconmax, njmax = warp_data_sizes(layout, physics)
    return mjx.make_data(mj_model, impl="warp", naconmax=naconmax, njmax=njmax)


def servo_error_limits(physics: PhysicsConfig) -> np.ndarray | None:
    """Largest velocity error (m/s, m/s, rad/s) of the x, y, yaw servos the env commands, where
    the model's servos have no force limit (impl "warp", build_mjcf); None where they have."""
    if physics.impl != "warp":
        return None
    lin, ang = physics.force_limit_n / physics.kv_linear, physics.torque_limit_nm / physics.kv_angular
    return np.array([lin, lin, ang], np.float32)


def robot_body_id(m: mujoco.MjModel) -> int:
    return int(m.body("robot").id)


def box_geometry(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MJX geom_pos / geom_size (half-extents) of boxes from their corners."""
    return (lo + hi) / 2.0, (hi - lo) / 2.0
