"""Panoramic RGB-D sensors: a fast caster of our own and the `mujoco.mjx.ray` reference.

Both cast the same rays (SensorConfig's equirectangular layout) and return depth (metres along
the ray, max_depth where nothing is hit) and the MJX geom id hit (-1 for none), from which RGB
is a colour lookup. The fast caster uses the scene's structure: every box is axis-aligned, so
per image column the ray is a 2-D ray and each box a 2-D slab interval; per row the box's z
range turns into a second interval along the same horizontal distance; their intersection
gives the exact hit. The floor is analytic per row; capsules (the humanoid) are tested per ray.
The nearest hit and its id are found together by a min over packed integer keys.

Three implementations of that caster share the packing: `fast_depth_ids` (kind "fast")
computes the per-geom terms once per column (G, W) and per row (G, H) and writes the per-pixel
test as one expression whose min over geoms XLA fuses, so only (H, W) arrays reach memory;
`envs.panorama_pallas` (kind "pallas") runs the same per-pixel functions in a Triton kernel that
also skips geoms a block of columns cannot see; `legacy_depth_ids` (kind "legacy") is the
previous form, a running min over passes of `geoms_per_pass` geoms that materialise
(P, H, W) arrays. Data flow: robot pose + scene boxes + human capsules -> (depth, geom id) -> rgbd.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from envs.config import SensorConfig
from envs.mjcf import RAY_GEOMGROUP

_EPS = 1e-9
# Packed key = quantised depth (upper 24 bits) | geom id (lower 8 bits); min over keys gives
# the nearest hit and its id in one simple reduction XLA can fuse with the intersection math.
_ID_BITS = 8
_MAX_GEOMS = (1 << _ID_BITS) - 1  # id 255 means "no hit"
_DEPTH_BITS = 24
SKY_RGB = np.array([0.62, 0.72, 0.85], np.float32)


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
        [ce * jnp.cos(a)[None, :], ce * jnp.sin(a)[None, :], jnp.broadcast_to(jnp.sin(e)[:, None], (cfg.height, cfg.width))],
        axis=-1,
    )


def _scale(cfg: SensorConfig) -> float:
    return float((1 << _DEPTH_BITS) - 2) / cfg.max_depth_m


def _pack(depth: jax.Array, ids: jax.Array, cfg: SensorConfig) -> jax.Array:
    """uint32 keys; depths at or beyond max_depth (and misses) become the 'no hit' key."""
    q = jnp.floor(jnp.clip(depth, 0.0, cfg.max_depth_m) * _scale(cfg)).astype(jnp.uint32)
    hit = depth < cfg.max_depth_m
    key = (q << _ID_BITS) | ids.astype(jnp.uint32)
    return jnp.where(hit, key, jnp.uint32(0xFFFFFFFF))


def _unpack(key: jax.Array, cfg: SensorConfig) -> tuple[jax.Array, jax.Array]:
    miss = key == jnp.uint32(0xFFFFFFFF)
    ids = (key & jnp.uint32(_MAX_GEOMS)).astype(jnp.int32)
    # The centre of the quantisation bin: error at most half a bin (~0.3 micrometres at 10 m).
    depth = ((key >> _ID_BITS).astype(jnp.float32) + 0.5) / _scale(cfg)
    return jnp.where(miss, cfg.max_depth_m, depth), jnp.where(miss, -1, ids)


def _in_passes(cfg: SensorConfig, init: jax.Array, per_geom: tuple, keys_fn) -> jax.Array:
    """Running min of keys over geoms, `geoms_per_pass` at a time (lax.scan over passes).

    per_geom: arrays with a leading geom axis G; padded to a multiple of the pass size with
    copies of geom 0 (harmless: a duplicate cannot change a min)."""
    grouped = _split(per_geom, cfg.geoms_per_pass)

    def body(keys, group):
        return jnp.minimum(keys, jnp.min(keys_fn(*group), axis=0)), None

    keys, _ = jax.lax.scan(body, init, grouped)
    return keys


def _box_keys(cfg, cam, yaw, box_lo, box_hi, box_ids, box_valid, init):
    """Nearest box hit keys (H, W) merged into `init`: a 2-D slab test per column and a z
    interval per row, per box."""
    az, el = ray_angles(cfg)
    a = yaw + jnp.asarray(az)  # (W,)
    dx, dy = jnp.cos(a), jnp.sin(a)
    safe = lambda v: jnp.where(jnp.abs(v) < _EPS, jnp.where(v < 0, -_EPS, _EPS), v)
    inv_x, inv_y = 1.0 / safe(dx), 1.0 / safe(dy)
    tan_e = jnp.tan(jnp.asarray(el))
    tan_e = jnp.where(jnp.abs(tan_e) < _EPS, _EPS, tan_e)
    inv_cos = (1.0 / jnp.cos(jnp.asarray(el)))[None, :, None]

    def keys_fn(lo, hi, ids, valid):  # P boxes -> (P, H, W) keys
        # (P, W) horizontal distances of the 2-D slab entries / exits.
        tx1 = (lo[:, None, 0] - cam[0]) * inv_x[None]
        tx2 = (hi[:, None, 0] - cam[0]) * inv_x[None]
        ty1 = (lo[:, None, 1] - cam[1]) * inv_y[None]
        ty2 = (hi[:, None, 1] - cam[1]) * inv_y[None]
        t_in = jnp.maximum(jnp.minimum(tx1, tx2), jnp.minimum(ty1, ty2))
        t_out = jnp.minimum(jnp.maximum(tx1, tx2), jnp.maximum(ty1, ty2))
        # (P, H) horizontal distance interval where the row's ray is inside the box's z range.
        tz1 = (lo[:, None, 2] - cam[2]) / tan_e[None]
        tz2 = (hi[:, None, 2] - cam[2]) / tan_e[None]
        z_in, z_out = jnp.minimum(tz1, tz2), jnp.maximum(tz1, tz2)
        enter = jnp.maximum(jnp.maximum(t_in[:, None, :], z_in[:, :, None]), 0.0)  # (P, H, W)
        leave = jnp.minimum(t_out[:, None, :], z_out[:, :, None])
        hit = (enter <= leave) & valid[:, None, None]
        depth = jnp.where(hit, enter * inv_cos, jnp.inf)
        return _pack(depth, jnp.broadcast_to(ids[:, None, None], depth.shape), cfg)

    return _in_passes(cfg, init, (box_lo, box_hi, box_ids, box_valid), keys_fn)


def _capsule_depth(origin, dirs, p0, p1, radius):
    """Distance along unit rays (H, W, 3) to a capsule p0-p1 of `radius`; inf if missed.

    Closed form: the ray against the infinite cylinder, accepted where the hit lies between
    the end caps, else against the nearer end-cap sphere."""
    ba = p1 - p0
    oa = origin - p0
    baba = jnp.dot(ba, ba, precision=jax.lax.Precision.HIGHEST)
    bard = jnp.einsum("hwk,k->hw", dirs, ba, precision=jax.lax.Precision.HIGHEST)
    baoa = jnp.dot(ba, oa, precision=jax.lax.Precision.HIGHEST)
    rdoa = jnp.einsum("hwk,k->hw", dirs, oa, precision=jax.lax.Precision.HIGHEST)
    oaoa = jnp.dot(oa, oa, precision=jax.lax.Precision.HIGHEST)
    a = baba - bard * bard
    b = baba * rdoa - baoa * bard
    c = baba * oaoa - baoa * baoa - radius * radius * baba
    h = b * b - a * c
    a_safe = jnp.where(jnp.abs(a) < _EPS, _EPS, a)
    t_body = (-b - jnp.sqrt(jnp.maximum(h, 0.0))) / a_safe
    y = baoa + t_body * bard
    body_ok = (h >= 0) & (jnp.abs(a) >= _EPS) & (y > 0) & (y < baba) & (t_body > 0)
    # End caps: the sphere at p0 if the body hit falls before it, else at p1.
    cap_center_offset = jnp.where(y <= 0, 0.0, 1.0)[..., None]
    oc = origin - (p0 + cap_center_offset * ba)  # (H, W, 3)
    bc = jnp.sum(dirs * oc, axis=-1)
    cc = jnp.sum(oc * oc, axis=-1) - radius * radius
    hc = bc * bc - cc
    t_cap = -bc - jnp.sqrt(jnp.maximum(hc, 0.0))
    cap_ok = (hc >= 0) & (t_cap > 0)
    return jnp.where(body_ok, t_body, jnp.where(cap_ok, t_cap, jnp.inf))


def _capsule_keys(cfg, cam, dirs, cap_p0, cap_p1, cap_r, cap_ids, init):
    def keys_fn(p0, p1, r, ids):  # P capsules -> (P, H, W) keys
        depth = jax.vmap(_capsule_depth, in_axes=(None, None, 0, 0, 0))(cam, dirs, p0, p1, r)
        return _pack(depth, jnp.broadcast_to(ids[:, None, None], depth.shape), cfg)

    return _in_passes(cfg, init, (cap_p0, cap_p1, cap_r, cap_ids), keys_fn)


def _floor_keys(cfg, cam, floor_id):
    _, el = ray_angles(cfg)
    sin_e = jnp.asarray(np.sin(el))
    depth = jnp.where(sin_e < -_EPS, -cam[2] / jnp.where(sin_e < -_EPS, sin_e, -1.0), jnp.inf)  # (H,)
    depth = jnp.broadcast_to(depth[:, None], (cfg.height, cfg.width))
    return _pack(depth, jnp.full(depth.shape, floor_id, jnp.int32), cfg)


def legacy_depth_ids(
    cfg: SensorConfig,
    cam: jax.Array,
    yaw: jax.Array,
    box_lo: jax.Array,
    box_hi: jax.Array,
    box_ids: jax.Array,
    box_valid: jax.Array,
    cap_p0: jax.Array,
    cap_p1: jax.Array,
    cap_r: jax.Array,
    cap_ids: jax.Array,
    floor_id: int,
) -> tuple[jax.Array, jax.Array]:
    """The previous caster (kind "legacy"): the same keys as `fast_depth_ids`, computed in
    passes of `geoms_per_pass` geoms that each materialise (P, H, W) arrays. Kept as a
    bit-for-bit baseline for tests and `conav bench sim`."""
    keys = _floor_keys(cfg, cam, floor_id)
    keys = _box_keys(cfg, cam, yaw, box_lo, box_hi, box_ids, box_valid, keys)
    if cap_p0.shape[0]:
        keys = _capsule_keys(cfg, cam, ray_directions(cfg, yaw), cap_p0, cap_p1, cap_r, cap_ids, keys)
    return _unpack(keys, cfg)


# -- the fused caster (kind "fast") -------------------------------------------------------------
# Per-geom work is split into terms per (geom, column) and per (geom, row), computed once; per
# pixel only a few max/min/compare ops remain, in a running min over geoms that XLA fuses into
# one loop (the capsules, then the boxes in two passes of a lax.scan), so no (geoms, H, W)
# array is ever written to memory: only the (H, W) keys, three times. The same terms and
# per-pixel functions feed the Pallas kernel (envs/panorama_pallas.py).

_NO_HIT = 0xFFFFFFFF


def _split(arrays: tuple, p: int) -> tuple:
    """Arrays with a leading geom axis G -> (ceil(G / p), p, ...), padded with copies of geom 0
    (harmless: a duplicate cannot change a min)."""
    g = arrays[0].shape[0]
    n = -(-g // p)
    pad = n * p - g
    return tuple(jnp.concatenate([a, jnp.broadcast_to(a[:1], (pad,) + a.shape[1:])]).reshape((n, p) + a.shape[1:])
                 for a in arrays)


def box_terms(cfg: SensorConfig, cam, yaw, box_lo, box_hi, box_valid):
    """Per box: column terms (G, W) `col_in` (horizontal distance where the column's 2-D ray
    enters the box's footprint, at least 0; +inf where it misses it or the box is padding) and
    `col_out` (where it leaves), and row terms (G, H) `row_in`, `row_out`: the horizontal
    distance interval over which the row's ray is inside the box's z range."""
    az, el = ray_angles(cfg)
    a = yaw + jnp.asarray(az)  # (W,)
    dx, dy = jnp.cos(a), jnp.sin(a)
    safe = lambda v: jnp.where(jnp.abs(v) < _EPS, jnp.where(v < 0, -_EPS, _EPS), v)
    inv_x, inv_y = 1.0 / safe(dx), 1.0 / safe(dy)
    tx1 = (box_lo[:, None, 0] - cam[0]) * inv_x[None]
    tx2 = (box_hi[:, None, 0] - cam[0]) * inv_x[None]
    ty1 = (box_lo[:, None, 1] - cam[1]) * inv_y[None]
    ty2 = (box_hi[:, None, 1] - cam[1]) * inv_y[None]
    t_in = jnp.maximum(jnp.maximum(jnp.minimum(tx1, tx2), jnp.minimum(ty1, ty2)), 0.0)
    t_out = jnp.minimum(jnp.maximum(tx1, tx2), jnp.maximum(ty1, ty2))
    # A column that misses the footprint can never hit (enter >= t_in > t_out >= leave): the
    # same outcome as the per-pixel test, decided once per column.
    col_in = jnp.where(box_valid[:, None] & (t_in <= t_out), t_in, jnp.inf)
    tan_e = jnp.tan(jnp.asarray(el))
    tan_e = jnp.where(jnp.abs(tan_e) < _EPS, _EPS, tan_e)
    tz1 = (box_lo[:, None, 2] - cam[2]) / tan_e[None]
    tz2 = (box_hi[:, None, 2] - cam[2]) / tan_e[None]
    return col_in, t_out, jnp.minimum(tz1, tz2), jnp.maximum(tz1, tz2)


def box_pixel_keys(col_in, col_out, row_in, row_out, inv_cos, ids, scale: float, max_depth: float):
    """Packed keys for broadcastable column terms, row terms, 1/cos(elevation) and ids (uint32).
    The legacy caster's per-pixel arithmetic: keys agree bit for bit below max_depth."""
    enter = jnp.maximum(col_in, row_in)
    leave = jnp.minimum(col_out, row_out)
    return _pack_single_use(jnp.where(enter <= leave, enter * inv_cos, jnp.inf), ids, scale, max_depth)


def _pack_single_use(depth, ids, scale: float, max_depth: float):
    """Key of `depth` (inf for no hit) with each value used once, so that XLA fuses the
    producer (divides, square roots) into the min instead of writing it out. A hit needs its
    quantised depth below that of max_depth: the legacy test `depth < max_depth` except within
    one quantum (0.6 micrometres at 10 m) of max_depth."""
    q = jnp.floor(jnp.minimum(depth, max_depth) * scale).astype(jnp.uint32)
    q_max = np.uint32(np.floor(np.float32(max_depth) * np.float32(scale)))
    return jnp.where(q >= q_max, jnp.uint32(_NO_HIT), (q << _ID_BITS) | ids)


def capsule_terms(cfg: SensorConfig, cam, yaw, cap_p0, cap_p1, cap_r):
    """Per capsule: column terms (C, W) `u` = d_xy . (p1 - p0)_xy and `v` = d_xy . (cam - p0)_xy
    for the column's horizontal unit direction d_xy, and scalars (C,) for the closed form.
    A ray's direction is (cos e d_xy, sin e), so per pixel dir . x = cos e * (col term) + sin e * x_z."""
    az, _ = ray_angles(cfg)
    a = yaw + jnp.asarray(az)
    ca, sa = jnp.cos(a), jnp.sin(a)
    ba = cap_p1 - cap_p0
    oa = cam[None, :] - cap_p0
    u = ca[None] * ba[:, 0:1] + sa[None] * ba[:, 1:2]
    v = ca[None] * oa[:, 0:1] + sa[None] * oa[:, 1:2]
    dot = lambda x, y: jnp.sum(x * y, axis=-1)
    baba, baoa, oaoa = dot(ba, ba), dot(ba, oa), dot(oa, oa)
    r2 = cap_r * cap_r
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


def capsule_pixel_keys(u, v, ce, se, s, ids, scale: float, max_depth: float):
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
    return _pack_single_use(depth, ids, scale, max_depth)


def floor_row_keys(cfg: SensorConfig, cam, floor_id) -> jax.Array:
    """(H,) keys of the floor plane per row (no hit above the horizon)."""
    _, el = ray_angles(cfg)
    sin_e = jnp.asarray(np.sin(el))
    depth = jnp.where(sin_e < -_EPS, -cam[2] / jnp.where(sin_e < -_EPS, sin_e, -1.0), jnp.inf)
    return _pack(depth, jnp.full(depth.shape, floor_id, jnp.int32), cfg)


def elevation_terms(cfg: SensorConfig):
    """(1/cos e, cos e, sin e) per row (H,), as the legacy caster computes them."""
    _, el = ray_angles(cfg)
    e = jnp.asarray(el)
    return 1.0 / jnp.cos(e), jnp.cos(e), jnp.sin(e)


def fast_depth_ids(
    cfg: SensorConfig,
    cam: jax.Array,
    yaw: jax.Array,
    box_lo: jax.Array,
    box_hi: jax.Array,
    box_ids: jax.Array,
    box_valid: jax.Array,
    cap_p0: jax.Array,
    cap_p1: jax.Array,
    cap_r: jax.Array,
    cap_ids: jax.Array,
    floor_id: int,
) -> tuple[jax.Array, jax.Array]:
    """Depth (H, W) metres and geom ids (H, W) for one camera at `cam` (3,) facing `yaw`.

    box_lo/box_hi (G, 3) corners of axis-aligned boxes, box_ids (G,) their geom ids, box_valid
    (G,) which are real; capsules cap_p0/cap_p1 (C, 3) segment ends and cap_r (C,) radii.
    A running min over geoms of expressions built from (1, W) column terms and (H, 1) row
    terms (cfg.fast_min "unroll"), or min-reductions over (G, H, W) expressions ("reduce");
    see the section comment above."""
    scale, maxd = _scale(cfg), float(cfg.max_depth_m)
    inv_cos, ce, se = elevation_terms(cfg)
    keys = jnp.broadcast_to(floor_row_keys(cfg, cam, floor_id)[:, None], (cfg.height, cfg.width))
    col_in, col_out, row_in, row_out = box_terms(cfg, cam, yaw, box_lo, box_hi, box_valid)
    box_ids = box_ids.astype(jnp.uint32)
    if cap_p0.shape[0]:
        u, v, s = capsule_terms(cfg, cam, yaw, cap_p0, cap_p1, cap_r)
        cap_ids = cap_ids.astype(jnp.uint32)
        if cfg.fast_min == "reduce":
            ckeys = capsule_pixel_keys(
                u[:, None, :], v[:, None, :], ce[None, :, None], se[None, :, None],
                {k: x[:, None, None] for k, x in s.items()}, cap_ids[:, None, None], scale, maxd,
            )
            keys = jnp.minimum(keys, jnp.min(ckeys, axis=0))
        else:  # "unroll": a running min, one elementwise chain per geom
            for c in range(cap_p0.shape[0]):
                keys = jnp.minimum(keys, capsule_pixel_keys(
                    u[c][None, :], v[c][None, :], ce[:, None], se[:, None],
                    {n: x[c] for n, x in s.items()}, cap_ids[c], scale, maxd,
                ))
    box_terms_ = (col_in, col_out, row_in, row_out, box_ids)
    if cfg.fast_min == "reduce":
        def one_pass(keys, group):
            ci, co, ri, ro, ids = group
            k = box_pixel_keys(ci[:, None, :], co[:, None, :], ri[:, :, None], ro[:, :, None],
                               inv_cos[None, :, None], ids[:, None, None], scale, maxd)
            return jnp.minimum(keys, jnp.min(k, axis=0)), None
    else:
        def one_pass(keys, group):
            for ci, co, ri, ro, ids in zip(*group):
                keys = jnp.minimum(keys, box_pixel_keys(ci[None, :], co[None, :], ri[:, None], ro[:, None],
                                                        inv_cos[:, None], ids, scale, maxd))
            return keys, None
    # Boxes in two passes of a lax.scan: its carry is a fusion boundary, so the keys are written
    # once (4 bytes a pixel) and depth, ids and colours read them. A caster ending in plain
    # elementwise ops lets XLA fuse it whole into each consumer (depth, the colour gather, each
    # rgbd channel, the front view) and cast the panorama several times over (seen on the CPU).
    keys, _ = jax.lax.scan(one_pass, keys, _split(box_terms_, max(1, -(-box_lo.shape[0] // 2))))
    return _unpack(keys, cfg)


def reference_depth_ids(
    cfg: SensorConfig, m: mjx.Model, d: mjx.Data, cam: jax.Array, yaw: jax.Array, exclude_body: int
) -> tuple[jax.Array, jax.Array]:
    """The same panorama from `mujoco.mjx.ray`, one ray per pixel (slow; the ground truth)."""
    dirs = ray_directions(cfg, yaw).reshape(-1, 3)
    dist, geom = jax.vmap(lambda v: mjx.ray(m, d, cam, v, geomgroup=RAY_GEOMGROUP, bodyexclude=exclude_body))(dirs)
    hit = (geom >= 0) & (dist >= 0) & (dist < cfg.max_depth_m)
    depth = jnp.where(hit, dist, cfg.max_depth_m).reshape(cfg.height, cfg.width)
    ids = jnp.where(hit, geom, -1).reshape(cfg.height, cfg.width)
    return depth, ids


def colourise(depth: jax.Array, ids: jax.Array, geom_rgb: jax.Array) -> jax.Array:
    """RGB-D (H, W, 4): the hit geom's colour (sky where nothing is hit) and depth in metres."""
    rgb = jnp.where((ids >= 0)[..., None], geom_rgb[jnp.maximum(ids, 0)], jnp.asarray(SKY_RGB))
    return jnp.concatenate([rgb, depth[..., None]], axis=-1)


def front_view(rgbd: jax.Array) -> jax.Array:
    """The forward quarter of a panorama (..., H, W/4, 4): the intention predictor's view."""
    w = rgbd.shape[-2]
    return rgbd[..., 3 * w // 8 : 5 * w // 8, :]
