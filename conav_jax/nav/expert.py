"""The heuristic expert that labels imitation data (paper sec. 4.2): approach, observe, go.

Pure jittable functions for ONE robot (vmap for batches): robot pose, the human's current and
upcoming positions and the scene's grids (geodesic fields, wall clearance) in; an action
`(v_lin, v_ang)` in [-1, 1] and the next phase carry out. train.imitation.expert_agent feeds it
from the simulator's episode arrays.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage

from conav_jax.geometry import unit, wrap_angle
from conav_jax.nav.planning import cell_centres, descent_chain, field_cell, field_value

# Phases of the expert's plan, in order.
APPROACH, OBSERVE, GO = 0, 1, 2


@dataclass(frozen=True)
class ExpertConfig:
    """Every number of the expert. Human distances are metres from the robot's centre to the
    human's root (pelvis on the floor); the body reaches ~0.3 m beyond it, the robot 0.3 m."""

    approach_m: float = 1.5  # approach the human until this close, then observe
    approach_max_steps: int = 40  # stop approaching after this many steps (a walking human outpaces us)
    observe_steps: int = 10  # K: steps standing still, facing the human
    heading_gain: float = 2.0  # angular action per radian of heading error, clipped to [-1, 1]
    # Forward speed falls linearly with the heading error, to zero at this error: the robot
    # turns in place rather than pushing sideways against a wall it cannot then turn away from.
    drive_error_rad: float = 1.2
    lookahead_cells: int = 12  # the heading looks this many cells down the geodesic path
    # Walls: within wall_margin_m of the robot-inflated obstacles (i.e. of touching one), the
    # heading bends away from them by up to wall_gain (a unit vector of that weight is added).
    wall_margin_m: float = 0.3
    wall_gain: float = 0.5
    # Human positions the clearance rules consider, in steps from now (0.1 s each): the expert
    # is privileged and sees where the human is about to walk, so it yields before contact.
    human_lookahead_steps: tuple[int, ...] = (0, 5, 10, 15)
    # Yield: when that predicted path passes closer than yield_m, move away from it (in reverse
    # if quicker) at yield_speed (of v_max). Below the 1 m success radius, so the robot can
    # still reach a goal where the human already stands.
    yield_m: float = 0.8
    yield_speed: float = 1.0
    walking_m: float = 0.2  # the human counts as walking if the predicted path is longer than this
    # Sidestep (goal phase): a human ahead on the path, closer than avoid_m and less than
    # corridor_m off the path line, bends the heading sideways by up to sidestep_gain...
    avoid_m: float = 2.5
    corridor_m: float = 1.0
    sidestep_gain: float = 1.5
    # ...unless the human is no nearer than the goal (less this margin): the goal is the human's
    # standing spot, so dodging a human who stands there would only delay the arrival.
    pass_margin_m: float = 1.0
    # Forward speed falls linearly from full at slow_m to zero at stop_m for a human ahead.
    slow_m: float = 1.5
    stop_m: float = 0.7

    def __post_init__(self):
        # A tuple, whatever sequence was given: the config is a static (hashed) jit argument.
        object.__setattr__(self, "human_lookahead_steps", tuple(int(s) for s in self.human_lookahead_steps))
        if not 0.0 < self.stop_m < self.slow_m:
            raise ValueError("ExpertConfig needs 0 < stop_m < slow_m")
        if self.observe_steps < 0 or self.approach_max_steps < 0:
            raise ValueError("ExpertConfig step counts must be >= 0")
        if not self.human_lookahead_steps or self.human_lookahead_steps[0] != 0:
            raise ValueError("human_lookahead_steps must start with 0 (the human now)")


class ExpertMaps(NamedTuple):
    """One episode's grids (ny, nx), all on the same cells (origin (2,) world m of the corner)."""

    goal_field: jax.Array  # geodesic metres to the goal (activity B's spot)
    approach_field: jax.Array  # geodesic metres to activity A's spot (where the human starts)
    clearance: jax.Array  # signed metres to the nearest robot-blocked cell (clearance_map)
    origin: jax.Array


