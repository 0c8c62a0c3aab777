"""Navigation on a scene: robot occupancy grid, geodesic distance fields, A* paths.

Scene boxes that block the robot are inflated by the robot radius into a boolean grid; distances
are shortest 8-connected grid paths (straight steps cost one cell, diagonal steps sqrt(2) cells,
diagonals may not cut an occupied corner), in metres. Fields feed the episode generator (goal
reachability, human paths, SPL's shortest length) and, as arrays, the simulator and agents.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

from conav_jax.data.scene import Scene

SQRT2 = math.sqrt(2.0)
# (dy, dx, cost in cells) of the 8 neighbours.
NEIGHBOURS = tuple(
    (dy, dx, SQRT2 if dy and dx else 1.0) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)
)
UNREACHABLE = np.float32(np.inf)


@dataclass(frozen=True)
class OccupancyGrid:
    """free[iy, ix] is True where the robot centre may be. Cell (iy, ix) has its centre at
    (origin_x + (ix + 0.5) * cell_m, origin_y + (iy + 0.5) * cell_m)."""

    free: np.ndarray  # (ny, nx) bool
    origin: tuple[float, float]
    cell_m: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.free.shape

    def to_cell(self, xy) -> tuple[int, int]:
        """(iy, ix) of the cell holding the point xy (clamped to the grid)."""
        ix = int(math.floor((xy[0] - self.origin[0]) / self.cell_m))
        iy = int(math.floor((xy[1] - self.origin[1]) / self.cell_m))
        ny, nx = self.shape
        return min(max(iy, 0), ny - 1), min(max(ix, 0), nx - 1)

    def to_world(self, cells: np.ndarray) -> np.ndarray:
        """World xy (K, 2) of cell centres given (K, 2) integer (iy, ix)."""
        cells = np.asarray(cells, np.float64)
        return np.stack(
            [self.origin[0] + (cells[:, 1] + 0.5) * self.cell_m, self.origin[1] + (cells[:, 0] + 0.5) * self.cell_m],
            axis=-1,
        )

    def is_free(self, xy) -> bool:
        x, y = xy
        ny, nx = self.shape
        ix = math.floor((x - self.origin[0]) / self.cell_m)
        iy = math.floor((y - self.origin[1]) / self.cell_m)
        return 0 <= ix < nx and 0 <= iy < ny and bool(self.free[iy, ix])


def occupancy_grid(scene: Scene, clearance_m: float, cell_m: float, robot_height_m: float) -> OccupancyGrid:
    """Cells whose centre is at least `clearance_m` from every box the robot can hit."""
    x0, y0, x1, y1 = scene.bounds
    nx = int(math.ceil((x1 - x0) / cell_m))
    ny = int(math.ceil((y1 - y0) / cell_m))
    xs = x0 + (np.arange(nx) + 0.5) * cell_m
    ys = y0 + (np.arange(ny) + 0.5) * cell_m
    free = np.ones((ny, nx), bool)
    boxes = list(scene.walls) + [o.box for o in scene.objects if o.blocks_robot(robot_height_m)]
    for b in boxes:
        (cx, cy, _), (hx, hy, _) = b.center, b.half_extents
        # Distance from each cell centre to the box footprint (a rounded-rectangle test).
        dx = np.maximum(np.abs(xs - cx) - hx, 0.0)
        dy = np.maximum(np.abs(ys - cy) - hy, 0.0)
        free &= (dy[:, None] ** 2 + dx[None, :] ** 2) >= clearance_m**2
    # Outside the bounds is not navigable: keep one blocked ring of cells around the edge.
    free[0, :] = free[-1, :] = free[:, 0] = free[:, -1] = False
    return OccupancyGrid(free, (x0, y0), cell_m)


def _neighbour_moves(free: np.ndarray):
    """For each neighbour direction, the mask of cells from which that step is allowed."""
    ny, nx = free.shape
    padded = np.zeros((ny + 2, nx + 2), bool)
    padded[1:-1, 1:-1] = free
    moves = []
    for dy, dx, cost in NEIGHBOURS:
        target_free = padded[1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx]
        ok = free & target_free
        if dy and dx:  # no corner cutting: both orthogonal cells must be free too
            ok &= padded[1 + dy : 1 + dy + ny, 1 : 1 + nx] & padded[1 : 1 + ny, 1 + dx : 1 + dx + nx]
        moves.append((dy, dx, cost, ok))
    return moves


def geodesic_field(grid: OccupancyGrid, goal_xy) -> np.ndarray:
    """Shortest-path distance (metres) from every cell to the goal's cell; inf where no path.

    Vectorised Bellman-Ford relaxation over the whole grid (converges to the exact 8-connected
    Dijkstra distances; a few dozen numpy sweeps instead of a Python priority queue)."""
    free = grid.free
    dist = np.full(free.shape, np.inf)
    gy, gx = grid.to_cell(goal_xy)
    if not free[gy, gx]:
        return dist.astype(np.float32)
    dist[gy, gx] = 0.0
    moves = _neighbour_moves(free)
    ny, nx = free.shape
    while True:
        new = dist.copy()
        padded = np.full((ny + 2, nx + 2), np.inf)
        padded[1:-1, 1:-1] = dist
        for dy, dx, cost, ok in moves:
            via = padded[1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx] + cost
            np.minimum(new, np.where(ok, via, np.inf), out=new)
        if np.array_equal(new, dist):
            break
        dist = new
    return (dist * grid.cell_m).astype(np.float32)


def descend(grid: OccupancyGrid, field: np.ndarray, start_xy) -> np.ndarray:
    """Cell-centre path (K, 2) from start down the field to its goal (steepest descent)."""
    iy, ix = grid.to_cell(start_xy)
    if not np.isfinite(field[iy, ix]):
        raise ValueError(f"start {tuple(start_xy)} cannot reach the field's goal")
    moves = _neighbour_moves(grid.free)
    cells = [(iy, ix)]
    step_m = [cost * grid.cell_m for _, _, cost, _ in moves]
    while field[iy, ix] > 0:
        # The shortest-path parent: the neighbour minimising step cost + its distance.
        best, best_cell = np.inf, None
        for (dy, dx, _, ok), step in zip(moves, step_m):
            ny_, nx_ = iy + dy, ix + dx
            if ok[iy, ix] and field[ny_, nx_] < field[iy, ix] and field[ny_, nx_] + step < best:
                best, best_cell = field[ny_, nx_] + step, (ny_, nx_)
        if best_cell is None:  # cannot happen on an exact field; guard against a corrupt one
            raise RuntimeError("geodesic field has a local minimum away from its goal")
        iy, ix = best_cell
        cells.append(best_cell)
    return grid.to_world(np.asarray(cells))


def astar(grid: OccupancyGrid, start_xy, goal_xy) -> np.ndarray | None:
    """A* over the 8-connected grid (octile heuristic); cell-centre path (K, 2) or None."""
    start, goal = grid.to_cell(start_xy), grid.to_cell(goal_xy)
    if not (grid.free[start] and grid.free[goal]):
        return None
    moves = _neighbour_moves(grid.free)

    def h(c):
        dy, dx = abs(c[0] - goal[0]), abs(c[1] - goal[1])
        return (SQRT2 - 1) * min(dy, dx) + max(dy, dx)

    g = {start: 0.0}
    parent = {start: None}
    heap = [(h(start), 0.0, start)]
    closed = set()
    while heap:
        _, gc, c = heapq.heappop(heap)
        if c in closed:
            continue
        if c == goal:
            path = []
            while c is not None:
                path.append(c)
                c = parent[c]
            return grid.to_world(np.asarray(path[::-1]))
        closed.add(c)
        for dy, dx, cost, ok in moves:
            if not ok[c]:
                continue
            n = (c[0] + dy, c[1] + dx)
            ng = gc + cost
            if ng < g.get(n, math.inf):
                g[n] = ng
                parent[n] = c
                heapq.heappush(heap, (ng + h(n), ng, n))
    return None


def path_length(path_xy: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(path_xy, axis=0), axis=-1).sum())


def line_of_sight(grid: OccupancyGrid, a, b) -> bool:
    """Whether every point of the segment a-b lies in free cells (sampled at cell_m / 4)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    n = max(2, int(math.ceil(np.linalg.norm(b - a) / (grid.cell_m / 4))) + 1)
    pts = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
    ix = np.floor((pts[:, 0] - grid.origin[0]) / grid.cell_m).astype(int)
    iy = np.floor((pts[:, 1] - grid.origin[1]) / grid.cell_m).astype(int)
    ny, nx = grid.shape
    if (ix < 0).any() or (iy < 0).any() or (ix >= nx).any() or (iy >= ny).any():
        return False
    return bool(grid.free[iy, ix].all())


