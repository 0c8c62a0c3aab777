"""MuJoCo Warp's batch ray-traced renderer on CoNav scenes, beside our panorama caster.

The robot's view becomes four cameras on the robot body at the camera height, yaw offsets 0, 90,
180 and 270 degrees (envs.mjcf.build_mjcf with `render_cameras_fovy_deg`), each H x W/4 pixels:
together the W columns of our H x W panorama (envs.panorama). Two ray layouts:

- "panorama": our equirectangular rays are loaded into the render context's ray table, so camera
  k casts exactly the panorama's columns [3W/8 - kW/4, 5W/8 - kW/4) mod W and every pixel is a ray
  both renderers cast. MuJoCo Warp's depth is planar (along the camera's axis); dividing by the
  cosine of each ray to its camera's axis gives the distance along the ray, as ours.
- "pinhole": MuJoCo Warp's own perspective cameras, 90 degrees across with square pixels on the
  image plane (vertical field of view 2 atan(4H/W)). Its rays are spaced evenly in tangent, ours
  in angle, and H is even, so no pixel centre lies on a camera's axis: no ray but the axis itself
  (which no pixel samples) is common to both layouts; `pinhole_pixels_of_panorama` pairs each
  panorama ray with the nearest pinhole pixel (a resampling, half a pixel off at most).

Colours are flat, as our `colourise` (SensorConfig.materials "flat"): no lights, and MuJoCo's
headlight set to ambient 1, diffuse and specular 0, so a hit shows its geom's RGB (quantised to
8 bits). It does not draw our instance materials: their patterns are functions of the hit point
(envs.panorama.shade) that MuJoCo Warp's per-geom colours and textures cannot express, so
compare it with an env rendering "flat". Nothing hit (or hit beyond
SensorConfig.max_depth_m) shows the sky. The robot's capsule is left out of the render (the
cameras sit on its top), as are the physics slots; geom ids are the env's.

What MuJoCo Warp needs per world, written here in JAX from (episode, robot pose, step) with no
kinematics call: the geoms' world poses in the data (geom_xpos, geom_xmat: the scene boxes are
world-body geoms, which MuJoCo Warp's kinematics poses once in make_data and never again, so
their per-episode centres must be written; the humanoid's capsules from its keyframes; the
cameras from the pose), and the episode's box half-sizes and colours in the model (geom_size,
geom_rgba, batched per world: the renderer and the BVH read row `worldid % rows`). Each frame
then refits the BVH (`refit_bvh`: every render geom's AABB recomputed from pose and size, the one
BVH over all worlds' geoms refitted in place, never rebuilt) and renders. The BVH's topology is
built once, with the render context, from the host model's poses (`seed_topology` puts a real
scene there first). The context fixes the number of worlds (`batch`): its BVH and outputs are
sized by it.
Data flow: (episode, robot pose, step) per world -> poses, sizes, colours (JAX) -> refit_bvh ->
render (Warp through JAX's FFI) -> packed RGB, planar depth, geom ids per camera -> views (RGB
uint8, depth along the ray m, ids) -> the panorama layout (H, W), as ConavEnv.render_at gives.
"""

from __future__ import annotations

import dataclasses
import re
import time
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from conav_jax.envs.config import SensorConfig
from conav_jax.envs.humanoid import capsule_poses, quat_z_to
from conav_jax.envs.mjcf import build_model
from conav_jax.envs.panorama import SKY_RGB, ray_angles

if TYPE_CHECKING:
    from conav_jax.envs.conav_env import ConavEnv

RAY_LAYOUTS = ("panorama", "pinhole")
NUM_CAMERAS = 4
# Geom groups the renderer draws: the floor, scene boxes and humanoid (0). Left out: the physics
# slots (3) and, in the render model, the robot's capsule (4).
RENDER_GEOM_GROUPS = (0, 1, 2)
SKY_RGB_U8 = np.floor(SKY_RGB * 255.0).astype(np.uint8)  # as MuJoCo Warp packs its background


def camera_fovy_deg(cfg: SensorConfig) -> float:
    """Vertical field of view (degrees) of a pinhole camera W/4 pixels wide and H high, square
    pixels on the image plane, 90 degrees across: 90 at the default 112x448."""
    return float(np.degrees(2.0 * np.arctan(4.0 * cfg.height / cfg.width)))


