"""Crops of the panorama around the human: what the intention predictor looks at.

human position `(2,)` m in the robot frame (the env's `obs["human_pos"]`) -> the column of its
azimuth, by SensorConfig's convention (column j looks at azimuth yaw + pi - 2 pi (j + 0.5) / W),
and the rows over a standing human's body at its distance (camera at `camera_height_m`, rows of
square pixels over a vertical field of view of 2 pi H / W, row 0 at the top) -> a `(ch, cw, C)`
window of the panorama's own pixels (no resampling), wrapping across the seam behind the robot.
Jittable and vmappable; `crop_window` gives the window alone; `default_crop_hw` the crop's
size for a panorama resolution.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from conav_jax.config import TaskConfig
from conav_jax.models.perceiver import PerceiverConfig

# Heights (m) of the body the crop's rows frame: the floor up to a little above the crown of a
# standing human (~1.75 m), so hands raised to the face stay inside. When the body is taller
# than the crop (closer than ~2 m at 64 rows of a 112x448 panorama) the window keeps the top:
# the head, arms and the object handled say more about an activity than the feet.
BODY_Z_M = (0.0, 1.9)


def default_crop_hw(
    panorama_hw: tuple[int, int], side: int = PerceiverConfig.image_hw[0], multiple: int = PerceiverConfig.patch_size
) -> tuple[int, int]:
    """The square crop read from panoramas of `panorama_hw`: `side` (the Perceiver's default
    frame; 64 of a 112x448 panorama frames a standing human 2-3 m away), or the panorama's
    height rounded down to `multiple` (the Perceiver's patch) where that is smaller: a lower
    resolution sees the human in fewer pixels, and the crop is cut from the panorama the agents
    render."""
    h = panorama_hw[0]
    if h < multiple:
        raise ValueError(f"a {h}x{panorama_hw[1]} panorama is lower than one {multiple}-pixel patch")
    c = min(side, h // multiple * multiple)
    return c, c


def _check(panorama_hw: tuple[int, int], human_pos_xy: jax.Array, crop_hw: tuple[int, int]) -> None:
    """ValueError for shapes that cannot be cropped, and for a NaN position given as a value
    (a traced one cannot raise: `human_crop` fills its crop with NaN instead)."""
    h, w = panorama_hw
    ch, cw = crop_hw
    if not (isinstance(ch, (int, np.integer)) and isinstance(cw, (int, np.integer)) and ch >= 1 and cw >= 1):
        raise ValueError(f"crop_hw must be two positive integers, got {crop_hw}")
    if ch > h or cw > w:
        raise ValueError(f"a {ch}x{cw} crop does not fit the {h}x{w} panorama")
    if np.shape(human_pos_xy) != (2,):
        raise ValueError(f"human_pos_xy must have shape (2,) (x ahead, y left, m), got {np.shape(human_pos_xy)}")
    if not isinstance(human_pos_xy, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(human_pos_xy))):
        raise ValueError(f"human_pos_xy must be finite, got {np.asarray(human_pos_xy)}")


def crop_window(
    panorama_hw: tuple[int, int],
    human_pos_xy: jax.Array,
    crop_hw: tuple[int, int],
    camera_height_m: float = TaskConfig.camera_height_m,
    body_z_m: tuple[float, float] = BODY_Z_M,
) -> tuple[jax.Array, jax.Array]:
    """(first row () int32, columns (cw,) int32) of the crop of a `panorama_hw` panorama around a
    human at `human_pos_xy` (robot frame, m). The columns are centred on the human's azimuth,
    taken modulo W (a human behind the robot straddles the seam); the rows frame heights
    `body_z_m` at the human's horizontal distance: centred when they fit in `ch` rows, else
    from the top; clamped to the panorama. ValueError as `human_crop`."""
    _check(panorama_hw, human_pos_xy, crop_hw)
    h, w = panorama_hw
    ch, cw = crop_hw
    pos = jnp.asarray(human_pos_xy, jnp.float32)
    # Column j's centre looks at azimuth pi - 2 pi (j + 0.5) / W from the robot's heading.
    azimuth = jnp.arctan2(pos[1], pos[0])
    centre_col = (math.pi - azimuth) * (w / (2.0 * math.pi)) - 0.5
    first_col = jnp.round(centre_col - (cw - 1) / 2.0).astype(jnp.int32)
    cols = jnp.mod(first_col + jnp.arange(cw, dtype=jnp.int32), w)
    # Row i's centre looks at elevation vfov/2 - vfov (i + 0.5) / H, with vfov = 2 pi H / W.
    vfov = 2.0 * math.pi * h / w
    dist = jnp.linalg.norm(pos)
    row_of = lambda z: (vfov / 2.0 - jnp.arctan2(z - camera_height_m, dist)) * (h / vfov) - 0.5
    top, bottom = row_of(body_z_m[1]), row_of(body_z_m[0])
    first_row = jnp.minimum(top, (top + bottom) / 2.0 - (ch - 1) / 2.0)
    first_row = jnp.clip(jnp.round(first_row), 0, h - ch).astype(jnp.int32)
    return first_row, cols


def human_crop(
    rgbd: jax.Array,
    human_pos_xy: jax.Array,
    crop_hw: tuple[int, int],
    camera_height_m: float = TaskConfig.camera_height_m,
    body_z_m: tuple[float, float] = BODY_Z_M,
) -> jax.Array:
    """The `crop_hw` = (ch, cw) window of the panorama `rgbd (H, W, C)` (float; RGB-D as the
    sensor renders it) around the human at `human_pos_xy (2,)` (robot frame, m): `(ch, cw, C)`,
    see `crop_window`. ValueError when the shapes are wrong, the crop is larger than the
    panorama, or a concrete position holds NaN; under jit a NaN position gives a crop of NaN
    (the values are not known when tracing), which poisons whatever reads it rather than
    showing it some made-up view."""
    if rgbd.ndim != 3 or not jnp.issubdtype(rgbd.dtype, jnp.floating):
        raise ValueError(f"rgbd must be a float panorama (H, W, C), got {rgbd.dtype} {rgbd.shape}")
    first_row, cols = crop_window(rgbd.shape[:2], human_pos_xy, crop_hw, camera_height_m, body_z_m)
    rows = jax.lax.dynamic_slice_in_dim(rgbd, first_row, crop_hw[0], axis=0)
    crop = jnp.take(rows, cols, axis=1)
    finite = jnp.all(jnp.isfinite(jnp.asarray(human_pos_xy)))
    return jnp.where(finite, crop, jnp.nan)
