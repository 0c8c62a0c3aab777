"""Jittable planning on geodesic fields: distance lookups and the downhill direction.

A field is a (ny, nx) array of shortest-path metres to a goal over a grid with the given origin
and cell size (conav_jax.navigation). These functions run inside jit/vmap: the simulator's
reward and SPL, the expert, and the oracle-pathfinder baselines all use them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# The 8 neighbour offsets (dy, dx) and their lengths in cells.
_OFFSETS = np.array([(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)], np.int32)
_LENGTHS = np.sqrt((_OFFSETS**2).sum(-1)).astype(np.float32)


def field_cell(field: jax.Array, origin: jax.Array, cell_m: float, xy: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(iy, ix) of the cell holding xy, clamped to the grid."""
    ny, nx = field.shape
    ix = jnp.clip(jnp.floor((xy[0] - origin[0]) / cell_m).astype(jnp.int32), 0, nx - 1)
    iy = jnp.clip(jnp.floor((xy[1] - origin[1]) / cell_m).astype(jnp.int32), 0, ny - 1)
    return iy, ix


def field_value(field: jax.Array, origin: jax.Array, cell_m: float, xy: jax.Array) -> jax.Array:
    """Geodesic metres from xy to the field's goal (inf where unreachable)."""
    iy, ix = field_cell(field, origin, cell_m, xy)
    return field[iy, ix].astype(jnp.float32)


def field_direction(field: jax.Array, origin: jax.Array, cell_m: float, xy: jax.Array, lookahead: int = 4) -> jax.Array:
    """Unit world direction (2,) that leads downhill toward the goal.

    Follows the field's steepest-descent chain `lookahead` cells ahead and points at the cell
    it ends in, which smooths the 45-degree zig-zag of a grid path. Zero at the goal or where
    no neighbour is lower."""
    ny, nx = field.shape
    f = field.astype(jnp.float32)
    offsets = jnp.asarray(_OFFSETS)
    lengths = jnp.asarray(_LENGTHS) * cell_m

    def downhill(cell, _):
        iy, ix = cell
        ny_ = jnp.clip(iy + offsets[:, 0], 0, ny - 1)
        nx_ = jnp.clip(ix + offsets[:, 1], 0, nx - 1)
        cand = f[ny_, nx_] + lengths
        k = jnp.argmin(cand)
        better = f[ny_[k], nx_[k]] < f[iy, ix]
        return (jnp.where(better, ny_[k], iy), jnp.where(better, nx_[k], ix)), None

    start = field_cell(field, origin, cell_m, xy)
    (iy, ix), _ = jax.lax.scan(downhill, start, None, length=lookahead)
    target = jnp.stack([origin[0] + (ix + 0.5) * cell_m, origin[1] + (iy + 0.5) * cell_m])
    delta = target - xy
    norm = jnp.linalg.norm(delta)
    moved = (iy != start[0]) | (ix != start[1])
    return jnp.where(moved & (norm > 1e-6), delta / jnp.maximum(norm, 1e-6), 0.0)


def fill_blocked(field: np.ndarray, free: np.ndarray, cell_m: float, reach_m: float = 0.5) -> np.ndarray:
    """Extend a field into blocked cells within reach_m of free ones (value + straight distance).

    A robot pressed against a wall has its centre in a cell the inflated grid calls blocked;
    this gives such cells the distance through their nearest free neighbour instead of inf."""
    out = field.astype(np.float32).copy()
    r = int(np.ceil(reach_m / cell_m))
    ny, nx = field.shape
    src = np.where(free, field, np.inf).astype(np.float32)
    best = np.full_like(out, np.inf)
    padded = np.full((ny + 2 * r, nx + 2 * r), np.inf, np.float32)
    padded[r : r + ny, r : r + nx] = src
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            dist = cell_m * np.hypot(dy, dx)
            if dist > reach_m:
                continue
            np.minimum(best, padded[r + dy : r + dy + ny, r + dx : r + dx + nx] + dist, out=best)
    out[~free] = best[~free]
    return out
