"""Panoramic RGB-D sensors: a fast caster of our own and the `mujoco.mjx.ray` reference.

Both cast the same rays (SensorConfig's equirectangular layout) and return depth (metres along
the ray, max_depth where nothing is hit) and the MJX geom id hit (-1 for none), from which RGB
is computed after the cast, the same for every caster: `shade` (instance materials with
procedural patterns, Lambertian-shaded by the surface normal) or `colourise` (flat colours per
geom). The fast caster uses the scene's structure: every box is axis-aligned, so
per image column the ray is a 2-D ray and each box a 2-D slab interval; per row the box's z
range turns into a second interval along the same horizontal distance; their intersection
gives the exact hit. The floor is analytic per row; capsules (the humanoid) are tested per ray.
The nearest hit and its id are found together by a min over keys that pack both
(`pack_depth_id` / `unpack_depth_id`).

Every caster is `caster(cfg, cam_xyz_m, yaw_rad, geometry) -> (depth (H, W) m, geom ids (H, W))`
over a `SceneGeometry`, and `caster_for(kind)` picks it: `fast_depth_ids` (kind "fast") computes
the per-geom terms once per column (G, W) and per row (G, H) and writes the per-pixel test as
one expression whose min over geoms XLA fuses, so only (H, W) arrays reach memory;
`envs.panorama_pallas.pallas_depth_ids` (kind "pallas") runs the same per-pixel functions in a
Triton kernel that also skips geoms a block of columns cannot see. `reference_depth_ids` (kind
"reference") casts through mjx.ray, so it takes the MJX model and data instead.
Data flow: robot pose + SceneGeometry (scene boxes, human capsules, floor) -> keys (H, W)
-> (depth, geom id) -> + materials, normals -> rgbd.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from conav_jax.data.materials import MATERIAL_WIDTH
from conav_jax.envs.config import SensorConfig, resolve_sensor_kind
from conav_jax.envs.mjcf import RAY_GEOMGROUP

_EPS = 1e-9
SKY_RGB = np.array([0.62, 0.72, 0.85], np.float32)


class SceneGeometry(NamedTuple):
    """What a caster sees of one scene at one moment: G axis-aligned boxes, C capsules and the
    floor plane z = 0, with their MJX geom ids (below 256: they share a key with the depth). A
    pytree, so it batches under vmap."""

    box_lo_m: jax.Array  # (G, 3) lower corners of the boxes (walls, furniture)
    box_hi_m: jax.Array  # (G, 3) upper corners
    box_ids: jax.Array  # (G,) int geom ids
    box_valid: jax.Array  # (G,) bool; False for padding slots (scenes have fewer boxes than G)
    capsule_p0_m: jax.Array  # (C, 3) one end of each capsule's segment (the humanoid's limbs)
    capsule_p1_m: jax.Array  # (C, 3) the other end
    capsule_radius_m: jax.Array  # (C,)
    capsule_ids: jax.Array  # (C,) int geom ids
    floor_id: int | jax.Array  # geom id of the floor plane


# (cfg, camera position (3,) m, robot yaw rad, geometry) -> (depth (H, W) m, geom ids (H, W)).
Caster = Callable[[SensorConfig, jax.Array, jax.Array, SceneGeometry], tuple[jax.Array, jax.Array]]


# -- keys: depth and geom id in one uint32 ------------------------------------------------------
# Quantised depth in the upper 24 bits, geom id in the lower 8: a min over keys gives the nearest
# hit and its id in one simple reduction, which XLA fuses with the intersection math and the
# Pallas kernel keeps in registers.
_ID_BITS = 8
_DEPTH_BITS = 24
NO_HIT_KEY = 0xFFFFFFFF  # above every hit's key (their depth quantum is below 2**24 - 2)


def _depth_quanta_per_m(max_depth_m: float) -> float:
    """Depths [0, max_depth_m] span quanta [0, 2**24 - 2]: 0.6 micrometres each at 10 m."""
    return float((1 << _DEPTH_BITS) - 2) / max_depth_m


def pack_depth_id(depth_m: jax.Array, geom_id: jax.Array, max_depth_m: float) -> jax.Array:
    """uint32 keys of hits at `depth_m` (>= 0; inf for no hit) on geoms `geom_id` (integers below
    256), broadcast together. Keys order as the depth quanta do, ties by id, so the min over geoms
    of the keys is the nearest hit. A depth whose quantum reaches max_depth_m's is a miss,
    NO_HIT_KEY: for float32 depths that is exactly `depth_m >= max_depth_m`, tested on the
    quantum so that `depth_m` is used once and XLA fuses its producer (divides, square roots)
    into the min instead of writing it out."""
    scale = _depth_quanta_per_m(max_depth_m)
    q = jnp.floor(jnp.minimum(depth_m, max_depth_m) * scale).astype(jnp.uint32)
    q_max = np.uint32(np.floor(np.float32(max_depth_m) * np.float32(scale)))
    ids = jnp.asarray(geom_id).astype(jnp.uint32)
    return jnp.where(q >= q_max, jnp.uint32(NO_HIT_KEY), (q << _ID_BITS) | ids)


def unpack_depth_id(key: jax.Array, max_depth_m: float) -> tuple[jax.Array, jax.Array]:
    """(depth m float32, geom id int32) of keys from `pack_depth_id`; (max_depth_m, -1) for
    NO_HIT_KEY. The depth is the centre of its quantum: within half a quantum (0.3 micrometres
    at 10 m) of the depth packed."""
    miss = key == jnp.uint32(NO_HIT_KEY)
    ids = (key & jnp.uint32((1 << _ID_BITS) - 1)).astype(jnp.int32)
    depth = ((key >> _ID_BITS).astype(jnp.float32) + 0.5) / _depth_quanta_per_m(max_depth_m)
    return jnp.where(miss, max_depth_m, depth), jnp.where(miss, -1, ids)


def ray_angles(cfg: SensorConfig) -> tuple[np.ndarray, np.ndarray]:
    """(azimuth offsets from the robot's yaw (W,), elevations (H,)) in radians."""
    j = np.arange(cfg.width, dtype=np.float64)
    azimuth = np.pi - 2.0 * np.pi * (j + 0.5) / cfg.width
    vfov = 2.0 * np.pi * cfg.height / cfg.width
    i = np.arange(cfg.height, dtype=np.float64)
    elevation = vfov / 2.0 - vfov * (i + 0.5) / cfg.height
    return azimuth.astype(np.float32), elevation.astype(np.float32)


def ray_directions(cfg: SensorConfig, yaw: jax.Array) -> jax.Array:
    """Unit ray directions (H, W, 3) in the world frame for a robot facing `yaw`."""
    az, el = ray_angles(cfg)
    a = yaw + jnp.asarray(az)
    e = jnp.asarray(el)
    ce = jnp.cos(e)[:, None]
    return jnp.stack(
        [ce * jnp.cos(a)[None, :], ce * jnp.sin(a)[None, :], jnp.broadcast_to(jnp.sin(e)[:, None], cfg.resolution)],
        axis=-1,
    )


# -- the fused caster (kind "fast") -------------------------------------------------------------
# Per-geom work is split into terms per (geom, column) and per (geom, row), computed once; per
# pixel only a few max/min/compare ops remain, in a running min over geoms that XLA fuses into
# one loop (the capsules, then the boxes in two passes of a lax.scan), so no (geoms, H, W)
# array is ever written to memory: only the (H, W) keys, three times. The same terms and
# per-pixel functions feed the Pallas kernel (envs/panorama_pallas.py).


def _split(arrays: tuple, p: int) -> tuple:
    """Arrays with a leading geom axis G -> (ceil(G / p), p, ...), padded with copies of geom 0
    (harmless: a duplicate cannot change a min)."""
    g = arrays[0].shape[0]
    n = -(-g // p)
    pad = n * p - g
    return tuple(jnp.concatenate([a, jnp.broadcast_to(a[:1], (pad,) + a.shape[1:])]).reshape((n, p) + a.shape[1:])
                 for a in arrays)


def column_directions(cfg: SensorConfig, yaw_rad) -> tuple[jax.Array, jax.Array]:
    """(1 / dx, 1 / dy) per column (W,) of the columns' horizontal ray directions (dx, dy), each
    kept at least _EPS from zero."""
    az, _ = ray_angles(cfg)
    a = yaw_rad + jnp.asarray(az)  # (W,)
    safe = lambda v: jnp.where(jnp.abs(v) < _EPS, jnp.where(v < 0, -_EPS, _EPS), v)
    return 1.0 / safe(jnp.cos(a)), 1.0 / safe(jnp.sin(a))


def footprint_terms(rel_lo_x, rel_hi_x, rel_lo_y, rel_hi_y, valid, inv_x, inv_y):
    """(col_in, col_out) for broadcastable box footprints relative to the camera (lo/hi x and y,
    metres), whether each box is real (`valid`), and column inverse directions (`inv_x`,
    `inv_y`, column_directions): the horizontal distance where the column's 2-D ray enters the
    footprint (at least 0; +inf where it misses it or the box is padding) and where it leaves.
    The XLA and the Pallas casters both call it, so their keys agree bit for bit."""
    tx1, tx2 = rel_lo_x * inv_x, rel_hi_x * inv_x
    ty1, ty2 = rel_lo_y * inv_y, rel_hi_y * inv_y
    t_in = jnp.maximum(jnp.maximum(jnp.minimum(tx1, tx2), jnp.minimum(ty1, ty2)), 0.0)
    t_out = jnp.minimum(jnp.maximum(tx1, tx2), jnp.maximum(ty1, ty2))
    # A column that misses the footprint can never hit (enter >= t_in > t_out >= leave): the
    # same outcome as the per-pixel test, decided once per column.
    return jnp.where(valid & (t_in <= t_out), t_in, jnp.inf), t_out


def box_row_terms(cfg: SensorConfig, cam_xyz_m, geometry: SceneGeometry) -> tuple[jax.Array, jax.Array]:
    """(row_in, row_out) per box and row (G, H): the horizontal distance interval over which the
    row's ray is inside the box's z range, metres."""
    _, el = ray_angles(cfg)
    tan_e = jnp.tan(jnp.asarray(el))
    tan_e = jnp.where(jnp.abs(tan_e) < _EPS, _EPS, tan_e)
    tz1 = (geometry.box_lo_m[:, None, 2] - cam_xyz_m[2]) / tan_e[None]
    tz2 = (geometry.box_hi_m[:, None, 2] - cam_xyz_m[2]) / tan_e[None]
    return jnp.minimum(tz1, tz2), jnp.maximum(tz1, tz2)


def box_terms(cfg: SensorConfig, cam_xyz_m, yaw_rad, geometry: SceneGeometry):
    """Per box of `geometry`: column terms (G, W) `col_in`, `col_out` (footprint_terms) and row
    terms (G, H) `row_in`, `row_out` (box_row_terms). Metres."""
    cam, box_lo, box_hi = cam_xyz_m, geometry.box_lo_m, geometry.box_hi_m
    inv_x, inv_y = column_directions(cfg, yaw_rad)
    col_in, col_out = footprint_terms(box_lo[:, None, 0] - cam[0], box_hi[:, None, 0] - cam[0],
                                      box_lo[:, None, 1] - cam[1], box_hi[:, None, 1] - cam[1],
                                      geometry.box_valid[:, None], inv_x[None], inv_y[None])
    return (col_in, col_out, *box_row_terms(cfg, cam, geometry))


def box_pixel_keys(col_in, col_out, row_in, row_out, inv_cos, ids, max_depth_m: float):
    """Packed keys for broadcastable column terms, row terms, 1/cos(elevation) and ids (uint32):
    the box is hit where the column's and the row's intervals overlap, at the entry's distance
    along the ray."""
    enter = jnp.maximum(col_in, row_in)
    leave = jnp.minimum(col_out, row_out)
    return pack_depth_id(jnp.where(enter <= leave, enter * inv_cos, jnp.inf), ids, max_depth_m)


def capsule_terms(cfg: SensorConfig, cam_xyz_m, yaw_rad, geometry: SceneGeometry):
    """Per capsule of `geometry`: column terms (C, W) `u` = d_xy . (p1 - p0)_xy and
    `v` = d_xy . (cam - p0)_xy for the column's horizontal unit direction d_xy, and scalars (C,)
    for the closed form.
    A ray's direction is (cos e d_xy, sin e), so per pixel dir . x = cos e * (col term) + sin e * x_z."""
    cap_p0 = geometry.capsule_p0_m
    az, _ = ray_angles(cfg)
    a = yaw_rad + jnp.asarray(az)
    ca, sa = jnp.cos(a), jnp.sin(a)
    ba = geometry.capsule_p1_m - cap_p0
    oa = cam_xyz_m[None, :] - cap_p0
    u = ca[None] * ba[:, 0:1] + sa[None] * ba[:, 1:2]
    v = ca[None] * oa[:, 0:1] + sa[None] * oa[:, 1:2]
    dot = lambda x, y: jnp.sum(x * y, axis=-1)
    baba, baoa, oaoa = dot(ba, ba), dot(ba, oa), dot(oa, oa)
    r2 = geometry.capsule_radius_m * geometry.capsule_radius_m
    ob = oa - ba
    scal = {
        "ba_z": ba[:, 2],
        "oa_z": oa[:, 2],
        "baba": baba,
        "baoa": baoa,
        "c": baba * oaoa - baoa * baoa - r2 * baba,
        "cc0": oaoa - r2,  # end-cap sphere at p0: |cam - p0|^2 - r^2
        "cc1": dot(ob, ob) - r2,  # at p1
    }
    return u, v, scal


def capsule_pixel_keys(u, v, ce, se, s, ids, max_depth_m: float):
    """Packed keys of the capsule hit for broadcastable column terms u, v, cos/sin of the
    elevation ce, se, per-capsule scalars s (dict) and ids (uint32). The ray against the infinite
    cylinder, accepted between the end caps, else against the nearer end-cap sphere."""
    bard = ce * u + se * s["ba_z"]
    rdoa = ce * v + se * s["oa_z"]
    baba, baoa = s["baba"], s["baoa"]
    a = baba - bard * bard
    b = baba * rdoa - baoa * bard
    h = b * b - a * s["c"]
    small = jnp.abs(a) < _EPS
    a_s = jnp.where(small, _EPS, a)
    # t_body = n / a_s; the tests on it and on y = baoa + t_body * bard are made on n and
    # y * |a_s| so the division is used once (XLA then keeps it inside the fused min).
    n = -b - jnp.sqrt(jnp.maximum(h, 0.0))
    sgn = jnp.where(a_s < 0, -1.0, 1.0)
    ya = (baoa * a_s + n * bard) * sgn  # y * |a_s|
    body_ok = (h >= 0) & ~small & (ya > 0) & (ya < baba * (a_s * sgn)) & (n * sgn > 0)
    first = ya <= 0
    bc = jnp.where(first, rdoa, rdoa - bard)  # dir . (cam - cap centre)
    hc = bc * bc - jnp.where(first, s["cc0"], s["cc1"])
    t_cap = -bc - jnp.sqrt(jnp.maximum(hc, 0.0))
    cap_ok = (hc >= 0) & (t_cap > 0)
    depth = jnp.where(body_ok, n / a_s, jnp.where(cap_ok, t_cap, jnp.inf))
    return pack_depth_id(depth, ids, max_depth_m)


def floor_row_keys(cfg: SensorConfig, cam_xyz_m, floor_id) -> jax.Array:
    """(H,) keys of the floor plane z = 0 per row (no hit above the horizon)."""
    _, el = ray_angles(cfg)
    sin_e = jnp.asarray(np.sin(el))
    depth = jnp.where(sin_e < -_EPS, -cam_xyz_m[2] / jnp.where(sin_e < -_EPS, sin_e, -1.0), jnp.inf)
    return pack_depth_id(depth, jnp.full(depth.shape, floor_id, jnp.int32), cfg.max_depth_m)


def elevation_terms(cfg: SensorConfig):
    """(1/cos e, cos e, sin e) per row (H,) for the rows' elevations e."""
    _, el = ray_angles(cfg)
    e = jnp.asarray(el)
    return 1.0 / jnp.cos(e), jnp.cos(e), jnp.sin(e)


def fast_depth_ids(
    cfg: SensorConfig, cam_xyz_m: jax.Array, yaw_rad: jax.Array, geometry: SceneGeometry
) -> tuple[jax.Array, jax.Array]:
    """Depth (H, W) metres and geom ids (H, W) for one camera at `cam_xyz_m` (3,) facing
    `yaw_rad`, seeing `geometry`.

    A running min over geoms of expressions built from (1, W) column terms and (H, 1) row
    terms (cfg.fast_min "unroll"), or min-reductions over (G, H, W) expressions ("reduce");
    see the section comment above."""
    maxd = float(cfg.max_depth_m)
    inv_cos, ce, se = elevation_terms(cfg)
    keys = jnp.broadcast_to(floor_row_keys(cfg, cam_xyz_m, geometry.floor_id)[:, None], cfg.resolution)
    col_in, col_out, row_in, row_out = box_terms(cfg, cam_xyz_m, yaw_rad, geometry)
    box_ids = geometry.box_ids.astype(jnp.uint32)
    n_cap = geometry.capsule_p0_m.shape[0]
    if n_cap:
        u, v, s = capsule_terms(cfg, cam_xyz_m, yaw_rad, geometry)
        cap_ids = geometry.capsule_ids.astype(jnp.uint32)
        if cfg.fast_min == "reduce":
            ckeys = capsule_pixel_keys(
                u[:, None, :], v[:, None, :], ce[None, :, None], se[None, :, None],
                {k: x[:, None, None] for k, x in s.items()}, cap_ids[:, None, None], maxd,
            )
            keys = jnp.minimum(keys, jnp.min(ckeys, axis=0))
        else:  # "unroll": a running min, one elementwise chain per geom
            for c in range(n_cap):
                keys = jnp.minimum(keys, capsule_pixel_keys(
                    u[c][None, :], v[c][None, :], ce[:, None], se[:, None],
                    {n: x[c] for n, x in s.items()}, cap_ids[c], maxd,
                ))
    box_terms_ = (col_in, col_out, row_in, row_out, box_ids)
    if cfg.fast_min == "reduce":
        def one_pass(keys, group):
            ci, co, ri, ro, ids = group
            k = box_pixel_keys(ci[:, None, :], co[:, None, :], ri[:, :, None], ro[:, :, None],
                               inv_cos[None, :, None], ids[:, None, None], maxd)
            return jnp.minimum(keys, jnp.min(k, axis=0)), None
    else:
        def one_pass(keys, group):
            for ci, co, ri, ro, ids in zip(*group):
                keys = jnp.minimum(keys, box_pixel_keys(ci[None, :], co[None, :], ri[:, None], ro[:, None],
                                                        inv_cos[:, None], ids, maxd))
            return keys, None
    # Boxes in two passes of a lax.scan: its carry is a fusion boundary, so the keys are written
    # once (4 bytes a pixel) and depth, ids and colours read them. A caster ending in plain
    # elementwise ops lets XLA fuse it whole into each consumer (depth, the colour gather, each
    # rgbd channel, the front view) and cast the panorama several times over (seen on the CPU).
    keys, _ = jax.lax.scan(one_pass, keys, _split(box_terms_, max(1, -(-geometry.box_lo_m.shape[0] // 2))))
    return unpack_depth_id(keys, maxd)


def caster_for(kind: str) -> Caster:
    """The SceneGeometry caster of a SensorConfig.kind ("auto" resolved for this machine).
    "reference" has none: mjx.ray needs the MJX model and data, see `reference_depth_ids`."""
    kind = resolve_sensor_kind(kind)
    if kind == "fast":
        return fast_depth_ids
    if kind == "pallas":
        # Imported on first use: the kernel's module imports this one, and Pallas loads only
        # for those who cast with it.
        from conav_jax.envs.panorama_pallas import pallas_depth_ids

        return pallas_depth_ids
    raise ValueError(f"no SceneGeometry caster for sensor kind {kind!r} (reference_depth_ids casts through mjx.ray)")


def reference_depth_ids(
    cfg: SensorConfig, m: mjx.Model, d: mjx.Data, cam_xyz_m: jax.Array, yaw_rad: jax.Array, exclude_body: int
) -> tuple[jax.Array, jax.Array]:
    """The same panorama from `mujoco.mjx.ray`, one ray per pixel (slow; the ground truth), in the
    MJX model `m` with data `d` (its positions; kinematics runs here), not seeing body
    `exclude_body` (the robot). Kinematics and rays run their matrix products at full float32
    precision (GPUs default to TF32, ~1e-3 relative: millimetres at a few metres)."""
    dirs = ray_directions(cfg, yaw_rad).reshape(-1, 3)
    with jax.default_matmul_precision("highest"):
        d = mjx.kinematics(m, d)
        dist, geom = jax.vmap(
            lambda v: mjx.ray(m, d, cam_xyz_m, v, geomgroup=RAY_GEOMGROUP, bodyexclude=exclude_body))(dirs)
    hit = (geom >= 0) & (dist >= 0) & (dist < cfg.max_depth_m)
    depth = jnp.where(hit, dist, cfg.max_depth_m).reshape(cfg.resolution)
    ids = jnp.where(hit, geom, -1).reshape(cfg.resolution)
    return depth, ids


def colourise(depth: jax.Array, ids: jax.Array, geom_rgb: jax.Array) -> jax.Array:
    """RGB-D (H, W, 4): the hit geom's flat colour (sky where nothing is hit) and depth in
    metres (SensorConfig.materials "flat")."""
    rgb = jnp.where((ids >= 0)[..., None], geom_rgb[jnp.maximum(ids, 0)], jnp.asarray(SKY_RGB))
    return jnp.concatenate([rgb, depth[..., None]], axis=-1)


# -- instance materials and shading (SensorConfig.materials "instance") ---------------------------
# The colour of a pixel is computed after the cast from what every caster returns (depth, geom
# id) and the SceneGeometry, so the XLA, Pallas and mjx.ray casters shade alike. Patterns are
# smooth functions of the hit point with a bounded slope (sinusoidal stripes and checks clipped
# to a soft edge, trilinear value noise; periods of decimetres), so two casters whose hits differ
# by micrometres agree to far below one level in 255.

_PATTERN_GAIN = 1.5  # stripes and checks: mix = clip(0.5 + gain * wave): soft edges, bounded slope
_TILT = 0.5  # pattern coordinates lean with height, so vertical faces of any orientation show them


def _hash_unit(i: jax.Array, j: jax.Array, k: jax.Array) -> jax.Array:
    """A value in [0, 1) per integer lattice point (int32 arrays), by a 32-bit integer mix."""
    u = lambda x: x.astype(jnp.uint32)
    h = u(i) * jnp.uint32(0x8DA6B343) ^ u(j) * jnp.uint32(0xD8163841) ^ u(k) * jnp.uint32(0xCB1AB31F)
    h = (h ^ (h >> 16)) * jnp.uint32(0x7FEB352D)
    h = (h ^ (h >> 15)) * jnp.uint32(0x846CA68B)
    h = h ^ (h >> 16)
    return (h >> 8).astype(jnp.float32) / float(1 << 24)


def _value_noise(x: jax.Array, y: jax.Array, z: jax.Array) -> jax.Array:
    """Smooth value noise in [0, 1] at points (x, y, z) in lattice units (arrays of one shape):
    lattice values blended with smoothstep weights (continuous across cells)."""
    cells = [jnp.floor(v) for v in (x, y, z)]
    w = [(v - c) * (v - c) * (3.0 - 2.0 * (v - c)) for v, c in zip((x, y, z), cells)]
    c = [cell.astype(jnp.int32) for cell in cells]
    out = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                weight = ((w[0] if dx else 1 - w[0]) * (w[1] if dy else 1 - w[1]) * (w[2] if dz else 1 - w[2]))
                out = out + weight * _hash_unit(c[0] + dx, c[1] + dy, c[2] + dz)
    return out


def pattern_mix(hit_m, pattern: jax.Array, period_m: jax.Array, angle_rad: jax.Array) -> jax.Array:
    """How much of the second colour (..., ) in [0, 1] a material shows at world points `hit_m`
    ((x, y, z) m, three arrays of one shape, or one array (..., 3)): pattern index
    (conav_jax.data.materials.PATTERNS) 0 plain, 1 stripes, 2 checks, 3 noise, at `period_m`,
    turned by `angle_rad` about z. Written per component, without reductions over a last axis,
    so XLA fuses it with the gathers feeding it into one pass over the pixels."""
    x, y, z = (hit_m[..., 0], hit_m[..., 1], hit_m[..., 2]) if not isinstance(hit_m, tuple) else hit_m
    c, s = jnp.cos(angle_rad), jnp.sin(angle_rad)
    a = (c * x + s * y + _TILT * z) / period_m
    b = (c * y - s * x - _TILT * z) / period_m
    soft = lambda wave: jnp.clip(0.5 + _PATTERN_GAIN * wave, 0.0, 1.0)
    sin_a = jnp.sin(2.0 * np.pi * a)
    stripes = soft(sin_a)
    checks = soft(sin_a * jnp.sin(2.0 * np.pi * b) * 2.0)
    noise = _value_noise(a, b, z / period_m)
    return jnp.where(pattern == 1, stripes, jnp.where(pattern == 2, checks, jnp.where(pattern == 3, noise, 0.0)))


def _geom_table(n_geoms: int, ids: jax.Array, rows: jax.Array, fill: float = 0.0) -> jax.Array:
    """(n_geoms, ...) with `rows` at `ids` and `fill` elsewhere."""
    return jnp.full((n_geoms,) + rows.shape[1:], fill, rows.dtype).at[ids].set(rows)


def _ray_components(cfg: SensorConfig, yaw_rad: jax.Array, elevation_rad: jax.Array):
    """Unit ray directions of the rows at `elevation_rad` (R,) as three arrays broadcastable to
    (R, W): x, y (R, W), z (R, 1)."""
    az, _ = ray_angles(cfg)
    a = yaw_rad + jnp.asarray(az)[None, :]
    ce, se = jnp.cos(elevation_rad)[:, None], jnp.sin(elevation_rad)[:, None]
    return ce * jnp.cos(a), ce * jnp.sin(a), se


# Rows coloured together on an accelerator: the colouring runs over blocks of rows (lax.map), so
# its per-pixel temporaries exist for one block of every env of a batch at a time, whatever XLA
# fuses. The CPU colours whole panoramas: its batches are small, and the loop costs it more than
# the temporaries.
SHADE_BLOCK_ROWS = 16


def _row_block(height: int, backend: str) -> int:
    """Rows coloured together on `backend` (jax.default_backend()): all of them on the CPU, else
    the largest divisor of `height` not above SHADE_BLOCK_ROWS."""
    if backend == "cpu":
        return height
    return max(r for r in range(1, min(height, SHADE_BLOCK_ROWS) + 1) if height % r == 0)


# Columns of the per-geom shading table (`shading_table`): the material row (MATERIAL_WIDTH
# values, conav_jax.data.materials), then what the surface normal needs: the geom's kind
# (SHADE_KIND_*), a box's corners and a capsule's segment. One table, so the XLA colouring and
# the Pallas kernel read a hit geom's row the same way (a gather by geom id).
SHADE_KIND_OTHER, SHADE_KIND_BOX, SHADE_KIND_CAPSULE = 0.0, 1.0, 2.0
# The material row's layout (conav_jax.data.materials.Material.row): base rgb, second rgb,
# pattern index, period (m), orientation (rad).
_RGB_COL, _RGB2_COL, _PATTERN_COL, _PERIOD_COL, _ANGLE_COL = 0, 3, 6, 7, 8
_KIND_COL = MATERIAL_WIDTH
_LO_COL, _HI_COL, _P0_COL, _P1_COL = _KIND_COL + 1, _KIND_COL + 4, _KIND_COL + 7, _KIND_COL + 10
SHADING_WIDTH = _KIND_COL + 13


def shading_table(geometry: SceneGeometry, geom_material: jax.Array) -> jax.Array:
    """(n_geoms, SHADING_WIDTH) float32 rows by geom id: `geom_material` (n_geoms,
    MATERIAL_WIDTH), the kind (box, capsule, other: the floor and anything else), the box
    corners and the capsule segment of `geometry` (zeros where they do not apply)."""
    n_geoms = geom_material.shape[0]
    kind = _geom_table(n_geoms, geometry.box_ids, jnp.full(geometry.box_ids.shape, SHADE_KIND_BOX, jnp.float32),
                       fill=SHADE_KIND_OTHER)
    kind = kind.at[geometry.capsule_ids].set(SHADE_KIND_CAPSULE)
    parts = [geom_material.astype(jnp.float32), kind[:, None],
             _geom_table(n_geoms, geometry.box_ids, geometry.box_lo_m),
             _geom_table(n_geoms, geometry.box_ids, geometry.box_hi_m),
             _geom_table(n_geoms, geometry.capsule_ids, geometry.capsule_p0_m),
             _geom_table(n_geoms, geometry.capsule_ids, geometry.capsule_p1_m)]
    return jnp.concatenate([x.astype(jnp.float32) for x in parts], axis=-1)


def _normal_components(dirs, hit, column):
    """The outward unit normal (three arrays like `hit`'s) at hits `hit` of rays `dirs` (three
    arrays each, broadcastable) on the geoms whose shading-table columns `column(k)` returns per
    pixel: a box's face the ray entered (of the three faces facing the ray, the one whose plane
    is nearest the hit), a capsule's radial direction from its segment, up elsewhere."""
    kind = column(_KIND_COL)
    gap = [jnp.abs(h - jnp.where(d > 0, column(_LO_COL + k), column(_HI_COL + k)))
           for k, (d, h) in enumerate(zip(dirs, hit))]
    face_x = (gap[0] <= gap[1]) & (gap[0] <= gap[2])
    face_y = ~face_x & (gap[1] <= gap[2])
    face_z = ~face_x & ~face_y
    box_n = [jnp.where(f, -jnp.sign(d), 0.0) for f, d in zip((face_x, face_y, face_z), dirs)]
    a = [column(_P0_COL + k) for k in range(3)]
    ba = [column(_P1_COL + k) - a[k] for k in range(3)]
    ha = [h - a_ for h, a_ in zip(hit, a)]
    t = jnp.clip(sum(u * v for u, v in zip(ha, ba)) / jnp.maximum(sum(v * v for v in ba), _EPS), 0.0, 1.0)
    radial = [u - t * v for u, v in zip(ha, ba)]
    inv = 1.0 / jnp.maximum(jnp.sqrt(sum(r * r for r in radial)), _EPS)
    up = (0.0, 0.0, 1.0)
    return [jnp.where(kind == SHADE_KIND_BOX, bn, jnp.where(kind == SHADE_KIND_CAPSULE, r * inv, u))
            for bn, r, u in zip(box_n, radial, up)]


def _table_columns(table: jax.Array, ids: jax.Array):
    """`column(k)`: column k of `table`'s rows at geom ids `ids` (clipped into the table)."""
    safe = jnp.clip(ids, 0, table.shape[0] - 1)
    return lambda k: table[safe, k]


def light_unit(cfg: SensorConfig) -> np.ndarray:
    """SensorConfig's light direction normalised (3,) float32."""
    light = np.asarray(cfg.light_direction, np.float64)
    return (light / np.linalg.norm(light)).astype(np.float32)


def shade_pixels(cfg: SensorConfig, cam_xyz_m, dirs, depth, ids, column):
    """RGB (three arrays like `depth`) of hits at `depth` (m) along rays `dirs` (three
    broadcastable arrays, world frame) from `cam_xyz_m` on geoms `ids` (-1: sky), whose
    shading-table columns (`shading_table`) `column(k)` returns per pixel: the material's
    pattern at the hit point, Lambertian-shaded by the surface normal plus the ambient term.
    The XLA colouring and the Pallas kernel both call it (their `column` differs: an array
    gather, a load from the kernel's table), so their colours agree."""
    hit = [cam_xyz_m[k] + depth * dirs[k] for k in range(3)]
    pattern = jnp.floor(column(_PATTERN_COL) + 0.5).astype(jnp.int32)  # stored as a float index
    mix = pattern_mix(tuple(hit), pattern, column(_PERIOD_COL), column(_ANGLE_COL))
    light = light_unit(cfg)
    normal = _normal_components(dirs, hit, column)
    lambert = jnp.maximum(sum(float(light[k]) * normal[k] for k in range(3)), 0.0)
    gain = cfg.ambient + (1.0 - cfg.ambient) * lambert
    hit_any = ids >= 0
    base = [column(_RGB_COL + c) for c in range(3)]
    return [jnp.where(hit_any, (base[c] + mix * (column(_RGB2_COL + c) - base[c])) * gain, float(SKY_RGB[c]))
            for c in range(3)]


def shade(cfg: SensorConfig, cam_xyz_m: jax.Array, yaw_rad: jax.Array, depth: jax.Array, ids: jax.Array,
          geometry: SceneGeometry, geom_material: jax.Array) -> jax.Array:
    """RGB-D (H, W, 4) of a cast (depth (H, W) m, geom ids (H, W), from any caster) from a camera
    at `cam_xyz_m` facing `yaw_rad`: each hit geom's material (`geom_material` (n_geoms,
    MATERIAL_WIDTH) rows by geom id, conav_jax.data.materials) with its pattern at the hit point,
    Lambertian-shaded by the surface normal under SensorConfig's light plus its ambient term;
    sky where nothing is hit; depth unchanged (`shade_pixels`).

    With the Pallas caster (SensorConfig.kind "pallas", or "auto" where it resolves so) and
    SensorConfig.pallas_shade the colouring runs in a Pallas kernel too
    (envs.panorama_pallas.pallas_shade): XLA writes the per-pixel gathers of the material and
    geometry tables to memory rather than fusing them, and the kernel keeps them in registers.
    Otherwise XLA computes it from gathers of the shading table, on an accelerator a block of
    rows at a time (SHADE_BLOCK_ROWS): a batch of thousands of panoramas never holds more than a
    block's temporaries. The same colours either way."""
    table = shading_table(geometry, geom_material)
    if cfg.pallas_shade and cfg.kind != "reference" and resolve_sensor_kind(cfg.kind) == "pallas":
        from conav_jax.envs.panorama_pallas import pallas_shade

        return pallas_shade(cfg, cam_xyz_m, yaw_rad, depth, ids, table)
    height, width = depth.shape
    rows = _row_block(height, jax.default_backend())
    _, el = ray_angles(cfg)
    n = height // rows

    def block(args):
        d, i, e = args
        rgb = shade_pixels(cfg, cam_xyz_m, _ray_components(cfg, yaw_rad, e), d, i, _table_columns(table, i))
        return jnp.stack(rgb + [d], axis=-1)

    if n == 1:
        return block((depth, ids, jnp.asarray(el)))
    out = jax.lax.map(block, (depth.reshape(n, rows, width), ids.reshape(n, rows, width),
                              jnp.asarray(el).reshape(n, rows)))
    return out.reshape(height, width, 4)


def front_view(rgbd: jax.Array) -> jax.Array:
    """The forward quarter of a panorama (..., H, W/4, 4): the intention predictor's view."""
    w = rgbd.shape[-2]
    return rgbd[..., 3 * w // 8 : 5 * w // 8, :]