class ExpertCarry(NamedTuple):
    """The expert's memory: its phase (APPROACH/OBSERVE/GO, int32) and steps spent in it."""

    phase: jax.Array
    steps: jax.Array


def initial_carry() -> ExpertCarry:
    """The carry at an episode's start: approaching, no steps yet."""
    return ExpertCarry(jnp.int32(APPROACH), jnp.int32(0))


def clearance_map(free: np.ndarray, cell_m: float) -> np.ndarray:
    """Signed clearance (ny, nx) float32 metres of a robot occupancy grid (True = the robot's
    centre may be here): distance to the nearest blocked cell in free cells, minus the distance
    to the nearest free cell in blocked ones. Its gradient points away from walls everywhere."""
    free = np.asarray(free, bool)
    return ((ndimage.distance_transform_edt(free) - ndimage.distance_transform_edt(~free)) * cell_m).astype(np.float32)


def _cross(a: jax.Array, b: jax.Array) -> jax.Array:
    """z of a x b for 2-vectors (broadcasting): > 0 when b is left of a."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _drive(cfg: ExpertConfig, yaw: jax.Array, direction: jax.Array, speed: jax.Array, reversible: bool) -> jax.Array:
    """Action toward world `direction` (unit (2,); zero: stand still) at `speed` in [0, 1]:
    turn by the heading error, drive slower the larger it is. `reversible`: drive backwards
    when the direction is behind."""
    err = wrap_angle(jnp.arctan2(direction[1], direction[0]) - yaw)
    back = reversible & (jnp.cos(err) < 0.0)
    err = jnp.where(back, wrap_angle(err + jnp.pi), err)
    v = speed * jnp.clip(1.0 - jnp.abs(err) / cfg.drive_error_rad, 0.0, 1.0) * jnp.where(back, -1.0, 1.0)
    w = jnp.clip(cfg.heading_gain * err, -1.0, 1.0)
    return jnp.where(jnp.linalg.norm(direction) > 0.0, jnp.stack([v, w]), 0.0)


def _free_direction(
    field: jax.Array, clearance: jax.Array, origin: jax.Array, cell_m: float, xy: jax.Array, lookahead: int
) -> jax.Array:
    """Unit world direction (2,) along the geodesic path down `field`, through free cells only.

    The steepest-descent chain keeps to cells of positive clearance (planning.descent_chain, so
    it does not cut a door's corner into the jamb), runs `lookahead` cells, and the robot aims at the farthest chain cell it can reach in a straight
    line through free cells (string pulling: no 45-degree zig-zag). Zero at the goal."""
    start = field_cell(field, origin, cell_m, xy)
    start_blocked = clearance[start] <= 0.0
    chain = descent_chain(field, origin, cell_m, xy, lookahead, clearance)  # (lookahead, 2) (iy, ix)
    targets = cell_centres(origin, cell_m, chain)  # (lookahead, 2) world xy
    # Straight-line reachability of each chain cell, sampled every ~half cell.
    frac = (jnp.arange(2 * lookahead) + 1.0) / (2 * lookahead)
    pts = xy + frac[None, :, None] * (targets - xy)[:, None, :]  # (lookahead, samples, 2)
    cells = jax.vmap(jax.vmap(lambda p: field_cell(field, origin, cell_m, p)))(pts)
    seen = jnp.all(clearance[cells] > 0.0, axis=-1) | start_blocked
    j = jnp.where(seen.any(), lookahead - 1 - jnp.argmax(seen[::-1]), 0)
    moved = jnp.any(chain[j] != jnp.stack(start))
    return jnp.where(moved, unit(targets[j] - xy), 0.0)


def _wall_push(grid: jax.Array, origin: jax.Array, cell_m: float, xy: jax.Array) -> jax.Array:
    """Unit world direction (2,) of increasing clearance at xy (central differences)."""
    ny, nx = grid.shape
    iy, ix = field_cell(grid, origin, cell_m, xy)
    g = grid.astype(jnp.float32)
    dx = g[iy, jnp.minimum(ix + 1, nx - 1)] - g[iy, jnp.maximum(ix - 1, 0)]
    dy = g[jnp.minimum(iy + 1, ny - 1), ix] - g[jnp.maximum(iy - 1, 0), ix]
    return unit(jnp.stack([dx, dy]))


def _closest_on_path(points: jax.Array, xy: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(closest point (2,), distance) of xy to the polyline through points (L, 2)."""
    a = points[:-1] if points.shape[0] > 1 else points
    b = points[1:] if points.shape[0] > 1 else points
    d = b - a
    s = jnp.clip(jnp.sum((xy - a) * d, -1) / jnp.maximum(jnp.sum(d * d, -1), 1e-9), 0.0, 1.0)
    c = a + s[:, None] * d
    dist = jnp.linalg.norm(xy - c, axis=-1)
    k = jnp.argmin(dist)
    return c[k], dist[k]


def _next_phase(cfg: ExpertConfig, carry: ExpertCarry, human_dist_m: jax.Array) -> ExpertCarry:
    """Advance the plan: APPROACH -> OBSERVE when near the human (or after too long),
    OBSERVE -> GO after observe_steps (OBSERVE is skipped when that is 0)."""
    p, n = carry.phase, carry.steps
    to_observe = (p == APPROACH) & ((human_dist_m < cfg.approach_m) | (n >= cfg.approach_max_steps))
    to_go = (p == OBSERVE) & (n >= cfg.observe_steps)
    after_approach = OBSERVE if cfg.observe_steps > 0 else GO
    new = jnp.where(to_observe, after_approach, jnp.where(to_go, GO, p)).astype(jnp.int32)
    return ExpertCarry(new, jnp.where(new == p, n, 0).astype(jnp.int32))


def expert_action(
    cfg: ExpertConfig,
    maps: ExpertMaps,
    cell_m: float,
    robot_pose: jax.Array,
    human_xy: jax.Array,
    human_at_a: jax.Array,
    carry: ExpertCarry,
) -> tuple[jax.Array, ExpertCarry]:
    """One step of the expert for one robot.

    Args:
      cfg: ExpertConfig (static).
      maps: the episode's ExpertMaps; cell_m: their cell size (m, static).
      robot_pose: (3,) world (x m, y m, yaw rad).
      human_xy: (L, 2) world metres of the human's root now (row 0) and at the later steps of
        cfg.human_lookahead_steps.
      human_at_a: () bool, the human is still doing activity A (at its spot): approach along
        approach_field; afterwards the expert pursues the human in a straight line.
      carry: ExpertCarry from `initial_carry()` or the previous step.
    Returns:
      action (2,) = (v_lin, v_ang) in [-1, 1] (fractions of v_max, w_max), the new carry.
    """
    human_xy = jnp.asarray(human_xy, jnp.float32).reshape(-1, 2)
    xy, yaw = robot_pose[:2], robot_pose[2]
    rel = human_xy - xy  # (L, 2) robot -> human
    dist = jnp.linalg.norm(rel, axis=-1)
    carry = _next_phase(cfg, carry, dist[0])
    origin = maps.origin

    # Where the current phase leads.
    to_human = unit(rel[0])
    use_field = human_at_a & jnp.isfinite(field_value(maps.approach_field, origin, cell_m, xy))
    approach_dir = jnp.where(
        use_field, _free_direction(maps.approach_field, maps.clearance, origin, cell_m, xy, cfg.lookahead_cells), to_human
    )
    goal_dir = _free_direction(maps.goal_field, maps.clearance, origin, cell_m, xy, cfg.lookahead_cells)
    go = carry.phase == GO
    task_dir = jnp.where(go, goal_dir, approach_dir)

    # Sidestep a human ahead on the way (goal phase only: approaching heads for them on purpose).
    along = rel @ task_dir
    lateral = _cross(task_dir, rel)  # > 0: human left of the path
    goal_m = field_value(maps.goal_field, origin, cell_m, xy)
    in_way = (along > 0.0) & (jnp.abs(lateral) < cfg.corridor_m) & (dist < cfg.avoid_m)
    in_way &= go & (goal_m > dist + cfg.pass_margin_m)
    k = jnp.argmin(jnp.where(in_way, dist, jnp.inf))
    strength = jnp.clip((cfg.avoid_m - dist[k]) / (cfg.avoid_m - cfg.yield_m), 0.0, 1.0) * in_way[k]
    side = jnp.where(lateral[k] > 0.0, -1.0, 1.0)  # pass on the side away from the human
    left = jnp.stack([-task_dir[1], task_dir[0]])
    heading = task_dir + cfg.sidestep_gain * strength * side * left

    # Keep off walls; touching one, slide along it (a heading into it is useless).
    clear = field_value(maps.clearance, origin, cell_m, xy)
    normal = _wall_push(maps.clearance, origin, cell_m, xy)
    touching = clear <= 0.0

    def slide(d):
        into = touching & (d @ normal < 0.0)
        return jnp.where(into, unit(d - (d @ normal) * normal), d)

    wall = jnp.clip((cfg.wall_margin_m - clear) / cfg.wall_margin_m, 0.0, 1.0)
    heading = heading + cfg.wall_gain * wall * normal
    heading = jnp.where(jnp.linalg.norm(task_dir) > 0.0, slide(unit(heading)), 0.0)

    # Slow down for a human ahead on the chosen heading.
    ahead = (rel @ heading > 0.0) & (jnp.abs(_cross(heading, rel)) < cfg.corridor_m)
    slow = jnp.clip((dist - cfg.stop_m) / (cfg.slow_m - cfg.stop_m), 0.0, 1.0)
    speed = jnp.min(jnp.where(ahead, slow, 1.0))

    moving = _drive(cfg, yaw, heading, speed, False)
    observing = _drive(cfg, yaw, to_human, jnp.float32(0.0), False)  # turn to watch, stand still
    action = jnp.where(carry.phase == OBSERVE, observing, moving)

    # Yield: get off the human's path (their positions over the next ~1.5 s). From a walking
    # human step sideways out of their line (backing up along it only delays the contact), to
    # the roomier side when exactly on it; from a standing one, straight back.
    closest, gap = _closest_on_path(human_xy, xy)
    walk = human_xy[-1] - human_xy[0]
    line = unit(walk)
    off = xy - closest
    lateral = off - (off @ line) * line
    perp = jnp.stack([-line[1], line[0]])
    room = field_value(maps.clearance, origin, cell_m, xy + 0.5 * perp) - field_value(
        maps.clearance, origin, cell_m, xy - 0.5 * perp
    )
    sideways = jnp.where(jnp.linalg.norm(lateral) > 1e-3, unit(lateral), jnp.where(room >= 0.0, perp, -perp))
    back = jnp.where(jnp.linalg.norm(off) > 0.0, unit(off), -to_human)
    away = slide(jnp.where(jnp.linalg.norm(walk) > cfg.walking_m, sideways, back))
    yield_action = _drive(cfg, yaw, away, jnp.float32(cfg.yield_speed), True)
    action = jnp.where(gap < cfg.yield_m, yield_action, action)

    # Touching a wall, never drive into it: pressed against it the robot cannot turn (the
    # contact's friction beats the yaw servo), so it turns in place first.
    motion = jnp.sign(action[0]) * jnp.stack([jnp.cos(yaw), jnp.sin(yaw)])
    into_wall = touching & (motion @ normal < -0.1)
    action = action.at[0].set(jnp.where(into_wall, 0.0, action[0]))
    return action, carry._replace(steps=carry.steps + 1)
