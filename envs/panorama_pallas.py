"""The fast caster as one Pallas (Triton) GPU kernel: SensorConfig(kind="pallas").

A caster like `envs.panorama.fast_depth_ids` (same arguments, a SceneGeometry, and results) with
the same math: the row terms and the capsules' column terms come from the same functions,
computed in XLA; the boxes' column terms (`footprint_terms`, from a few scalars per box) and the
per-pixel key functions (`box_pixel_keys`, `capsule_pixel_keys`, packing with `pack_depth_id`)
are called inside the kernel, so keys agree with it bit for bit. The kernel
runs over a grid (env, column block): a program holds the running min key of its
(H_pad, block_w) pixels in registers and loops over boxes and capsules; nothing of size
geoms x H x W ever reaches memory. A geom that no column of the block can see is skipped
with a branch (a uniform `lax.cond` per program): boxes whose 2-D footprint all the block's
columns miss, and capsules outside the block's azimuth range, which in most blocks is every
capsule of the humanoid.

Triton constraints respected: every block dimension is a power of two (H padded to the next
power of two, W to a multiple of block_w, geoms to a power of two); per-geom rows are read with
a scalar index (`ref[g, :]`), no gathers. `pallas_interpret=True` runs the kernel through the
Pallas interpreter on any backend (the CPU tests); vmap over envs adds a grid axis.
Data flow: per-env terms (XLA, tiny) -> kernel -> keys (H_pad, W_pad) -> crop, unpack (XLA).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl

from conav_jax.parallel import lanes_on_devices
from conav_jax.envs.config import SensorConfig
from conav_jax.envs.panorama import (
    NO_HIT_KEY,
    SceneGeometry,
    box_pixel_keys,
    box_row_terms,
    capsule_pixel_keys,
    capsule_terms,
    column_directions,
    elevation_terms,
    floor_row_keys,
    footprint_terms,
    ray_angles,
    shade_pixels,
    unpack_depth_id,
)

# Order of the per-capsule scalars in the kernel's (C_pad, 8) table.
_CAP_SCALARS = ("ba_z", "oa_z", "baba", "baoa", "c", "cc0", "cc1")
# Slack (radians) on the capsule azimuth test: only makes culling more conservative.
_AZ_SLACK = 1e-3


def _pow2(n: int) -> int:
    return 1 << max(0, int(n - 1).bit_length())


def _pad(x, shape, value):
    return jnp.pad(x, [(0, s - d) for s, d in zip(shape, x.shape)], constant_values=value)


def capsule_column_mask(cfg: SensorConfig, cam_xyz_m, yaw_rad, geometry: SceneGeometry) -> jax.Array:
    """(C, W) float, 1 where column w's rays may hit capsule c (conservative): the column's
    azimuth lies within the angle that the capsule's bounding circle in the ground plane
    subtends from the camera, or the camera is inside that circle."""
    cap_p0, cap_p1 = geometry.capsule_p0_m, geometry.capsule_p1_m
    az, _ = ray_angles(cfg)
    a = yaw_rad + jnp.asarray(az)  # (W,)
    mid = (cap_p0[:, :2] + cap_p1[:, :2]) / 2.0
    radius = jnp.linalg.norm(cap_p1[:, :2] - cap_p0[:, :2], axis=-1) / 2.0 + geometry.capsule_radius_m
    rel = mid - cam_xyz_m[None, :2]
    dist = jnp.linalg.norm(rel, axis=-1)
    inside = dist <= radius * 1.001 + 1e-4
    half = jnp.arcsin(jnp.clip(radius / jnp.maximum(dist, 1e-9), 0.0, 1.0)) + _AZ_SLACK
    phi = jnp.arctan2(rel[:, 1], rel[:, 0])
    x = a[None, :] - phi[:, None]
    diff = jnp.abs(jnp.arctan2(jnp.sin(x), jnp.cos(x)))  # wrapped to [0, pi]
    return (inside[:, None] | (diff <= half[:, None])).astype(jnp.float32)


def _how_to_run(cfg: SensorConfig):
    """(interpret, compiler_params) of a pallas_call: Triton needs a GPU, so elsewhere (the CPU
    tests and benches) the kernel is interpreted."""
    interpret = cfg.pallas_interpret or jax.default_backend() not in ("gpu", "cuda", "rocm")
    if interpret:
        return True, None
    from jax.experimental.pallas import triton as plgpu

    return False, plgpu.CompilerParams(num_warps=cfg.pallas_num_warps, num_stages=1)


def _kernel(n_box: int, n_cap: int, max_depth_m: float,
            floor_ref, inv_cos_ref, ce_ref, se_ref,
            inv_x_ref, inv_y_ref, bscal_ref, row_in_ref, row_out_ref, box_id_ref,
            u_ref, v_ref, cmask_ref, cscal_ref, cap_id_ref,
            out_ref):
    hp, bw = out_ref.shape
    keys = jnp.broadcast_to(floor_ref[...][:, None], (hp, bw))
    inv_cos = inv_cos_ref[...][:, None]
    inv_x, inv_y = inv_x_ref[...], inv_y_ref[...]

    def box(g, keys):
        # The footprint's column terms for this block's columns, from the box's scalars.
        ci, co = footprint_terms(*(bscal_ref[g, i] for i in range(4)), bscal_ref[g, 4] > 0.5, inv_x, inv_y)

        def hit(keys):
            k = box_pixel_keys(ci[None, :], co[None, :], row_in_ref[g, :][:, None],
                               row_out_ref[g, :][:, None], inv_cos, box_id_ref[g], max_depth_m)
            return jnp.minimum(keys, k)

        # Every column of the block misses the footprint: nothing to do (col_in is inf there).
        return jax.lax.cond(jnp.min(ci) < jnp.inf, hit, lambda k: k, keys)

    keys = jax.lax.fori_loop(0, n_box, box, keys)
    if n_cap:
        ce, se = ce_ref[...][:, None], se_ref[...][:, None]

        def cap(c, keys):
            def hit(keys):
                s = {name: cscal_ref[c, i] for i, name in enumerate(_CAP_SCALARS)}
                k = capsule_pixel_keys(u_ref[c, :][None, :], v_ref[c, :][None, :], ce, se, s,
                                       cap_id_ref[c], max_depth_m)
                return jnp.minimum(keys, k)

            return jax.lax.cond(jnp.max(cmask_ref[c, :]) > 0.0, hit, lambda k: k, keys)

        keys = jax.lax.fori_loop(0, n_cap, cap, keys)
    out_ref[...] = keys


def pallas_depth_ids(
    cfg: SensorConfig, cam_xyz_m: jax.Array, yaw_rad: jax.Array, geometry: SceneGeometry
) -> tuple[jax.Array, jax.Array]:
    """`envs.panorama.fast_depth_ids` (same arguments and results) as a Pallas kernel: depth
    (H, W) metres and geom ids (H, W) for one camera at `cam_xyz_m` facing `yaw_rad`. Batched
    inside a program partitioned over a mesh, each device casts its own lanes
    (conav_jax.parallel.lanes_on_devices)."""
    return lanes_on_devices(functools.partial(_depth_ids, cfg))(cam_xyz_m, yaw_rad, geometry)


def _depth_ids(cfg: SensorConfig, cam_xyz_m: jax.Array, yaw_rad: jax.Array, geometry: SceneGeometry):
    h, w, bw = cfg.height, cfg.width, cfg.pallas_block_w
    hp, wp = _pow2(h), -(-w // bw) * bw
    n_box, n_cap = int(geometry.box_lo_m.shape[0]), int(geometry.capsule_p0_m.shape[0])
    gp, cp = _pow2(max(n_box, 1)), _pow2(max(n_cap, 1))
    maxd = float(cfg.max_depth_m)
    inf = jnp.inf
    no_hit = np.uint32(NO_HIT_KEY)

    inv_cos, ce, se = elevation_terms(cfg)
    inv_x, inv_y = column_directions(cfg, yaw_rad)
    row_in, row_out = box_row_terms(cfg, cam_xyz_m, geometry)
    # Per box: its footprint relative to the camera and whether it is real, (G, 8); the kernel
    # makes the (G, W) column terms itself, so they never reach memory.
    lo, hi = geometry.box_lo_m - cam_xyz_m, geometry.box_hi_m - cam_xyz_m
    bscal = jnp.stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1], geometry.box_valid.astype(jnp.float32)], axis=-1)
    # Padding rows / columns / geoms never hit (their results are cropped anyway): a NaN
    # column direction misses every footprint.
    rows = lambda x, v: _pad(x, (hp,), v)
    args = [
        _pad(floor_row_keys(cfg, cam_xyz_m, geometry.floor_id), (hp,), no_hit),
        rows(inv_cos, 1.0), rows(ce, 1.0), rows(se, 0.0),
        _pad(inv_x, (wp,), jnp.nan), _pad(inv_y, (wp,), jnp.nan), _pad(bscal, (gp, 8), 0.0),
        _pad(row_in, (gp, hp), inf), _pad(row_out, (gp, hp), -inf),
        _pad(geometry.box_ids.astype(jnp.uint32), (gp,), no_hit),
    ]
    if n_cap:
        u, v, s = capsule_terms(cfg, cam_xyz_m, yaw_rad, geometry)
        mask = capsule_column_mask(cfg, cam_xyz_m, yaw_rad, geometry)
        table = jnp.stack([s[k] for k in _CAP_SCALARS] + [jnp.zeros_like(s["c"])], axis=-1)  # (C, 8)
        args += [_pad(u, (cp, wp), 0.0), _pad(v, (cp, wp), 0.0), _pad(mask, (cp, wp), 0.0),
                 _pad(table, (cp, 8), 0.0), _pad(geometry.capsule_ids.astype(jnp.uint32), (cp,), no_hit)]
    else:
        args += [jnp.zeros((cp, wp)), jnp.zeros((cp, wp)), jnp.zeros((cp, wp)), jnp.zeros((cp, 8)),
                 jnp.full((cp,), NO_HIT_KEY, jnp.uint32)]

    whole = lambda x: pl.BlockSpec(x.shape, lambda j: (0,) * x.ndim)
    cols = lambda x: pl.BlockSpec((x.shape[0], bw), lambda j: (0, j))
    block = pl.BlockSpec((bw,), lambda j: (j,))
    in_specs = [whole(a) for a in args[:4]] + [block, block, whole(args[6]), whole(args[7]), whole(args[8]),
                                                  whole(args[9]), cols(args[10]), cols(args[11]), cols(args[12]),
                                                  whole(args[13]), whole(args[14])]
    interpret, compiler_params = _how_to_run(cfg)
    keys = pl.pallas_call(
        functools.partial(_kernel, n_box, n_cap, maxd),
        out_shape=jax.ShapeDtypeStruct((hp, wp), jnp.uint32),
        grid=(wp // bw,),
        in_specs=in_specs,
        out_specs=pl.BlockSpec((hp, bw), lambda j: (0, j)),
        interpret=interpret,
        compiler_params=compiler_params,
        name="panorama_caster",
    )(*args)
    return unpack_depth_id(keys[:h, :w], maxd)


# -- shading (SensorConfig.materials "instance") ------------------------------------------------
# Pixels per shading program: rows x columns, each the largest power of two dividing the image's
# size up to these caps, so blocks tile the image exactly (no padding pass in XLA). Short, wide
# blocks ran fastest of those timed (BENCHMARKS.md).
SHADE_BLOCK_ROWS, SHADE_BLOCK_COLS = 2, 64


def _pow2_divisor(n: int, cap: int) -> int:
    """The largest power of two dividing `n`, at most `cap`."""
    p = 1
    while p * 2 <= cap and n % (p * 2) == 0:
        p *= 2
    return p


def _shade_kernel(cfg: SensorConfig, cam_ref, ce_ref, se_ref, ca_ref, sa_ref, table_ref, depth_ref, ids_ref,
                  out_ref):
    depth, ids = depth_ref[...], ids_ref[...]
    ce, se = ce_ref[...][:, None], se_ref[...][:, None]
    dirs = (ce * ca_ref[...][None, :], ce * sa_ref[...][None, :], se)
    n_geoms = table_ref.shape[0]
    safe = jnp.clip(ids, 0, n_geoms - 1)
    rgb = shade_pixels(cfg, [cam_ref[k] for k in range(3)], dirs, depth, ids, lambda k: table_ref[safe, k])
    for c in range(3):
        out_ref[:, :, c] = rgb[c]
    out_ref[:, :, 3] = depth


def pallas_shade(cfg: SensorConfig, cam_xyz_m: jax.Array, yaw_rad: jax.Array, depth: jax.Array, ids: jax.Array,
                 table: jax.Array) -> jax.Array:
    """`envs.panorama.shade` as a Pallas kernel: RGB-D (H, W, 4) of a cast (depth (H, W) m, geom
    ids (H, W)) from a camera at `cam_xyz_m` facing `yaw_rad`, coloured from the shading table
    `table` (n_geoms, SHADING_WIDTH; envs.panorama.shading_table). Each program colours one
    block of pixels, loading its geoms' rows from the table (a gather the kernel keeps in
    registers), with `shade_pixels`, the XLA colouring's own per-pixel function. Batched inside
    a program partitioned over a mesh, each device colours its own lanes."""
    return lanes_on_devices(functools.partial(_shade, cfg))(cam_xyz_m, yaw_rad, depth, ids, table)


def _shade(cfg: SensorConfig, cam_xyz_m: jax.Array, yaw_rad: jax.Array, depth: jax.Array, ids: jax.Array,
           table: jax.Array) -> jax.Array:
    h, w = depth.shape
    rb, cb = _pow2_divisor(h, SHADE_BLOCK_ROWS), _pow2_divisor(w, SHADE_BLOCK_COLS)
    az, el = ray_angles(cfg)
    a = yaw_rad + jnp.asarray(az)
    e = jnp.asarray(el)
    # Whole-array blocks need power-of-two sizes: the table padded with zero rows and columns
    # (a hit's id is always a real geom's; the sky's -1 is clipped to row 0, as in XLA).
    n_geoms, width = table.shape
    table = _pad(table, (_pow2(n_geoms), _pow2(width)), 0.0)
    cam = _pad(jnp.asarray(cam_xyz_m, jnp.float32), (4,), 0.0)
    args = [cam, jnp.cos(e), jnp.sin(e), jnp.cos(a), jnp.sin(a), table, depth, ids.astype(jnp.int32)]
    whole = lambda x: pl.BlockSpec(x.shape, lambda i, j: (0,) * x.ndim)
    rows = pl.BlockSpec((rb,), lambda i, j: (i,))
    cols = pl.BlockSpec((cb,), lambda i, j: (j,))
    pixels = pl.BlockSpec((rb, cb), lambda i, j: (i, j))
    interpret, compiler_params = _how_to_run(cfg)
    return pl.pallas_call(
        functools.partial(_shade_kernel, cfg),
        out_shape=jax.ShapeDtypeStruct((h, w, 4), jnp.float32),
        grid=(h // rb, w // cb),
        in_specs=[whole(cam), rows, rows, cols, cols, whole(table), pixels, pixels],
        out_specs=pl.BlockSpec((rb, cb, 4), lambda i, j: (i, j, 0)),
        interpret=interpret,
        compiler_params=compiler_params,
        name="panorama_shade",
    )(*args)