def camera_strip_columns(cfg: SensorConfig) -> tuple[np.ndarray, np.ndarray]:
    """(camera (W,), column within that camera's image (W,)) of each panorama column: camera k
    (yaw offset k x 90 degrees) holds columns [3W/8 - kW/4, 5W/8 - kW/4) mod W, left to right."""
    w = cfg.width // NUM_CAMERAS
    j = np.arange(cfg.width)
    c = (j + cfg.width // 8) % cfg.width  # column in the strip [cam2 | cam1 | cam0 | cam3]
    cam = np.array([2, 1, 0, 3])[c // w]
    return cam, c % w


def panorama_camera_rays(cfg: SensorConfig) -> np.ndarray:
    """(H, W/4, 3) unit rays in a camera's frame (x right, y up, looking along -z) that cast the
    panorama's rays: relative azimuth a = pi/4 - 2 pi (u + 0.5) / W for image column u (the
    panorama's, from the camera's yaw) and row elevations e as envs.panorama.ray_angles."""
    w = cfg.width // NUM_CAMERAS
    _, el = ray_angles(cfg)
    u = np.arange(w, dtype=np.float64)
    a = np.pi / 4 - 2.0 * np.pi * (u + 0.5) / cfg.width
    e = el.astype(np.float64)[:, None]
    rays = np.stack(np.broadcast_arrays(-np.cos(e) * np.sin(a), np.sin(e), -np.cos(e) * np.cos(a)), axis=-1)
    return rays.astype(np.float32)


def pinhole_pixels_of_panorama(cfg: SensorConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For each panorama pixel (H, W): (camera, row, column) of the nearest pinhole pixel on the
    image plane, and whether the ray falls inside that camera's image (the panorama's corner rows
    reach above and below it: elevation 45 degrees at 45 degrees azimuth is 54.7 on the plane)."""
    h, w = cfg.height, cfg.width // NUM_CAMERAS
    cam, u_strip = camera_strip_columns(cfg)
    _, el = ray_angles(cfg)
    a = np.pi / 4 - 2.0 * np.pi * (u_strip + 0.5) / cfg.width  # (W,) azimuth from the camera's axis
    x = -np.tan(a)[None, :]  # image-plane coordinates at unit distance, x right, y up
    y = np.tan(el)[:, None] / np.cos(a)[None, :]
    half_h = 4.0 * h / cfg.width  # tan(fovy / 2); the half-width is tan(45 degrees) = 1
    col = np.floor((x + 1.0) / 2.0 * w).astype(np.int64)
    row = np.floor((half_h - y) / (2.0 * half_h) * h).astype(np.int64)
    inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
    cams = np.broadcast_to(cam[None, :], (h, cfg.width))
    return cams, np.clip(row, 0, h - 1), np.broadcast_to(np.clip(col, 0, w - 1), (h, cfg.width)), inside


@dataclasses.dataclass(frozen=True, eq=False)
class MjwarpRenderer:
    """A render context for `batch` worlds of an env's scenes, and what feeds it. Constants only."""

    env: ConavEnv  # whose bank, layout and sensor config it renders
    batch: int  # worlds per render call (the context's nworld)
    rays: str  # "panorama" or "pinhole"
    segmentation: bool  # whether renders return geom ids
    mj_model: mujoco.MjModel  # the render model (cameras on the robot)
    model: mjx.Model  # its MuJoCo Warp model, geoms without materials (per-world rgba is used)
    context: object  # mujoco.mjx.warp.render_context.RenderContext
    data0: mjx.Data  # template data, poses replaced per world
    geom_xpos0: np.ndarray  # (ngeom, 3) poses at qpos0 (the floor's; the rest are replaced)
    geom_xmat0: np.ndarray  # (ngeom, 3, 3)
    ray_cos: np.ndarray  # (4, H, W/4) cosine of each pixel's ray to its camera's axis
    context_create_s: float
    warp_live_bytes: int | None  # Warp's allocations kept by the context (BVH, rays, bounds)
    warp_peak_bytes: int | None  # their peak while it was made (with its zeroed output buffers)


def _parse_warp_report(text: str) -> tuple[int | None, int | None]:
    """(live bytes, peak bytes) summed over devices from a Warp allocation report."""
    units = {"B": 1, "KB": 1 << 10, "MB": 1 << 20, "GB": 1 << 30, "TB": 1 << 40}

    def section(name: str, pattern: str) -> int | None:
        m = re.search(name + r":\n((?:[ \t]+\S+[^\n]*\n?)+)", text)
        if not m:
            return None
        vals = [float(v) * units[u] for v, u in re.findall(pattern, m.group(1))]
        return int(sum(vals)) if vals else None

    return (section("Live allocations", r"\(([\d.]+) ([KMGT]?B)\)"),
            section("Peak usage", r"\S+\s+([\d.]+) ([KMGT]?B)"))


def seed_topology(m: mujoco.MjModel, env: ConavEnv, episode: int) -> None:
    """Put `episode`'s scene boxes (render slots) and its humanoid at step 0 (mocap bodies) into
    the host model `m`. MuJoCo Warp builds its BVH's topology once, when the render context is
    made, from the model's poses, and afterwards only refits the bounds: built from the model as
    it is (every render slot a padding box at the same spot) the tree groups boxes at random."""
    b, lay = env.bank, env.layout
    s = int(b.scene_index[episode])
    lo = np.concatenate([np.asarray(b.col_lo[s]), np.asarray(b.vis_lo[s])])
    hi = np.concatenate([np.asarray(b.col_hi[s]), np.asarray(b.vis_hi[s])])
    boxes = slice(lay.col_start, lay.physics_start)
    m.geom_pos[boxes] = (lo + hi) / 2.0
    m.geom_size[boxes] = (hi - lo) / 2.0
    centre, axis, _ = capsule_poses(env.human_joints(jnp.int32(episode), jnp.int32(0)))
    bodies = m.geom_bodyid[lay.human_start:lay.ngeom]
    m.body_pos[bodies] = np.asarray(centre)
    m.body_quat[bodies] = np.asarray(quat_z_to(axis))


def make_renderer(env: ConavEnv, batch: int, rays: str = "panorama", segmentation: bool = False,
                  topology_episode: int | None = 0) -> MjwarpRenderer:
    """The render model and a render context for `batch` worlds of `env`'s scenes, rendering
    RGB and depth (and geom ids with `segmentation`) at the env's SensorConfig resolution. The
    BVH's topology comes from episode `topology_episode`'s scene (`seed_topology`; None: from the
    model's padding poses); every world refits it to its own scene."""
    import warp as wp

    if rays not in RAY_LAYOUTS:
        raise ValueError(f"rays must be one of {RAY_LAYOUTS}, got {rays!r}")
    cfg = env.config.sensor
    physics = dataclasses.replace(env.config.physics, impl="warp")
    m, mx = build_model(env.layout, env.task, physics, render_cameras_fovy_deg=camera_fovy_deg(cfg))
    # The context reads these at creation: the far plane (MuJoCo Warp drops hits whose planar
    # depth is beyond it; a hit's planar depth is at most its distance along the ray, so only hits
    # that ours reads as nothing are dropped) and a headlight that lights every surface at
    # exactly its colour.
    m.stat.extent = 1.0
    m.vis.map.znear = 0.01
    m.vis.map.zfar = cfg.max_depth_m
    m.vis.headlight.active = 1
    m.vis.headlight.ambient = (1.0, 1.0, 1.0)
    m.vis.headlight.diffuse = (0.0, 0.0, 0.0)
    m.vis.headlight.specular = (0.0, 0.0, 0.0)
    if topology_episode is not None:
        seed_topology(m, env, topology_episode)
    w, h = cfg.width // NUM_CAMERAS, cfg.height
    t0 = time.perf_counter()
    reports: list[str] = []
    with wp.ScopedMemoryTracker("mjwarp_render", print=False, report_func=reports.append) as tracker:
        tracker.clear()  # its totals are global: count only what this context allocates
        ctx = mjx.create_render_context(
            mjm=m, nworld=batch, cam_res=(w, h), render_rgb=True, render_depth=True, render_seg=segmentation,
            use_textures=False, use_shadows=False, enabled_geom_groups=list(RENDER_GEOM_GROUPS),
            background_color=(*SKY_RGB.tolist(), 1.0), enable_specular=False, enable_emission=False,
            enable_per_light_ambient=False,
            # No camera is inside a render geom (the robot is left out), so culling back faces
            # would only cost time.
            enable_backface_culling=False,
        )
        if rays == "panorama":
            table = np.tile(panorama_camera_rays(cfg).reshape(-1, 3), (NUM_CAMERAS, 1))
            for c in ctx._contexts.values():  # MuJoCo Warp's context per device it renders on
                c.ray.assign(table)
        tracker.report()
    context_create_s = time.perf_counter() - t0
    live, peak = _parse_warp_report(reports[0]) if reports else (None, None)
    ray_table = ctx.ray.numpy()[: NUM_CAMERAS * w * h].reshape(NUM_CAMERAS, h, w, 3)
    d_host = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d_host)
    # A material would override rgba (MuJoCo Warp does where a geom keeps MuJoCo's default grey).
    model = mx.replace(geom_matid=jnp.full_like(mx.geom_matid, -1))
    return MjwarpRenderer(
        env=env, batch=batch, rays=rays, segmentation=segmentation, mj_model=m, model=model, context=ctx,
        data0=mjx.make_data(m, impl="warp"), geom_xpos0=d_host.geom_xpos.astype(np.float32).copy(),
        geom_xmat0=d_host.geom_xmat.reshape(-1, 3, 3).astype(np.float32).copy(),
        ray_cos=(-ray_table[..., 2]).astype(np.float32), context_create_s=context_create_s,
        warp_live_bytes=live, warp_peak_bytes=peak,
    )


def _quat_to_mat(q: jax.Array) -> jax.Array:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) (w, x, y, z)."""
    w, x, y, z = jnp.moveaxis(q, -1, 0)
    return jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def world_inputs(r: MjwarpRenderer, episode: jax.Array, robot_pose: jax.Array, t: jax.Array):
    """(geom_size (ngeom, 3), geom_rgba (ngeom, 4), data) of one world: the robot at
    `robot_pose` (x m, y m, yaw rad), the humanoid at step `t` of `episode`."""
    env = r.env
    b, lay = env.bank, env.layout
    s = b.scene_index[episode]
    lo = jnp.concatenate([b.col_lo[s], b.vis_lo[s]])
    hi = jnp.concatenate([b.col_hi[s], b.vis_hi[s]])
    boxes = slice(lay.col_start, lay.physics_start)
    humans = slice(lay.human_start, lay.ngeom)
    centre, axis, _ = capsule_poses(env.human_joints(episode, jnp.asarray(t, jnp.int32)))
    geom_xpos = jnp.asarray(r.geom_xpos0).at[boxes].set((lo + hi) / 2.0).at[humans].set(centre)
    # The humanoid's mocap bodies carry these quaternions in the env (ConavEnv._pose_human).
    geom_xmat = jnp.asarray(r.geom_xmat0).at[humans].set(_quat_to_mat(quat_z_to(axis)))
    geom_size = r.model.geom_size.at[boxes].set((hi - lo) / 2.0)
    rgb = env._geom_rgb(episode)  # the colours our caster's colourise uses
    geom_rgba = jnp.concatenate([rgb, jnp.ones(rgb.shape[:1] + (1,), rgb.dtype)], axis=-1)
    pose = jnp.asarray(robot_pose, jnp.float32)
    c, sn = jnp.cos(pose[2]), jnp.sin(pose[2])
    rz = jnp.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
    # The robot body sits at (x, y, 0) turned by yaw; its cameras at their body-frame poses.
    cam_xpos = jnp.array([pose[0], pose[1], 0.0]) + jnp.asarray(r.mj_model.cam_pos, jnp.float32) @ rz.T
    cam_xmat = rz @ jnp.asarray(r.mj_model.cam_mat0.reshape(-1, 3, 3), jnp.float32)
    d = r.data0.replace(qpos=pose.astype(r.data0.qpos.dtype), geom_xpos=geom_xpos, geom_xmat=geom_xmat,
                        cam_xpos=cam_xpos, cam_xmat=cam_xmat)
    return geom_size, geom_rgba, d


def render_views(r: MjwarpRenderer, episodes: jax.Array, robot_poses: jax.Array, t: jax.Array) -> dict:
    """The four cameras' views of `batch` worlds: episodes (B,), robot poses (B, 3) and humanoid
    steps (B,) -> {"rgb": (B, 4, H, W/4, 3) uint8, "depth_m": (B, 4, H, W/4) along the ray,
    max_depth_m where nothing is hit within it, "geom_ids": (B, 4, H, W/4) int32 (-1 none) with
    segmentation, else None}. Camera k looks at yaw + k x 90 degrees."""
    cfg = r.env.config.sensor
    if episodes.shape[0] != r.batch:
        raise ValueError(f"the render context holds {r.batch} worlds, got a batch of {episodes.shape[0]}")
    ctx = r.context.pytree()

    def one(episode, pose, step):
        size, rgba, d = world_inputs(r, episode, pose, step)
        m = r.model.replace(geom_size=size, geom_rgba=rgba)
        d = mjx.refit_bvh(m, d, ctx)
        if r.segmentation:
            rgb, depth, seg, _ = mjx.render_with_segmentation(m, d, ctx)
            return rgb, depth, seg[..., 0]
        rgb, depth, _ = mjx.render(m, d, ctx)
        return rgb, depth, None

    packed, planar, seg = jax.vmap(one)(episodes, robot_poses, t)
    shape = (r.batch, NUM_CAMERAS, cfg.height, cfg.width // NUM_CAMERAS)
    packed = packed.reshape(shape)
    depth = planar.reshape(shape) / jnp.asarray(r.ray_cos)
    miss = (planar.reshape(shape) <= 0.0) | (depth >= cfg.max_depth_m)
    rgb = jnp.stack([(packed >> 16) & 0xFF, (packed >> 8) & 0xFF, packed & 0xFF], axis=-1).astype(jnp.uint8)
    rgb = jnp.where(miss[..., None], jnp.asarray(SKY_RGB_U8), rgb)
    ids = None if seg is None else jnp.where(miss, -1, seg.reshape(shape).astype(jnp.int32))
    return {"rgb": rgb, "depth_m": jnp.where(miss, cfg.max_depth_m, depth), "geom_ids": ids}


def views_to_panorama(r: MjwarpRenderer, views: dict) -> tuple[jax.Array, jax.Array | None]:
    """(rgbd (B, H, W, 4) float32: RGB in [0, 1] and depth m, geom ids (B, H, W) or None): the
    views side by side in the panorama's column order (ConavEnv.render_at's format). Under the
    "pinhole" layout this is a strip of four perspective images, not an equirectangular panorama."""
    cam, col = camera_strip_columns(r.env.config.sensor)
    take = lambda x: jnp.moveaxis(x[:, cam, :, col], 0, 2)  # (W, B, H, ...) -> (B, H, W, ...)
    rgb = take(views["rgb"]).astype(jnp.float32) / 255.0
    rgbd = jnp.concatenate([rgb, take(views["depth_m"])[..., None]], axis=-1)
    return rgbd, None if views["geom_ids"] is None else take(views["geom_ids"])


def render_panorama(r: MjwarpRenderer, episodes: jax.Array, robot_poses: jax.Array, t: jax.Array):
    """`render_views` in the panorama layout: (rgbd (B, H, W, 4), geom ids (B, H, W) or None)."""
    return views_to_panorama(r, render_views(r, episodes, robot_poses, t))


def compare_with_caster(r: MjwarpRenderer, episodes: jax.Array, robot_poses: jax.Array, t: jax.Array) -> dict:
    """Per-pixel agreement of MuJoCo Warp's render (`r` made with segmentation) and the env's
    own sensor (ConavEnv.render_at) on the same worlds: on every pixel for the "panorama" layout
    (identical rays), on the nearest pinhole pixel of each panorama ray inside the cameras'
    images for "pinhole" (a resampling: depth differs by the rays' angle, ids at edges)."""
    if not r.segmentation:
        raise ValueError("compare_with_caster needs a renderer made with segmentation=True")
    cfg = r.env.config.sensor
    views = jax.jit(lambda e, p, s: render_views(r, e, p, s))(episodes, robot_poses, t)
    ours, our_ids = jax.jit(jax.vmap(r.env.render_at))(episodes, robot_poses, t)
    ours, our_ids = np.asarray(ours), np.asarray(our_ids)
    depth, ids, rgb = (np.asarray(views[k]) for k in ("depth_m", "geom_ids", "rgb"))
    if r.rays == "panorama":
        cam, col = camera_strip_columns(cfg)
        take = lambda x: np.moveaxis(x[:, cam, :, col], 0, 2)
        inside = np.ones(cfg.resolution, bool)
        method = "identical rays: every pixel"
    else:
        cam, row, col, inside = pinhole_pixels_of_panorama(cfg)
        take = lambda x: x[:, cam, row, col]
        method = "nearest pinhole pixel of each panorama ray inside the cameras' images"
    sel = np.broadcast_to(inside, our_ids.shape)
    diff = np.abs(take(depth) - ours[..., 3])[sel]
    same = (take(ids) == our_ids)[sel]
    rgb_diff = np.abs(take(rgb).astype(np.float32) / 255.0 - ours[..., :3])[sel]
    return {
        "rays": r.rays,
        "method": method,
        "worlds": int(episodes.shape[0]),
        "pixels_compared": int(diff.size),
        "share_of_panorama_compared": round(float(inside.mean()), 4),
        "depth_abs_diff_max_m": float(diff.max()),
        "depth_abs_diff_median_m": float(np.median(diff)),
        "depth_within_1cm": float((diff <= 0.01).mean()),
        "geom_id_agreement": float(same.mean()),
        "depth_abs_diff_max_same_id_m": float(diff[same].max()) if same.any() else None,
        "rgb_abs_diff_max_same_id": float(rgb_diff[same].max()) if same.any() else None,
    }