def smooth_path(grid: OccupancyGrid, path_xy: np.ndarray) -> np.ndarray:
    """String pulling: from each kept waypoint, extend the straight line along the path for as
    long as it stays in free space; keep the last point it reached. Linear in path length."""
    path_xy = np.asarray(path_xy, np.float64)
    if len(path_xy) <= 2:
        return path_xy
    out = [path_xy[0]]
    anchor, j = 0, 1
    while j < len(path_xy) - 1:
        if line_of_sight(grid, path_xy[anchor], path_xy[j + 1]):
            j += 1
            continue
        out.append(path_xy[j])
        anchor, j = j, j + 1
    out.append(path_xy[-1])
    return np.asarray(out)


def reachable_mask(grid: OccupancyGrid, seed_xy) -> np.ndarray:
    """Cells connected to the seed point's cell."""
    return np.isfinite(geodesic_field(grid, seed_xy))


def largest_component(grid: OccupancyGrid) -> np.ndarray:
    """Mask of the largest 8-connected free region (the apartment's navigable floor)."""
    remaining = grid.free.copy()
    best = np.zeros_like(remaining)
    while remaining.any():
        iy, ix = np.argwhere(remaining)[0]
        comp = reachable_mask(grid, grid.to_world(np.array([[iy, ix]]))[0])
        if comp.sum() > best.sum():
            best = comp
        remaining &= ~comp
        if best.sum() >= remaining.sum():
            break
    return best


def sample_field(field: np.ndarray, grid: OccupancyGrid, xy) -> float:
    """Field value at the cell holding xy, in metres (inf if that cell is unreachable)."""
    return float(field[grid.to_cell(xy)])
