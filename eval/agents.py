"""Baseline agents of the paper's Table 2 as `envs.rollout.Agent`s, and the registry of all agents.

Each baseline acts for one environment and is jittable: it reads the brax state (robot pose in
`pipeline_state.qpos`, observations, the episode index in `info`) and, where it is an oracle, the
env's episode bank through a closure. Data flow: state -> target direction (world, unit) ->
`steer` -> action (v_lin, v_ang) in [-1, 1]. Learned agents (expert, conav, ppo) live in other
modules and are imported only when asked for, so this registry works before they exist.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from conav_jax.planning import field_cell, field_value
from envs.mjcf import UD
from envs.rollout import Agent


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


# The 8 grid neighbours (dy, dx) a descent chain steps to.
_NEIGHBOURS = np.array([(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)], np.int32)


def _wrap(a: jax.Array) -> jax.Array:
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))


def steer(pose: jax.Array, direction: jax.Array, speed: jax.Array, env, cfg: BaselineConfig) -> jax.Array:
    """Action (2,) that turns the robot at pose (x, y, yaw) toward the unit world `direction`
    (2,) and drives at `speed` (fraction of v_max) once roughly facing it; zero for a zero
    direction (nothing to do)."""
    task = env.task
    err = _wrap(jnp.arctan2(direction[1], direction[0]) - pose[2])
    w = jnp.clip(err / (cfg.turn_time_s * task.w_max_radps), -1.0, 1.0)
    forward = jnp.where(jnp.abs(err) < cfg.max_drive_error_rad, jnp.cos(err), 0.0)
    active = jnp.linalg.norm(direction) > 1e-6
    return jnp.where(active, jnp.stack([speed * forward, w]), 0.0)


def _descent_chain(field: jax.Array, origin: jax.Array, cell_m: float, xy: jax.Array, n: int) -> jax.Array:
    """World centres (n, 2) of the next n cells down the field's steepest-descent chain from xy
    (8-neighbour moves, each to the neighbour minimising value + step length, as
    planning.field_direction walks it); the chain repeats its last cell at a minimum."""
    ny, nx = field.shape
    f = field.astype(jnp.float32)
    offsets = jnp.asarray(_NEIGHBOURS)
    lengths = jnp.asarray(np.sqrt((_NEIGHBOURS**2).sum(-1)), jnp.float32) * cell_m

    def downhill(cell, _):
        iy, ix = cell
        cy = jnp.clip(iy + offsets[:, 0], 0, ny - 1)
        cx = jnp.clip(ix + offsets[:, 1], 0, nx - 1)
        k = jnp.argmin(f[cy, cx] + lengths)
        better = f[cy[k], cx[k]] < f[iy, ix]
        nxt = (jnp.where(better, cy[k], iy), jnp.where(better, cx[k], ix))
        return nxt, jnp.stack([origin[0] + (nxt[1] + 0.5) * cell_m, origin[1] + (nxt[0] + 0.5) * cell_m])

    _, centres = jax.lax.scan(downhill, field_cell(field, origin, cell_m, xy), None, length=n)
    return centres


def _clearance(env, scene: jax.Array, p: jax.Array) -> jax.Array:
    """Distance (m) from points p (..., 2) to the nearest blocking box footprint of `scene`."""
    b = env.bank
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
    b = env.bank
    chain = _descent_chain(b.fields[scene, jnp.maximum(k, 0)], b.field_origin[scene], b.cell_m, xy, cfg.path_lookahead_cells)
    return jnp.where(k >= 0, _pursue(env, cfg, scene, xy, chain), 0.0)


def _to_world(p_robot: jax.Array, pose: jax.Array) -> jax.Array:
    """Points (..., 2) in the robot frame -> world, for the robot at pose (x, y, yaw)."""
    c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
    x, y = p_robot[..., 0], p_robot[..., 1]
    return jnp.stack([c * x - s * y, s * x + c * y], axis=-1) + pose[:2]


# -- baselines ---------------------------------------------------------------------------------


def random_agent(env) -> Agent:
    """Uniform actions in [-1, 1]^2 from the step key."""

    def act(state, carry, key):
        return jax.random.uniform(key, (2,), minval=-1.0, maxval=1.0), carry

    return Agent("random", lambda key, episode: (), act)


def pioneer_agent(env, cfg: BaselineConfig | None = None) -> Agent:
    """The paper's pioneer: where will the human be in a few seconds, and go there first.

    Our reading of "the next waypoint ... based on its orientation and speed, and a ground-truth
    pathfinder": the human's velocity is estimated from the observed `human_history` (8 past
    positions, robot frame) and extrapolated `pioneer_horizon_s` ahead to a waypoint; the target
    is the scene object standing point nearest that waypoint (straight-line distance), and the
    oracle pathfinder is that point's geodesic field, descended at full speed. The paper's
    pathfinder teleports the robot to the waypoint; ours drives, so it obeys walls and speed
    limits. While the human stands still the pioneer keeps its last target, or waits (zero
    action) if it never had one: extrapolating a standing human points at the human itself.
    Carry: the target field index (int32, -1 none).
    """
    cfg = cfg or BaselineConfig()
    b, dt = env.bank, env.task.control_dt_s
    n_hist = env.config.human_history_steps
    if n_hist < 2:
        raise ValueError("the pioneer needs human_history_steps >= 2 to estimate the human's velocity")

    def act(state, carry, key):
        del key
        pose = state.pipeline_state.qpos
        scene = b.scene_index[state.info["episode"]]
        hist = _to_world(state.obs["human_history"], pose)  # (n_hist, 2), oldest first
        vel = (hist[-1] - hist[0]) / ((n_hist - 1) * dt)
        waypoint = hist[-1] + vel * cfg.pioneer_horizon_s
        gap = jnp.linalg.norm(b.field_stand[scene, :, :2] - waypoint, axis=-1)
        gap = jnp.where(b.field_category[scene] >= 0, gap, jnp.inf)
        moving = jnp.linalg.norm(vel) >= cfg.pioneer_min_speed_mps
        k = jnp.where(moving, jnp.argmin(gap).astype(jnp.int32), carry)
        return steer(pose, _field_dir(env, cfg, scene, k, pose[:2]), 1.0, env, cfg), k

    return Agent("pioneer", lambda key, episode: jnp.int32(-1), act)


def follower_agent(env, cfg: BaselineConfig | None = None) -> Agent:
    """Human follower, after Habitat 3.0's social-navigation agent: keep ~1 m behind the human.

    Pursues the human's own path (privileged: the episode's root positions up to now), so it
    goes around furniture the way the human did: the trail ends at the latest past position at
    least `follow_distance_m` from the human (the human itself if they have not moved that far),
    and the robot aims along the trail from the trail point nearest to it. Full speed while the
    human is farther than `follow_slow_m`, slowing to a stop at `follow_distance_m`; closer than
    that it faces the human and backs away, at full speed `follow_back_off_m` inside it. Carry: none.
    """
    cfg = cfg or BaselineConfig()
    b = env.bank
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

    return Agent("follower", lambda key, episode: (), act)


def objectgoal_agent(env, cfg: BaselineConfig | None = None) -> Agent:
    """Object-goal navigation with the oracle goal category (the paper's Table 2 row marked †).

    At the start it picks, among the scene's objects of the episode's object-B category, the
    one whose standing point is nearest by geodesic distance from the robot's start (the
    smallest field value there), and descends that field at full speed, ignoring the human.
    With several instances it can pick the wrong one, as a real object-goal agent would.
    Carry: the chosen field index (int32).
    """
    cfg = cfg or BaselineConfig()
    b = env.bank

    def init(key, episode):
        del key
        scene = b.scene_index[episode]
        xy = b.robot_start[episode, :2]
        values = jax.vmap(lambda f: field_value(f, b.field_origin[scene], b.cell_m, xy))(b.fields[scene])
        values = jnp.where(b.field_category[scene] == b.object_b[episode], values, jnp.inf)
        return jnp.argmin(values).astype(jnp.int32)

    def act(state, carry, key):
        del key
        pose = state.pipeline_state.qpos
        scene = b.scene_index[state.info["episode"]]
        return steer(pose, _field_dir(env, cfg, scene, carry, pose[:2]), 1.0, env, cfg), carry

    return Agent("objectgoal", init, act)


# -- registry ----------------------------------------------------------------------------------


class AgentSpec(NamedTuple):
    """How to build one agent. `module`: the module it needs (None: always present);
    `needs_checkpoint`: it loads a run directory."""

    title: str  # the row name in reports, after the paper's Table 2
    build: Callable[..., Agent]  # (env, checkpoint, **kwargs) -> Agent
    module: str | None = None
    needs_checkpoint: bool = False
    takes_predictors: bool = False  # accepts intention_run / trajectory_run keyword arguments


def _lazy(module: str, function: str, with_checkpoint: bool) -> Callable[..., Agent]:
    def build(env, checkpoint, **kwargs):
        fn = getattr(importlib.import_module(module), function, None)
        if fn is None:
            raise ValueError(f"{module} has no {function}(); the agent cannot be built")
        return fn(env, checkpoint, **kwargs) if with_checkpoint else fn(env, **kwargs)

    return build


AGENTS: dict[str, AgentSpec] = {
    "random": AgentSpec("Random Agent", lambda env, ckpt, **kw: random_agent(env, **kw)),
    "pioneer": AgentSpec("Pioneer Agent (Oracle Pathfinder)", lambda env, ckpt, **kw: pioneer_agent(env, **kw)),
    "follower": AgentSpec("Human-following Agent", lambda env, ckpt, **kw: follower_agent(env, **kw)),
    "objectgoal": AgentSpec("Object-goal Agent (Oracle Goal Object)", lambda env, ckpt, **kw: objectgoal_agent(env, **kw)),
    "expert": AgentSpec("Expert (imitation teacher)", _lazy("train.imitation", "expert_agent", False), "train.imitation"),
    "conav": AgentSpec("CoNav Agent (Ours)", _lazy("eval.learned", "policy_agent", True), "eval.learned", True, True),
    "ppo": AgentSpec("PPO Agent", _lazy("train.ppo", "ppo_agent", True), "train.ppo", True),
}


def _module_exists(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:  # the parent package itself is missing
        return False


def check_agent(name: str, checkpoint: str | Path | None = None) -> AgentSpec:
    """The spec of agent `name`, after checking it can be built; ValueError otherwise.

    Cheap (no env, no compile, no heavy import): sweeps call it for every agent first."""
    spec = AGENTS.get(name)
    if spec is None:
        raise ValueError(f"unknown agent {name!r}; choose from {', '.join(AGENTS)}")
    if spec.module is not None and not _module_exists(spec.module):
        raise ValueError(f"agent {name!r} is not available yet: its module {spec.module} does not exist")
    if spec.needs_checkpoint:
        if checkpoint is None:
            raise ValueError(f"agent {name!r} needs a trained run: pass --checkpoint RUN_DIR")
        if not Path(checkpoint).is_dir():
            raise ValueError(f"checkpoint run directory not found for agent {name!r}: {checkpoint}")
    return spec


def make_agent(name: str, env, checkpoint: str | Path | None = None, **kwargs: Any) -> Agent:
    """Build agent `name` for `env`. `checkpoint`: the run directory of a learned agent (ignored
    by the others); `kwargs` go to the agent's constructor (e.g. `cfg=BaselineConfig(...)`)."""
    spec = check_agent(name, checkpoint)
    return spec.build(env, None if checkpoint is None else str(checkpoint), **kwargs)
