"""The paper's scripted Table 2 baselines, and our oracle object-goal planner, as Agents.

Each acts for one environment and is jittable. The random agent sees nothing (an
observation-only Agent); the others are StateAgents: they read the brax state (robot pose in
`pipeline_state.qpos`, the observation keys they declare, the episode index in `info`) and the
env's episode bank through a closure; every such read is named in the agent's `privileged`. Data flow: state -> target direction (world, unit) -> `steer` -> action
(v_lin, v_ang) in [-1, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from conav_jax.geometry import to_world, wrap_angle
from conav_jax.nav.planning import cell_centres, descent_chain, field_value
from conav_jax.envs.agents.base import (
    CANDIDATE_GOAL_POINTS,
    ORACLE_GOAL_CATEGORY,
    ORACLE_GOAL_POINT,
    ORACLE_MAP,
    ORACLE_MOVES,
    Agent,
    StateAgent,
)
from conav_jax.envs.mjcf import UD


@dataclass(frozen=True)
class BaselineConfig:
    """Tunable numbers of the heuristic baselines (seconds, metres, radians)."""

    # Steering: the heading error is closed over this time at most, so the robot turns at full
    # rate only for errors above w_max * turn_time_s and does not overshoot small ones.
    turn_time_s: float = 0.2
    # Above this heading error the robot turns in place; below it drives at speed * cos(error).
    max_drive_error_rad: float = math.pi / 3
    # Path following: aim at the farthest of the next path_lookahead_cells path cells reachable
    # in a straight line with clearance_margin_m to spare (checked at clearance_samples points).
    path_lookahead_cells: int = 10
    clearance_margin_m: float = 0.05
    clearance_samples: int = 8
    # Pioneer: extrapolate the human's motion this far ahead; below the minimum speed the human
    # counts as standing still and the pioneer keeps its previous target (or waits if none).
    pioneer_horizon_s: float = 2.0  # 2 s and 3 s tie on the tiny train split; 5 s and 8 s do worse
    pioneer_min_speed_mps: float = 0.2
    # Follower: trail the human's path this far behind them; full speed when the human is
    # farther than follow_slow_m, slowing linearly to a stop at follow_distance_m; nearer, it
    # reverses, at full speed once follow_back_off_m inside it (a human walking at the robot
    # closes 0.12 m a step). Its path lookahead is path_lookahead_cells trail points
    # follow_stride_steps apart.
    follow_distance_m: float = 1.0
    follow_slow_m: float = 2.0
    follow_back_off_m: float = 0.25
    follow_stride_steps: int = 2  # spacing (env steps) of the trail points the follower aims at


def steer(pose: jax.Array, direction: jax.Array, speed: jax.Array, env, cfg: BaselineConfig) -> jax.Array:
    """Action (2,) that turns the robot at pose (x, y, yaw) toward the unit world `direction`
    (2,) and drives at `speed` (fraction of v_max) once roughly facing it; zero for a zero
    direction (nothing to do)."""
    task = env.task
    err = wrap_angle(jnp.arctan2(direction[1], direction[0]) - pose[2])
    w = jnp.clip(err / (cfg.turn_time_s * task.w_max_radps), -1.0, 1.0)
    forward = jnp.where(jnp.abs(err) < cfg.max_drive_error_rad, jnp.cos(err), 0.0)
    active = jnp.linalg.norm(direction) > 1e-6
    return jnp.where(active, jnp.stack([speed * forward, w]), 0.0)


def _clearance(env, scene: jax.Array, p: jax.Array) -> jax.Array:
    """Distance (m) from points p (..., 2) to the nearest blocking box footprint of `scene`."""
    b = env.bank_view
    c = (b.col_lo[scene, :, :2] + b.col_hi[scene, :, :2]) / 2.0
    h = (b.col_hi[scene, :, :2] - b.col_lo[scene, :, :2]) / 2.0
    gap = jnp.maximum(jnp.abs(p[..., None, :] - c) - h, 0.0)
    return jnp.min(jnp.where(b.col_valid[scene], jnp.linalg.norm(gap, axis=-1), jnp.inf), axis=-1)


def _pursue(env, cfg: BaselineConfig, scene: jax.Array, xy: jax.Array, points: jax.Array) -> jax.Array:
    """Unit direction (2,) from xy to the farthest of the candidate points (L, 2) (a path ahead,
    nearest first) whose straight segment keeps the robot's body clear of every blocking box:
    clearance at least robot radius + margin, or no less than it is now when the robot already
    touches something (so it may back away). Falls back to the first point; zero if there is
    nowhere to go. This string-pulling keeps a robot from cutting corners into walls, where
    contact friction would pin it."""
    s = jnp.linspace(0.0, 1.0, cfg.clearance_samples)[1:, None, None]
    seg = xy + s * (points - xy)  # (S-1, L, 2)
    need = jnp.minimum(env.task.robot_radius_m + cfg.clearance_margin_m, _clearance(env, scene, xy) - 1e-3)
    ok = jnp.all(_clearance(env, scene, seg) >= need, axis=0)  # (L,)
    moved = jnp.linalg.norm(points - xy, axis=-1) > 1e-3
    ok = ok & moved
    idx = jnp.where(jnp.any(ok), jnp.max(jnp.where(ok, jnp.arange(points.shape[0]), -1)), 0)
    delta = points[idx] - xy
    norm = jnp.linalg.norm(delta)
    return jnp.where(norm > 1e-3, delta / jnp.maximum(norm, 1e-3), 0.0)


def _field_dir(env, cfg: BaselineConfig, scene: jax.Array, k: jax.Array, xy: jax.Array) -> jax.Array:
    """Unit direction (2,) along field k of `scene` from xy (the oracle pathfinder); zero when
    k < 0 (no target)."""
    b = env.bank_view
    cells = descent_chain(b.fields[scene, jnp.maximum(k, 0)], b.field_origin[scene], b.cell_m, xy, cfg.path_lookahead_cells)
    chain = cell_centres(b.field_origin[scene], b.cell_m, cells)
    return jnp.where(k >= 0, _pursue(env, cfg, scene, xy, chain), 0.0)


# -- baselines ---------------------------------------------------------------------------------


def random_agent(env) -> Agent:
    """Uniform actions in [-1, 1]^2 from the step key."""

    def act(carry, obs, key):
        return carry, jax.random.uniform(key, (2,), minval=-1.0, maxval=1.0)

    return Agent("Random Agent", lambda key, obs: (), act, reads=(), name="random")


def _pioneer_target(env, cfg: BaselineConfig, state, carry) -> jax.Array:
    """The pioneer's target: the scene object standing point nearest to where the human will be
    in `pioneer_horizon_s` (velocity from the observed `human_history`, 8 past positions in the
    robot frame); while the human stands still it keeps its previous target (`carry`, -1: none):
    extrapolating a standing human points at the human itself. -> field index (int32)."""
    b, dt = env.bank_view, env.task.control_dt_s
    n_hist = env.config.human_history_steps
    pose = state.pipeline_state.qpos
    scene = b.scene_index[state.info["episode"]]
    hist = to_world(state.obs["human_history"], pose)  # (n_hist, 2), oldest first
    vel = (hist[-1] - hist[0]) / ((n_hist - 1) * dt)
    waypoint = hist[-1] + vel * cfg.pioneer_horizon_s
    gap = jnp.linalg.norm(b.field_stand[scene, :, :2] - waypoint, axis=-1)
    gap = jnp.where(b.field_category[scene] >= 0, gap, jnp.inf)
    moving = jnp.linalg.norm(vel) >= cfg.pioneer_min_speed_mps
    return jnp.where(moving, jnp.argmin(gap).astype(jnp.int32), carry)


def _check_history(env) -> None:
    if env.config.human_history_steps < 2:
        raise ValueError("the pioneer needs human_history_steps >= 2 to estimate the human's velocity")


def pioneer_agent(env, cfg: BaselineConfig | None = None) -> StateAgent:
    """The paper's pioneer: the next waypoint from the human's current orientation and speed,
    and the robot translated to it by the oracle pathfinder.

    The waypoint is where the human will be in `pioneer_horizon_s`; the target is the scene
    object standing point nearest it (_pioneer_target), and the robot is put at that standing
    pose at once (a pose action: ConavEnv.step_to_pose), every step the target holds: privileged, it
    never drives, and contacts at the poses it is put at count as any other. While the human
    has not moved it stays where it is. Carry: the target field index (int32, -1 none)."""
    cfg = cfg or BaselineConfig()
    _check_history(env)
    b = env.bank_view

    def act(state, carry, key):
        del key
        k = _pioneer_target(env, cfg, state, carry)
        scene = b.scene_index[state.info["episode"]]
        return jnp.where(k >= 0, b.field_stand[scene, jnp.maximum(k, 0)], state.pipeline_state.qpos), k

    return StateAgent("pioneer", lambda key, state: jnp.int32(-1), act, title="Pioneer Agent",
                      privileged=(CANDIDATE_GOAL_POINTS, ORACLE_MOVES), reads=("human_history",), action_size=3)


def pioneer_drive_agent(env, cfg: BaselineConfig | None = None) -> StateAgent:
    """The pioneer that drives: the same target (_pioneer_target), reached by descending its
    geodesic field at full speed (the oracle map), so it obeys walls and speed limits; it waits
    (zero action) until the human first moves. Carry: the target field index (int32, -1 none)."""
    cfg = cfg or BaselineConfig()
    _check_history(env)
    b = env.bank_view

    def act(state, carry, key):
        del key
        pose = state.pipeline_state.qpos
        scene = b.scene_index[state.info["episode"]]
        k = _pioneer_target(env, cfg, state, carry)
        return steer(pose, _field_dir(env, cfg, scene, k, pose[:2]), 1.0, env, cfg), k

    return StateAgent("pioneer-drive", lambda key, state: jnp.int32(-1), act, title="Pioneer Agent, driving",
                      privileged=(CANDIDATE_GOAL_POINTS, ORACLE_MAP), reads=("human_history",))


def follower_agent(env, cfg: BaselineConfig | None = None) -> StateAgent:
    """Human follower, after Habitat 3.0's social-navigation agent: keep ~1 m behind the human.

    Pursues the human's own path (the episode's root positions up to now: what `human_pos`
    shows the robot step by step), so it
    goes around furniture the way the human did: the trail ends at the latest past position at
    least `follow_distance_m` from the human (the human itself if they have not moved that far),
    and the robot aims along the trail from the trail point nearest to it. Full speed while the
    human is farther than `follow_slow_m`, slowing to a stop at `follow_distance_m`; closer than
    that it faces the human and backs away, at full speed `follow_back_off_m` inside it. Carry: none.
    """
    cfg = cfg or BaselineConfig()
    b = env.bank_view
    steps = jnp.arange(b.max_steps)
    ahead = cfg.follow_stride_steps * jnp.arange(1, cfg.path_lookahead_cells + 1)

    def act(state, carry, key):
        del key
        pose = state.pipeline_state.qpos
        xy, episode = pose[:2], state.info["episode"]
        t = jnp.minimum(state.pipeline_state.userdata[UD["t"]].astype(jnp.int32), b.max_steps - 1)
        path = b.root_xy[episode]  # (T, 2)
        human = path[t]
        behind = (steps <= t) & (jnp.linalg.norm(path - human, axis=-1) >= cfg.follow_distance_m)
        trail = jnp.where(jnp.any(behind), jnp.max(jnp.where(behind, steps, -1)), t)
        nearest = jnp.argmin(jnp.where(steps <= trail, jnp.linalg.norm(path - xy, axis=-1), jnp.inf))
        points = path[jnp.minimum(nearest + ahead, trail)]
        to_human = jnp.linalg.norm(human - xy)
        close = to_human <= cfg.follow_distance_m
        # Negative inside the follow distance: it backs away, still facing the human.
        gap = to_human - cfg.follow_distance_m
        speed = jnp.clip(gap / jnp.where(close, cfg.follow_back_off_m, cfg.follow_slow_m - cfg.follow_distance_m), -1.0, 1.0)
        face = (human - xy) / jnp.maximum(to_human, 1e-6)
        direction = jnp.where(close, face, _pursue(env, cfg, b.scene_index[episode], xy, points))
        return steer(pose, direction, speed, env, cfg), carry

    return StateAgent("follower", lambda key, state: (), act, title="Human-following Agent", privileged=(ORACLE_MAP,))


def nearest_instance(env, scene: jax.Array, category: jax.Array, xy: jax.Array) -> jax.Array:
    """The field index (int32) of the object of `category` in `scene` whose standing point is
    nearest to xy by geodesic distance (the smallest field value there)."""
    b = env.bank_view
    values = jax.vmap(lambda f: field_value(f, b.field_origin[scene], b.cell_m, xy))(b.fields[scene])
    values = jnp.where(b.field_category[scene] == category, values, jnp.inf)
    return jnp.argmin(values).astype(jnp.int32)


def objectgoal_planner_agent(env, cfg: BaselineConfig | None = None, replan: bool = False) -> StateAgent:
    """An object-goal planner with the oracle goal category and the oracle map: privileged, ours,
    not the paper's learned object-goal agent (envs.agents.goalnav: it reads only its camera,
    pose and the category, and imitates this planner).

    At the start it picks, among the scene's objects of the episode's object-B category, the
    one whose standing point is nearest by geodesic distance from the robot's start (the
    smallest field value there), and descends that field at full speed, ignoring the human.
    With several instances it can pick the wrong one, as a real object-goal agent would.
    With `replan` it picks the nearest instance again from wherever the robot is, every step:
    the same path from the start (descending a field keeps its instance the nearest), and the
    teacher's answer in any state a learner's own rollout reaches (DAgger).
    Carry: the chosen field index (int32).
    """
    cfg = cfg or BaselineConfig()
    b = env.bank_view

    def init(key, state):
        del key
        episode = state.info["episode"]
        return nearest_instance(env, b.scene_index[episode], b.object_b[episode], b.robot_start[episode, :2])

    def act(state, carry, key):
        del key
        pose = state.pipeline_state.qpos
        episode = state.info["episode"]
        scene = b.scene_index[episode]
        if replan:
            carry = nearest_instance(env, scene, b.object_b[episode], pose[:2])
        return steer(pose, _field_dir(env, cfg, scene, carry, pose[:2]), 1.0, env, cfg), carry

    return StateAgent("objectgoal-planner", init, act, title="Object-goal planner",
                      privileged=(ORACLE_GOAL_CATEGORY, ORACLE_MAP))


def goal_planner_agent(env, cfg: BaselineConfig | None = None) -> StateAgent:
    """The geodesic planner to the episode's goal itself (its standing point for activity B):
    descends the goal's field at full speed, ignoring the human. The image-goal agent's
    teacher (envs.agents.goalnav): where the goal image was taken is where it leads. Carry: none."""
    cfg = cfg or BaselineConfig()
    b = env.bank_view

    def act(state, carry, key):
        del key
        pose = state.pipeline_state.qpos
        episode = state.info["episode"]
        return steer(pose, _field_dir(env, cfg, b.scene_index[episode], b.field_b[episode], pose[:2]), 1.0, env, cfg), carry

    return StateAgent("goal-planner", lambda key, state: (), act, title="Goal planner",
                      privileged=(ORACLE_GOAL_POINT, ORACLE_MAP))
