"""The CoNav environment: a brax `Env` over MuJoCo MJX with a replayed humanoid.

`reset(rng)` draws an episode from the bank, `reset_to_episode(rng, index)` starts a given one
(evaluation visits every episode exactly once this way), `step(state, action)` applies
`(v_lin, v_ang)` in [-1, 1] for one control step (an oracle mover's pose goes through the separate,
privileged `step_to_pose`), and `observe(state, keys)` computes the observation keys asked for
(envs.observations). Everything that changes within an episode
lives in the MJX data (`pipeline_state`): the robot's joints, the humanoid's mocap poses, and the
step index and metric accumulators in `userdata` (layout: envs.mjcf.USERDATA_FIELDS). That is
what lets brax's AutoResetWrapper, which restores only `pipeline_state` and `obs`, restart an
episode correctly. `State.info["episode"]` is the bank index.

It subclasses `brax.envs.base.Env` rather than `PipelineEnv`: PipelineEnv holds one fixed
`sys` and steps it with brax's pipeline, while each CoNav episode needs its own scene geometry
in the MJX model and mocap poses set between substeps.

An episode ends when the human finishes activity B (`t_end`), or, with
`EnvConfig.end_at_reach`, when the robot first reaches the goal. After it ends further steps
leave the state unchanged, so a fixed-length `lax.scan` over a batch of episodes of different
lengths reads every episode's result at its end.

Physics runs on MJX's JAX implementation or on MuJoCo Warp (PhysicsConfig.impl). MuJoCo Warp's
contact buffer is one for all the worlds of a batch (not one per world), so it cannot be merged
per env with `jnp.where` as brax's AutoResetWrapper, the frozen ended episode and the rollout's
lane refill do. It is scratch, rewritten by every substep's collision pass: the State's data
holds the per-world fields only, and `_physics` hands MuJoCo Warp fresh buffers for the
substeps of a control step. With impl="jax" nothing is held back.
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State
from mujoco import mjx

from conav_jax.config import TaskConfig
from conav_jax.data.activities import NUM_ACTIVITIES
from conav_jax.data.categories import NUM_CATEGORIES
from conav_jax.data.episodes import EpisodeSplit, load_split
from conav_jax.geometry import to_frame, wrap_angle
from conav_jax.nav.planning import field_value
from conav_jax.envs import contact
from conav_jax.envs.bank import FLOOR_RGB_F, EpisodeBank, build_bank
from conav_jax.envs.config import EnvConfig, resolve_physics_impl, resolve_sensor_kind
from conav_jax.envs.humanoid import CAPSULE_RADII, capsule_colours, capsule_groups, capsule_poses, quat_z_to
from conav_jax.envs.observations import PRIVILEGED_KEYS, SENSOR_KEYS, observation
from conav_jax.envs.mjcf import (
    UD,
    GeomLayout,
    build_model,
    make_data,
    robot_body_id,
    servo_error_limits,
    warp_lost_contact_bits,
)
from conav_jax.envs.panorama import (
    SceneGeometry,
    caster_for,
    colourise,
    fast_depth_ids,
    front_view,
    reference_depth_ids,
    shade,
)

ROBOT_RGB = np.array([0.3, 0.3, 0.32], np.float32)

# MJX's JAX pipeline and the XLA sensor (the fast caster, the colouring) as jitted functions of
# their own, the sensor's config static: a program that calls them again (a rollout's scan, a
# second step, another program of an env of the same shapes) reuses their traced and batched
# jaxprs rather than tracing them anew, which is most of what building an env program costs.
# XLA inlines them: the compiled program is the one it would be without. MuJoCo Warp and the
# Pallas kernels are called as they are.
@jax.jit
def _mjx_step(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    return mjx.step(m, d)


@jax.jit
def _mjx_forward(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    return mjx.forward(m, d)


_fast_depth_ids = jax.jit(fast_depth_ids, static_argnums=0)
_xla_shade = jax.jit(shade, static_argnums=0)


class BankView:
    """`env.bank`, looked up on every attribute read rather than once: an agent that keeps a
    BankView (not the bank) reads the bank bound at trace time (ConavEnv.bound_bank)."""

    def __init__(self, env: "ConavEnv"):
        self._env = env

    def __getattr__(self, name: str):
        return getattr(self._env.bank, name)


class ConavEnv(Env):
    """CoNav as a brax environment. Constants (bank, model, config) are fields; state is in State.

    Args:
      data_dir: a dataset written by `conav generate` (or pass `episodes=` already loaded).
      split: "train" or "val".
      config: sensors, physics and reward (envs.config.EnvConfig).
      max_episodes: load at most this many episodes of the split.
    """

    def __init__(
        self,
        data_dir: str | None = None,
        split: str = "train",
        config: EnvConfig | None = None,
        *,
        episodes: EpisodeSplit | None = None,
        max_episodes: int | None = None,
    ):
        if episodes is None:
            if data_dir is None:
                raise ValueError("ConavEnv needs data_dir (a generated dataset) or episodes=")
            episodes = load_split(data_dir, split, max_episodes=max_episodes)
        config = config or EnvConfig()
        # "auto" becomes the caster this machine runs (pallas on a GPU, else fast), and the
        # physics implementation (warp on one CUDA GPU with warp-lang, else jax).
        sensor = dataclasses.replace(config.sensor, kind=resolve_sensor_kind(config.sensor.kind))
        physics = dataclasses.replace(config.physics, impl=resolve_physics_impl(config.physics.impl))
        self.config = dataclasses.replace(config, sensor=sensor, physics=physics)
        self.task: TaskConfig = episodes.config.task
        self.split = episodes
        self.bank: EpisodeBank = build_bank(episodes)
        slots = min(self.config.physics.collision_slots, self.bank.col_slots)
        self.layout = GeomLayout(self.bank.col_slots, self.bank.vis_slots, slots)
        self.mj_model, self.mjx_model = build_model(self.layout, self.task, self.config.physics)
        data0 = make_data(self.mj_model, self.mjx_model, self.layout, self.config.physics)
        self._shared = shared_buffer_shapes(data0)  # MuJoCo Warp's all-worlds buffers: not in the State
        self._data0 = without_shared_buffers(data0, self._shared)
        self._servo_error_limits = servo_error_limits(self.config.physics)
        self._lost_bits = warp_lost_contact_bits() if physics.impl == "warp" else 0
        # The mjx.ray reference sensor is JAX code that reads geometry only: it renders from a JAX
        # model whatever runs the physics.
        self._render_base = self.mjx_model if physics.impl == "jax" else mjx.put_model(self.mj_model)
        self._robot_body = robot_body_id(self.mj_model)
        substeps = self.task.control_dt_s / self.config.physics.timestep_s
        if abs(substeps - round(substeps)) > 1e-6:
            raise ValueError("control_dt_s must be a whole number of physics timesteps")
        self._substeps = int(round(substeps))
        lay = self.layout
        self._box_ids = jnp.arange(lay.col_start, lay.physics_start, dtype=jnp.int32)
        self._cap_ids = jnp.arange(lay.human_start, lay.ngeom, dtype=jnp.int32)
        self._cap_r = jnp.asarray(CAPSULE_RADII)
        self._static_rgb = (FLOOR_RGB_F, ROBOT_RGB, capsule_colours())

    # -- brax Env interface ------------------------------------------------------------------
    @property
    def observation_size(self):
        obs = jax.eval_shape(self.reset, jax.random.PRNGKey(0)).obs
        return {k: v.shape for k, v in obs.items()}

    @property
    def action_size(self) -> int:
        return 2

    @property
    def backend(self) -> str:
        return "mjx"

    @contextlib.contextmanager
    def bound_bank(self, bank: EpisodeBank):
        """Within the block the env (and every agent reading `env.bank` as it acts) uses `bank`,
        e.g. a jitted function's argument: traced there, the episode arrays enter the compiled
        program as an argument instead of as constants (on the paper's val split the humanoid's
        joints alone are 726 MB, which XLA would copy into the program and compile around).
        ValueError for a bank of another structure or shape."""
        if jax.tree.structure(bank) != jax.tree.structure(self.bank) or any(
                a.shape != b.shape for a, b in zip(jax.tree.leaves(bank), jax.tree.leaves(self.bank))):
            raise ValueError("bound_bank needs a bank of the env's own structure and shapes")
        saved, self.bank = self.bank, bank
        try:
            yield self
        finally:
            self.bank = saved

    @property
    def bank_view(self) -> "BankView":
        """The episode bank as agents should hold it: read when they act, so a bank bound by
        `bound_bank` (a compiled program's argument) is what they read."""
        return BankView(self)

    @property
    def num_episodes(self) -> int:
        return self.bank.num_episodes

    def reset(self, rng: jax.Array) -> State:
        """Start a random episode of the bank."""
        rng, key = jax.random.split(rng)
        episode = jax.random.randint(key, (), 0, self.bank.num_episodes)
        return self.reset_to_episode(rng, episode)

    def reset_to_episode(self, rng: jax.Array, episode: jax.Array, observe: bool = True) -> State:
        """Start episode `episode` (an index into the bank) at its first step. With
        `observe=False` the State's obs is `{}` (see `step`)."""
        del rng  # the episode fixes everything; kept for the brax signature's sake
        b = self.bank
        episode = jnp.asarray(episode, jnp.int32)
        start = b.robot_start[episode]
        m = self._episode_model(episode, start[:2])
        d = self._data0.replace(qpos=start, qvel=jnp.zeros(3))
        d = self._pose_human(d, episode, jnp.int32(0))
        geo = self._goal_distance(episode, start[:2])
        ud = jnp.zeros(len(UD)).at[UD["t_reach"]].set(-1.0).at[UD["prev_geodesic_m"]].set(geo)
        d = self._forward(m, d.replace(userdata=ud))
        state = State(pipeline_state=d, obs={}, reward=jnp.zeros(()), done=jnp.zeros(()),
                      metrics=self._metrics(d, episode), info={"episode": episode})
        return self.observe(state) if observe else state

    def default_observation_keys(self) -> tuple[str, ...]:
        """The keys `reset`/`step` observe (brax's interface, training): the sensors, and the
        privileged keys (ground-truth intentions, segmentation) with `EnvConfig.intention_obs`. An agent in a rollout observes
        only the keys it declares (envs.rollout)."""
        return SENSOR_KEYS + (tuple(PRIVILEGED_KEYS) if self.config.intention_obs else ())

    def observe(self, state: State, keys: Sequence[str] | None = None) -> State:
        """`state` with the observation of its data: the keys `keys` (envs.observations; default
        `default_observation_keys()`), and only those are computed (no panorama unless `rgbd` or
        `front` is asked for). ValueError for an unknown key."""
        keys = self.default_observation_keys() if keys is None else tuple(keys)
        for k in keys:
            observation(k)
        return state.replace(obs=self._observe(state.pipeline_state, state.info["episode"], keys))

    def step(self, state: State, action: jax.Array, observe: bool = True) -> State:
        """One control step. `action` (2,) = (v_lin, v_ang) in [-1, 1], clipped; an action with
        a NaN acts as zero (stay put) and is counted. ValueError for any other shape: an oracle
        mover's pose goes through `step_to_pose`.

        `observe=False` leaves the observation out (State.obs `{}`): a rollout that calls
        `observe` before its agent acts renders only what the agent reads (a loop-carried
        observation is computed whether read or not), once per step."""
        action = jnp.asarray(action)
        if action.shape != (2,):
            raise ValueError(f"action must have shape (2,) = (v_lin, v_ang) per environment, got {action.shape}; "
                             "an oracle mover sets the pose with ConavEnv.step_to_pose")
        return self._advance(state, action, None, False, observe)

    def step_to_pose(self, state: State, pose: jax.Array, observe: bool = True, *,
                     action: jax.Array | None = None, use_pose: jax.Array | bool = True) -> State:
        """An oracle mover's control step (privileged: "pose set by an oracle pathfinder"): the
        robot is put at `pose` (3,) = (x m, y m, yaw rad) before the step's physics, which then
        stands still; the move counts in the path length, and contacts at the new pose count as
        any other. A pose with a NaN keeps the robot where it is (counted). With `action` (2,)
        velocities and a traced bool `use_pose`, the step does either (one compiled rollout
        serving velocity and pose agents: envs.agents.base.switch_agent)."""
        pose = jnp.asarray(pose)
        if pose.shape != (3,) or (action is not None and jnp.shape(action) != (2,)):
            raise ValueError(f"step_to_pose takes a pose (3,) = (x, y, yaw) and optionally velocities (2,), got "
                             f"{pose.shape} and {None if action is None else jnp.shape(action)}")
        velocity = jnp.zeros(2, pose.dtype) if action is None else jnp.asarray(action)
        return self._advance(state, velocity, pose, use_pose, observe)

    def _advance(self, state: State, velocity: jax.Array, pose: jax.Array | None, use_pose, observe: bool) -> State:
        """The control step of `step` and `step_to_pose`: velocities (2,), or, where `use_pose`,
        the robot put at `pose` (3,) first."""
        episode = state.info["episode"]
        b, task = self.bank, self.task
        d0 = state.pipeline_state
        ud0 = d0.userdata
        t = ud0[UD["t"]].astype(jnp.int32) + 1
        v_nan = jnp.any(jnp.isnan(velocity))
        a = jnp.clip(jnp.where(v_nan, 0.0, velocity), -1.0, 1.0)
        v, w = a[0] * task.v_max_mps, a[1] * task.w_max_radps
        if pose is None:
            d_start, is_nan = d0, v_nan
        else:
            p_nan = jnp.any(jnp.isnan(pose))
            is_nan = jnp.where(use_pose, p_nan, v_nan)
            # Put at the pose, then the physics of standing still.
            qpos = jnp.where(use_pose & ~p_nan, pose.astype(d0.qpos.dtype), d0.qpos)
            qvel = jnp.where(use_pose, jnp.zeros_like(d0.qvel), d0.qvel)
            d_start = d0.replace(qpos=qpos, qvel=qvel)
            v, w = jnp.where(use_pose, 0.0, v), jnp.where(use_pose, 0.0, w)

        m = self._episode_model(episode, d_start.qpos[:2])
        d = self._pose_human(d_start, episode, t)
        d = self._physics(m, d, v, w)

        xy = d.qpos[:2]
        human_touch, wall_touch = self._contacts(episode, xy, t)
        dist_goal = jnp.linalg.norm(xy - b.goal_xy[episode])
        reached_before = ud0[UD["reached"]] > 0
        reached = reached_before | (dist_goal <= task.success_radius_m)
        first_reach = reached & ~reached_before
        step_len = jnp.linalg.norm(xy - d0.qpos[:2])
        geo = self._goal_distance(episode, xy)
        prev_geo = ud0[UD["prev_geodesic_m"]]
        ud = ud0
        ud = ud.at[UD["t"]].set(t.astype(jnp.float32))
        ud = ud.at[UD["reached"]].set(reached.astype(jnp.float32))
        ud = ud.at[UD["t_reach"]].set(jnp.where(first_reach, t.astype(jnp.float32), ud0[UD["t_reach"]]))
        # CR counts touches up to the first reach, its step included; CR_full every touch.
        ud = ud.at[UD["collided"]].max((human_touch & ~reached_before).astype(jnp.float32))
        # A touch at the step the robot arrives does not count as "before t_reach".
        ud = ud.at[UD["collided_before_reach"]].max((human_touch & ~reached).astype(jnp.float32))
        ud = ud.at[UD["collided_full"]].max(human_touch.astype(jnp.float32))
        ud = ud.at[UD["human_touch"]].set(human_touch.astype(jnp.float32))
        ud = ud.at[UD["wall_touch"]].set(wall_touch.astype(jnp.float32))
        ud = ud.at[UD["path_length_m"]].add(jnp.where(reached_before, 0.0, step_len))
        ud = ud.at[UD["prev_geodesic_m"]].set(geo)
        ud = ud.at[UD["human_contact_steps"]].add(human_touch.astype(jnp.float32))
        ud = ud.at[UD["wall_contact_steps"]].add(wall_touch.astype(jnp.float32))
        ud = ud.at[UD["nan_actions"]].add(is_nan.astype(jnp.float32))
        done = (reached & self.config.end_at_reach) | (t >= b.t_end[episode])
        ud = ud.at[UD["done"]].set(done.astype(jnp.float32))
        d = d.replace(userdata=ud)

        r = self.config.reward
        progress = jnp.where(jnp.isfinite(geo) & jnp.isfinite(prev_geo), prev_geo - geo, 0.0)
        reward = (
            r.progress_scale * progress
            + jnp.where(first_reach & (t <= b.t_arrive[episode]), r.reach_first_bonus, 0.0)
            + jnp.where(first_reach & (t > b.t_arrive[episode]), r.reach_late_bonus, 0.0)
            - r.human_contact_penalty * human_touch
            - r.wall_contact_penalty * wall_touch
            - r.time_cost
        )
        # An ended episode stays as it ended (zero reward, still done). Its observation is
        # rendered again from the data it ended with, not kept: the same image, without
        # reading the old one back.
        ended = ud0[UD["done"]] > 0
        d = jax.tree.map(lambda old, nw: jnp.where(ended, old, nw), d0, d)
        new = state.replace(
            pipeline_state=d,
            obs={},
            reward=jnp.where(ended, 0.0, reward).astype(jnp.float32),
            done=jnp.where(ended, 1.0, done.astype(jnp.float32)),
            metrics=self._metrics(d, episode),
        )
        return self.observe(new) if observe else new

    # -- pieces --------------------------------------------------------------------------------
    def _physics(self, m: mjx.Model, d: mjx.Data, v: jax.Array, w: jax.Array) -> mjx.Data:
        """The MJX substeps of one control step, the robot servoed to (v m/s, w rad/s)."""

        lim = self._servo_error_limits
        step = _mjx_step if self.config.physics.impl == "jax" else mjx.step

        def substep(d, _):
            yaw = d.qpos[2]
            ctrl = jnp.stack([v * jnp.cos(yaw), v * jnp.sin(yaw), w])
            if lim is not None:  # the servos' force limits, as velocity errors (envs.mjcf.build_mjcf)
                ctrl = d.qvel + jnp.clip(ctrl - d.qvel, -lim, lim)
            return step(m, d.replace(ctrl=ctrl)), None

        d, _ = jax.lax.scan(substep, self._mjx_data(m, d), None, length=self._substeps,
                            unroll=min(self.config.physics.substep_unroll, self._substeps))
        return without_shared_buffers(d, self._shared)

    def _forward(self, m: mjx.Model, d: mjx.Data) -> mjx.Data:
        """mjx.forward on the State's data (positions and velocities to everything derived)."""
        forward = _mjx_forward if self.config.physics.impl == "jax" else mjx.forward
        return without_shared_buffers(forward(m, self._mjx_data(m, d)), self._shared)

    def _mjx_data(self, m: mjx.Model, d: mjx.Data) -> mjx.Data:
        """The State's data as MJX steps it in the episode model `m`. With impl="warp": fresh
        all-worlds contact buffers, and the physics slots' world positions: MuJoCo Warp takes
        geoms of the world body for static and computes their poses once, in make_data, while
        ours follow the robot (`_episode_model`). The world body's frame is the identity and the
        boxes are unrotated, so a slot's world position is its geom_pos."""
        if self.config.physics.impl == "jax":
            return d
        sl = slice(self.layout.physics_start, self.layout.robot)
        d = d.replace(geom_xpos=d.geom_xpos.at[sl].set(m.geom_pos[sl]))
        return with_shared_buffers(d, self._shared)

    def _episode_model(self, episode: jax.Array, robot_xy: jax.Array, render: bool = False) -> mjx.Model:
        """The shared MJX model with this episode's blocking boxes nearest `robot_xy` in the
        physics slots (and, with `render`, every scene box in the render slots)."""
        b, lay = self.bank, self.layout
        s = b.scene_index[episode]
        lo, hi = b.col_lo[s], b.col_hi[s]
        gap = jnp.linalg.norm(jnp.maximum(jnp.maximum(lo[:, :2] - robot_xy, robot_xy - hi[:, :2]), 0.0), axis=-1)
        _, near = jax.lax.top_k(-jnp.where(b.col_valid[s], gap, jnp.inf), lay.physics_slots)
        # A padding box picked when a scene has fewer boxes than slots sits below the floor.
        lo, hi = lo[near], hi[near]
        start, stop = lay.physics_start, lay.robot
        if render:
            lo = jnp.concatenate([b.col_lo[s], b.vis_lo[s], lo])
            hi = jnp.concatenate([b.col_hi[s], b.vis_hi[s], hi])
            start = lay.col_start
        pos, size = (lo + hi) / 2.0, (hi - lo) / 2.0
        sl = slice(start, stop)
        mm = self._render_base if render else self.mjx_model
        # Local AABB (centre, half-size): (ngeom, 6) in JAX's model, (ngeom, 2, 3) in Warp's.
        aabb = jnp.concatenate([jnp.zeros_like(size), size], axis=-1).reshape(size.shape[:1] + mm.geom_aabb.shape[1:])
        return mm.replace(
            geom_pos=mm.geom_pos.at[sl].set(pos),
            geom_size=mm.geom_size.at[sl].set(size),
            geom_rbound=mm.geom_rbound.at[sl].set(jnp.linalg.norm(size, axis=-1)),
            geom_aabb=mm.geom_aabb.at[sl].set(aabb),
        )

    def human_joints(self, episode: jax.Array, t: jax.Array) -> jax.Array:
        """World joints (22, 3) of the humanoid at step t (clamped to the episode's arrays)."""
        b = self.bank
        t = jnp.clip(t, 0, b.max_steps - 1)
        root = b.root_xy[episode, t]
        return b.joints_local[episode, t].astype(jnp.float32) + jnp.append(root, 0.0)

    def _pose_human(self, d: mjx.Data, episode: jax.Array, t: jax.Array) -> mjx.Data:
        centre, axis, _ = capsule_poses(self.human_joints(episode, t))
        return d.replace(mocap_pos=centre, mocap_quat=quat_z_to(axis))

    def _goal_distance(self, episode: jax.Array, xy: jax.Array) -> jax.Array:
        b = self.bank
        s = b.scene_index[episode]
        return field_value(b.fields[s, b.field_b[episode]], b.field_origin[s], b.cell_m, xy)

    def _contacts(self, episode: jax.Array, xy: jax.Array, t: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(touching the human, touching a wall or furniture) for the robot at xy."""
        b, task, tol = self.bank, self.task, self.config.physics.contact_tolerance_m
        s = b.scene_index[episode]
        _, _, ends = capsule_poses(self.human_joints(episode, t))
        human = contact.robot_touches_capsules(
            xy, task.robot_radius_m, task.robot_height_m, ends[0], ends[1], self._cap_r, tol
        )
        wall = contact.robot_touches_boxes(xy, task.robot_radius_m, b.col_lo[s], b.col_hi[s], b.col_valid[s], tol)
        return human, wall

    def _geom_rgb(self, episode: jax.Array) -> jax.Array:
        b = self.bank
        s = b.scene_index[episode]
        floor, robot, human = self._static_rgb
        hidden = jnp.zeros((self.layout.physics_slots, 3))  # physics slots never appear in images
        return jnp.concatenate(
            [jnp.asarray(floor)[None], b.col_rgb[s], b.vis_rgb[s], hidden, jnp.asarray(robot)[None], jnp.asarray(human)]
        )

    def _geom_material(self, episode: jax.Array) -> jax.Array:
        """(ngeom, MATERIAL_WIDTH) material rows by geom id (SensorConfig.materials "instance"):
        the scene's floor, boxes, the robot in its flat colour, the humanoid in the episode's
        clothing."""
        b = self.bank
        s = b.scene_index[episode]
        flat = lambda rgb: jnp.concatenate([rgb, rgb, jnp.zeros(rgb.shape[:-1] + (1,)),
                                            jnp.ones(rgb.shape[:-1] + (1,)), jnp.zeros(rgb.shape[:-1] + (1,))], -1)
        hidden = jnp.zeros((self.layout.physics_slots, b.floor_material.shape[-1]))
        human = flat(b.clothing_rgb[episode][jnp.asarray(capsule_groups())])
        return jnp.concatenate([b.floor_material[s][None], b.col_material[s], b.vis_material[s], hidden,
                                flat(jnp.asarray(ROBOT_RGB))[None], human])

    def _geom_category(self, episode: jax.Array) -> jax.Array:
        """(ngeom,) int32 object category by geom id, -1 for the floor, walls, robot and humanoid."""
        b = self.bank
        s = b.scene_index[episode]
        none = lambda n: jnp.full((n,), -1, jnp.int32)
        lay = self.layout
        return jnp.concatenate([none(1), b.col_category[s], b.vis_category[s],
                                none(lay.ngeom - lay.physics_start)])

    def segmentation(self, ids: jax.Array, episode: jax.Array) -> jax.Array:
        """Object category per pixel (int32, like `ids`) of hit geom ids `ids` in `episode`'s
        scene: -1 for the sky, floor, walls and the humanoid (observation key "segmentation")."""
        return jnp.where(ids >= 0, self._geom_category(episode)[jnp.maximum(ids, 0)], -1)

    def _colour(self, d: mjx.Data, episode: jax.Array, depth: jax.Array, ids: jax.Array) -> jax.Array:
        """RGB-D (H, W, 4) of a cast (depth, ids) from the robot's camera in `d`, in the
        configured materials (SensorConfig.materials)."""
        cfg = self.config.sensor
        if cfg.materials == "flat":
            return colourise(depth, ids, self._geom_rgb(episode))
        cam = jnp.array([d.qpos[0], d.qpos[1], self.task.camera_height_m])
        colour = shade if cfg.kind == "pallas" else _xla_shade  # the kind is resolved (__init__)
        return colour(cfg, cam, d.qpos[2], depth, ids, self._scene_geometry(d, episode), self._geom_material(episode))

    def panorama(self, d: mjx.Data, episode: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(depth (H, W) metres, geom ids (H, W)) of the robot's camera in data `d` from the
        configured sensor: mjx.ray in the episode's render model for "reference", else its caster
        over the episode's boxes and the humanoid's capsules at the data's step, as a
        SceneGeometry."""
        cfg = self.config.sensor
        cam = jnp.array([d.qpos[0], d.qpos[1], self.task.camera_height_m])
        yaw = d.qpos[2]
        if cfg.kind == "reference":
            m = self._episode_model(episode, d.qpos[:2], render=True)
            return reference_depth_ids(cfg, m, d, cam, yaw, self._robot_body)
        cast = _fast_depth_ids if cfg.kind == "fast" else caster_for(cfg.kind)
        return cast(cfg, cam, yaw, self._scene_geometry(d, episode))

    def _scene_geometry(self, d: mjx.Data, episode: jax.Array) -> SceneGeometry:
        """The episode's boxes and the humanoid's capsules at the data's step."""
        b = self.bank
        s = b.scene_index[episode]
        t = d.userdata[UD["t"]].astype(jnp.int32)
        _, _, ends = capsule_poses(self.human_joints(episode, t))
        return SceneGeometry(
            box_lo_m=jnp.concatenate([b.col_lo[s], b.vis_lo[s]]),
            box_hi_m=jnp.concatenate([b.col_hi[s], b.vis_hi[s]]),
            box_ids=self._box_ids,
            box_valid=jnp.concatenate([b.col_valid[s], b.vis_valid[s]]),
            capsule_p0_m=ends[0],
            capsule_p1_m=ends[1],
            capsule_radius_m=self._cap_r,
            capsule_ids=self._cap_ids,
            floor_id=self.layout.floor,
        )

    def render_at(self, episode: jax.Array, robot_pose: jax.Array, t: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(rgbd (H, W, 4), geom ids (H, W)): the panorama the robot's camera sees from
        `robot_pose` (x m, y m, yaw rad) with the humanoid posed at step `t` of `episode`, as
        the configured sensor renders it in `step`. Outside the simulation (nothing moves): for
        rendering datasets (the intention predictor's frames) and debugging."""
        t = jnp.asarray(t, jnp.int32)
        d = self._data0.replace(qpos=jnp.asarray(robot_pose, self._data0.qpos.dtype))
        d = d.replace(userdata=d.userdata.at[UD["t"]].set(t.astype(d.userdata.dtype)))
        d = self._pose_human(d, episode, t)  # mocap poses: what the mjx.ray reference sees
        return self.render(d, episode)

    def render(self, d: mjx.Data, episode: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(rgbd (H, W, 4), geom ids (H, W)) of the robot's camera in data `d`: `panorama`
        coloured in the configured materials."""
        depth, ids = self.panorama(d, episode)
        return self._colour(d, episode, depth, ids), ids

    def _observe(self, d: mjx.Data, episode: jax.Array, keys: tuple[str, ...]) -> dict[str, jax.Array]:
        """The observation keys `keys` (envs.observations) of data `d`, computing only those."""
        b, cfg = self.bank, self.config
        xy, yaw = d.qpos[:2], d.qpos[2]
        t = d.userdata[UD["t"]].astype(jnp.int32)
        now = jnp.minimum(t, b.max_steps - 1)
        start = b.robot_start[episode]

        made = {}

        def cast():  # (rgbd, geom ids), rendered once for the keys that read the panorama
            if not made:
                made["cast"] = self.render(d, episode)
            return made["cast"]

        def rgbd():
            return cast()[0]

        def steps(offsets):
            return jnp.clip(t + offsets, 0, b.max_steps - 1)

        def human_at(ts):
            return to_frame(b.root_xy[episode, ts], xy, yaw)

        sensors = {
            "rgbd": rgbd,
            "front": lambda: front_view(obs["rgbd"] if "rgbd" in obs else rgbd()),
            "gps_compass": lambda: jnp.concatenate([to_frame(xy, start[:2], start[2]),
                                                    wrap_angle(yaw - start[2])[None]]),
            "human_pos": lambda: human_at(now),
            "human_history": lambda: human_at(steps(-jnp.arange(cfg.human_history_steps - 1, -1, -1))),
            "activity_probs": lambda: jax.nn.one_hot(b.activity_b[episode], NUM_ACTIVITIES),
            "object_probs": lambda: jax.nn.one_hot(b.object_b[episode], NUM_CATEGORIES),
            "future_traj": lambda: human_at(steps(1 + jnp.arange(cfg.future_steps))),
            # Privileged: each pixel's object category, -1 for no object (ORACLE_SEGMENTATION).
            "segmentation": lambda: self.segmentation(cast()[1], episode),
        }
        obs = {}
        for k in sorted(keys, key=lambda k: k != "rgbd"):  # the panorama first: `front` cuts it
            obs[k] = sensors[k]()
        return {k: obs[k] for k in keys}

    def _metrics(self, d: mjx.Data, episode: jax.Array) -> dict[str, jax.Array]:
        """Per-episode accumulators plus the episode constants the metrics need (all scalars)."""
        ud, b = d.userdata, self.bank
        per_step = ("prev_geodesic_m", "human_touch", "wall_touch")
        out = {name: ud[i] for name, i in UD.items() if name not in per_step}
        if self.config.end_at_reach:  # the episode stops at the first reach: no CR_full
            del out["collided_full"]
        out["t_arrive"] = b.t_arrive[episode].astype(jnp.float32)
        out["t_end"] = b.t_end[episode].astype(jnp.float32)
        out["geodesic_start_goal_m"] = b.geodesic_start_goal_m[episode]
        out["shortest_path_steps"] = b.shortest_path_steps[episode]
        if self.config.physics.impl == "warp":  # 1: MuJoCo Warp dropped contacts (PhysicsConfig.warp_max_worlds)
            out["physics_overflow"] = ((d._impl.overflow & self._lost_bits) != 0).astype(jnp.float32)
        return out


def shared_buffer_shapes(d: mjx.Data) -> dict[str, jax.ShapeDtypeStruct]:
    """The arrays of MuJoCo Warp's data that are one for all worlds (contacts and their counters),
    by field name; none for MJX's JAX data."""
    if d.impl != mjx.Impl.WARP:
        return {}
    from mujoco.mjx.warp.types import DATA_NON_VMAP

    return {
        name: jax.ShapeDtypeStruct(x.shape, x.dtype)
        for name in sorted(DATA_NON_VMAP)
        if isinstance(x := getattr(d._impl, name), jax.Array)
    }


def without_shared_buffers(d: mjx.Data, shared: dict) -> mjx.Data:
    """`d` without the all-worlds buffers (None: no leaves), so every leaf is per world."""
    return d.replace(_impl=d._impl.replace(**dict.fromkeys(shared))) if shared else d


def with_shared_buffers(d: mjx.Data, shared: dict) -> mjx.Data:
    """`d` with fresh all-worlds buffers: zeros do, since each collision pass starts by zeroing
    the contact counters and writes every contact it reports."""
    if not shared:
        return d
    return d.replace(_impl=d._impl.replace(**{k: jnp.zeros(v.shape, v.dtype) for k, v in shared.items()}))
