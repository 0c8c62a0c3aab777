"""Jittable planning on geodesic fields: distance lookups and the downhill direction.

A field is a (ny, nx) array of shortest-path metres to a goal over a grid with the given origin
and cell size (conav_jax.nav.navigation). These functions run inside jit/vmap: the simulator's
reward, the expert and the oracle-pathfinder baselines all use them.
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


def descent_chain(
    field: jax.Array, origin: jax.Array, cell_m: float, xy: jax.Array, steps: int, clearance: jax.Array | None = None
) -> jax.Array:
    """Cells (steps, 2) int32 (iy, ix) of the next `steps` cells down the field's steepest-descent
    chain from the cell holding xy: each move goes to the 8-neighbour minimising value + step
    length, if that is lower than the current value; at a minimum the chain repeats its cell.

    With `clearance` (a signed wall-clearance grid on the same cells) the chain only enters
    cells of positive clearance, unless it starts in a blocked one (then it may leave through
    any): the simulator's fields give blocked cells near free space "nearest free value +
    straight distance", so an unconstrained descent may cut a door's corner through them."""
    ny, nx = field.shape
    f = field.astype(jnp.float32)
    offsets = jnp.asarray(_OFFSETS)
    lengths = jnp.asarray(_LENGTHS) * cell_m
    start = field_cell(field, origin, cell_m, xy)
    start_blocked = False if clearance is None else clearance[start] <= 0.0

    def downhill(cell, _):
        iy, ix = cell
        cy = jnp.clip(iy + offsets[:, 0], 0, ny - 1)
        cx = jnp.clip(ix + offsets[:, 1], 0, nx - 1)
        ok = True if clearance is None else (clearance[cy, cx] > 0.0) | start_blocked
        k = jnp.argmin(jnp.where(ok, f[cy, cx] + lengths, jnp.inf))
        better = (f[cy[k], cx[k]] < f[iy, ix]) & (True if clearance is None else ok[k])
        nxt = (jnp.where(better, cy[k], iy), jnp.where(better, cx[k], ix))
        return nxt, jnp.stack(nxt)

    _, chain = jax.lax.scan(downhill, start, None, length=steps)
    return chain


def cell_centres(origin: jax.Array, cell_m: float, cells: jax.Array) -> jax.Array:
    """World xy (..., 2) of the centres of grid cells (..., 2) given as (iy, ix)."""
    return origin + (cells[..., ::-1].astype(jnp.float32) + 0.5) * cell_m


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
