"""The MJX environment: physics, contacts, metrics, sensors' parity, batching, brax wrappers."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from worlds import goal_of, make_split

from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.config import PhysicsConfig
from conav_jax.envs.metrics import summarize
from conav_jax.envs.mjcf import UD

SMALL = EnvConfig(sensor=SensorConfig(resolution=(8, 32)))
# The env's steps compile much faster without XLA's fusion emitters (slower to run, which a few
# steps do not notice); every jit here takes them, so the programs compared round alike.
jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0,
                                                   "xla_cpu_use_fusion_emitters": False})


@pytest.fixture(scope="module")
def hall():
    """Episodes in the hand-built hall: 0 faces the east wall 1 m away; 1 faces the human;
    2 starts 2 m west of the goal (x = 8.5) facing it; 3 starts far from the goal."""
    return _hall_env(SMALL)


@pytest.fixture(scope="module")
def to_pose(hall):
    """The hall's step_to_pose, jitted once for the tests that put the robot at a pose."""
    return jit(hall[0].step_to_pose)


def _hall_env(config):
    split = make_split(
        [(8.0, 0.9, -np.pi / 2), (2.0, 2.0, np.pi), (6.5, 2.0, 0.0), (1.6, 3.3, 0.0)],
        t_arrive=20,
        t_end=40,
    )
    env = ConavEnv(episodes=split, config=config)
    return env, jit(env.reset_to_episode), jit(env.step)


def _run(env_fns, episode, actions, teleport=None):
    env, reset, step = env_fns
    s = reset(jax.random.PRNGKey(0), episode)
    states = [s]
    for k, a in enumerate(actions):
        if teleport is not None and k == teleport[0]:
            d = s.pipeline_state
            s = s.replace(pipeline_state=d.replace(qpos=d.qpos.at[:2].set(jnp.asarray(teleport[1]))))
        s = step(s, jnp.asarray(a, jnp.float32))
        states.append(s)
    return states


def test_robot_stops_at_wall(hall):
    # Episode 0: 0.8 m from the south wall's face (y = 0.1), driving south at full speed.
    states = _run(hall, 0, [(1.0, 0.0)] * 20)
    ys = np.array([float(s.pipeline_state.qpos[1]) for s in states])
    assert ys[3] < 0.65  # it moved (0.3 m in 3 steps, less the servo spin-up)
    assert ys.min() > 0.1 + 0.3 - 0.005  # face of the wall + radius, less 5 mm of soft contact
    assert abs(ys[-1] - ys[-5]) < 0.005  # and stays stopped
    assert float(states[-1].metrics["wall_contact_steps"]) > 5


def _slide_along_wall(env_fns, steps=20):
    """Episode 0 turned to face south-west, driven at full speed into the south wall at 45 deg."""
    env, reset, step = env_fns
    s = reset(jax.random.PRNGKey(0), 0)
    d = s.pipeline_state
    s = s.replace(pipeline_state=d.replace(qpos=d.qpos.at[2].set(-0.75 * np.pi)))
    states = [s]
    for _ in range(steps):
        states.append(step(states[-1], jnp.array([1.0, 0.0])))
    return np.array([np.asarray(s.pipeline_state.qpos[:2]) for s in states])


def test_robot_slides_along_a_wall_it_meets_at_an_angle(hall):
    # Frictionless contacts (PhysicsConfig.contact_condim = 1): pressed against the wall, the
    # robot keeps the along-wall half of its velocity, 0.1 m/step * cos 45 deg.
    xy = _slide_along_wall(hall)
    assert xy[:, 1].min() > 0.1 + 0.3 - 0.005  # never through the wall
    assert abs(xy[-1, 1] - 0.4) < 0.01  # pressed against it at the end
    slide = -np.diff(xy[-6:, 0])
    assert np.all(slide > 0.05) and np.all(slide < 0.075)


def test_default_solver_budget_matches_a_converged_solve(hall):
    # Three Newton iterations (PhysicsConfig default) against thirty on wall and human contacts.
    converged = _hall_env(dataclasses.replace(SMALL, physics=PhysicsConfig(solver_iterations=30, ls_iterations=30)))
    np.testing.assert_allclose(_slide_along_wall(hall), _slide_along_wall(converged), atol=1e-3)
    push = [(1.0, 0.0)] * 8  # episode 1: into the human
    fast = np.array([np.asarray(s.pipeline_state.qpos) for s in _run(hall, 1, push)])
    ref = np.array([np.asarray(s.pipeline_state.qpos) for s in _run(converged, 1, push)])
    np.testing.assert_allclose(fast, ref, atol=1e-3)


@pytest.mark.parametrize("bad", [dict(contact_condim=4), dict(solver_iterations=0), dict(timestep_s=0.0)])
def test_bad_physics_config_is_rejected(bad):
    with pytest.raises(ValueError, match="physics"):
        PhysicsConfig(**bad)


def test_bench_physics_overrides_are_typed_and_checked():
    import argparse

    from conav_jax.eval.cli import parse_physics_override

    assert parse_physics_override("solver_iterations=2") == ("solver_iterations", 2)
    assert parse_physics_override("timestep_s=0.02") == ("timestep_s", 0.02)
    with pytest.raises(argparse.ArgumentTypeError, match="NAME one of"):
        parse_physics_override("iterations=2")
    with pytest.raises(argparse.ArgumentTypeError, match="needs a int"):
        parse_physics_override("solver_iterations=two")


def test_touching_the_human_is_counted_and_robot_does_not_pass_through(hall):
    # Episode 1: human at the fridge stand (x~1.3), robot at x=2 facing it (-x), driving on.
    states = _run(hall, 1, [(1.0, 0.0)] * 8)
    m = states[-1].metrics
    assert float(m["collided"]) == 1.0 and float(m["human_contact_steps"]) >= 1
    # Each step's own contact flag (what rollout traces record) adds up to the count.
    per_step = [float(s.pipeline_state.userdata[UD["human_touch"]]) for s in states[1:]]
    assert sum(per_step) == float(m["human_contact_steps"]) and per_step[0] == 0.0
    human_x = float(hall[0].bank.root_xy[1, 0, 0])
    assert float(states[-1].pipeline_state.qpos[0]) > human_x  # pushed back, not through


@pytest.mark.parametrize(
    "teleport_step, fasr, rasr, t_reach",
    [(5, 1.0, 1.0, 6), (25, 0.0, 1.0, 26), (None, 0.0, 0.0, -1)],
)
def test_metrics_of_a_robot_teleported_onto_the_goal(hall, teleport_step, fasr, rasr, t_reach):
    env = hall[0]
    # 0.8 m short of the goal: inside the success radius, clear of the human standing there.
    goal = np.asarray(goal_of(env.split)) - np.array([0.8, 0.0])
    tele = None if teleport_step is None else (teleport_step, goal)
    states = _run(hall, 3, [(0.0, 0.0)] * 41, teleport=tele)
    m = {k: np.asarray(v)[None] for k, v in states[-1].metrics.items()}
    assert float(m["t_reach"][0]) == t_reach
    s = summarize(m)
    assert s["FASR"] == 100 * fasr and s["RASR"] == 100 * rasr
    if teleport_step is not None:
        # the odometer never sees a teleport: the path is only the standing robot's drift,
        # shorter than the geodesic, so the SPL weight is 1
        l = float(m["geodesic_start_goal_m"][0])
        p = float(m["path_length_m"][0])
        assert p < 0.05 and l > 5.0
        assert s["FASPL"] == pytest.approx(100 * fasr) and s["RASPL"] == pytest.approx(100 * rasr)
        assert s["AS"] == t_reach
        assert float(states[-1].done) == 1.0
    else:
        assert s["AS"] == 40 and float(states[-1].done) == 1.0  # ended at t_end


def test_ended_episode_stays_frozen(hall):
    states = _run(hall, 3, [(0.0, 0.0)] * 40 + [(1.0, 0.5)] * 5)  # driving after the end moves nothing
    a, b = states[40], states[45]  # t_end = 40: the episode ends at step 40
    assert float(a.done) == 1.0 and float(a.metrics["t"]) == 40.0
    # The data, the metrics and the observation (rendered again from that data) stay as they were.
    for part in ("pipeline_state", "metrics", "obs"):
        for x, y in zip(jax.tree.leaves(getattr(a, part)), jax.tree.leaves(getattr(b, part)), strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=part)
    assert float(b.reward) == 0.0 and float(b.done) == 1.0


def test_reward_is_geodesic_progress_plus_bonus(hall):
    env = hall[0]
    cfg = env.config.reward
    # Episode 2: 2 m west of the goal facing it; drive straight at 1 m/s: 0.1 m per step.
    states = _run(hall, 2, [(1.0, 0.0)] * 14)
    r = np.array([float(s.reward) for s in states[1:]])
    reach_step = int(states[-1].metrics["t_reach"])
    assert 10 <= reach_step <= 12  # 1 m to cover, plus the servo's spin-up
    for k in range(1, reach_step - 1):  # steady cruising steps: progress ~0.1 m minus time cost
        assert r[k] == pytest.approx(0.1 * cfg.progress_scale - cfg.time_cost, abs=0.02)
    assert r[reach_step - 1] > cfg.reach_first_bonus * 0.9  # before t_arrive = 20: first-arrival bonus


def test_nan_action_acts_as_zero_and_is_counted(hall):
    states = _run(hall, 3, [(np.nan, 0.5)] * 3)
    s0, s3 = states[0], states[-1]
    np.testing.assert_allclose(np.asarray(s3.pipeline_state.qpos), np.asarray(s0.pipeline_state.qpos), atol=1e-6)
    assert float(s3.metrics["nan_actions"]) == 3.0


def test_bad_action_shape_is_rejected(hall):
    env, reset, _ = hall
    s = reset(jax.random.PRNGKey(0), 0)
    with pytest.raises(ValueError, match=r"action must have shape \(2,\)"):
        env.step(s, jnp.zeros(4))


def test_a_pose_action_puts_the_robot_there_and_counts_the_move(hall, to_pose):
    # Episode 3 starts far from the goal; an oracle mover puts it 0.8 m short of the goal.
    env, reset, step = hall
    target = np.append(np.asarray(goal_of(env.split)) - np.array([0.8, 0.0]), 0.5).astype(np.float32)
    s0 = reset(jax.random.PRNGKey(0), 3)
    s1 = to_pose(s0, jnp.asarray(target))
    np.testing.assert_allclose(np.asarray(s1.pipeline_state.qpos), target, atol=1e-3)
    assert float(s1.metrics["t_reach"]) == 1.0
    moved = float(np.linalg.norm(target[:2] - np.asarray(s0.pipeline_state.qpos[:2])))
    assert float(s1.metrics["path_length_m"]) == pytest.approx(moved, abs=1e-3)


def test_a_pose_step_given_velocities_steps_as_the_one_it_is_told(hall, to_pose):
    """step_to_pose(pose, action=velocities, use_pose): the pose step where use_pose, else the
    velocity step; a NaN counts only in the part used."""
    env, reset, step = hall  # the plain steps, compiled once for the module
    either = jit(lambda s, v, p, use: env.step_to_pose(s, p, action=v, use_pose=use))
    s0 = reset(jax.random.PRNGKey(0), 3)
    target = np.append(np.asarray(goal_of(env.split)) - np.array([0.8, 0.0]), 0.5).astype(np.float32)
    velocity = np.array([0.7, -0.3], np.float32)
    cases = [(velocity, np.full(3, np.nan), False), (np.full(2, np.nan), target, True),
             (np.array([np.nan, 0.2]), np.ones(3), False), (velocity, np.array([np.nan, 1.0, 1.0]), True)]
    for v, p, use in cases:
        v, p = jnp.asarray(v, jnp.float32), jnp.asarray(p, jnp.float32)
        a, b = either(s0, v, p, jnp.bool_(use)), to_pose(s0, p) if use else step(s0, v)
        np.testing.assert_allclose(np.asarray(a.pipeline_state.qpos), np.asarray(b.pipeline_state.qpos), atol=1e-6)
        for key in ("nan_actions", "path_length_m", "t_reach"):
            assert float(a.metrics[key]) == pytest.approx(float(b.metrics[key]), abs=1e-6), (use, key)
    assert float(either(s0, jnp.asarray(velocity), jnp.full(3, jnp.nan), jnp.bool_(False)).metrics["nan_actions"]) == 0.0


def test_gps_compass_and_human_position_frames(hall):
    env, reset, step = hall
    s = reset(jax.random.PRNGKey(0), 1)  # robot at (2, 2) facing -x; human ~ (1.3, 2)
    np.testing.assert_allclose(np.asarray(s.obs["gps_compass"]), [0, 0, 0], atol=1e-5)
    hp = np.asarray(s.obs["human_pos"])
    assert hp[0] > 0.4 and abs(hp[1]) < 0.05  # the human is straight ahead
    s = step(s, jnp.array([-0.5, 0.0]))  # backwards 0.05 m: +x in the world, -x in the start frame
    assert float(s.obs["gps_compass"][0]) == pytest.approx(-0.05, abs=0.01)



def test_touching_the_human_before_reaching_voids_success(hall):
    # Episode 1: drive into the human at the fridge (a touch before t_reach), then be put 0.8 m
    # short of the goal: reached in time, but neither FASR nor RASR counts it.
    env = hall[0]
    goal = np.asarray(goal_of(env.split)) - np.array([0.8, 0.0])
    touched = _run(hall, 1, [(1.0, 0.0)] * 8 + [(0.0, 0.0)] * 4, teleport=(8, goal))
    m = {k: np.asarray(v)[None] for k, v in touched[-1].metrics.items()}
    assert float(m["t_reach"][0]) == 9 and float(m["collided_before_reach"][0]) == 1.0
    s = summarize(m)
    assert s["FASR"] == 0.0 and s["RASR"] == 0.0 and s["CR"] == 100.0
    # The same reach without the touch succeeds.
    clean = _run(hall, 1, [(0.0, 0.0)] * 12, teleport=(8, goal))
    s = summarize({k: np.asarray(v)[None] for k, v in clean[-1].metrics.items()})
    assert s["FASR"] == 100.0 and s["CR"] == 0.0


def test_the_episode_runs_to_t_end_and_cr_full_counts_contacts_after_the_reach(hall):
    # Episode 3 (facing east) is put 0.8 m west of the goal at step 25, when the human has stood
    # there since step 20: reached, untouched. From step 31 it drives on into the human: touches
    # after the reach count for CR_full only, and the episode goes on to t_end = 40.
    env = hall[0]
    goal = np.asarray(goal_of(env.split)) - np.array([0.8, 0.0])
    states = _run(hall, 3, [(0.0, 0.0)] * 30 + [(1.0, 0.0)] * 10, teleport=(24, goal))
    m = {k: np.asarray(v)[None] for k, v in states[-1].metrics.items()}
    assert float(m["t_reach"][0]) == 25 and float(states[26].done) == 0.0 and float(states[-1].done) == 1.0
    assert float(m["human_contact_steps"][0]) > 0 and float(m["t"][0]) == 40
    out = summarize(m)
    assert out["RASR"] == 100.0 and out["CR"] == 0.0 and out["CR_full"] == 100.0


def test_spl_in_steps_weighs_a_waiting_robot_below_a_direct_one(hall):
    # Episode 2: 2 m west of the goal facing it (l = 10 steps). Driving at once reaches it in
    # about 11 steps; waiting 3 steps first (gone before the walking human comes by), 3 later.
    # In metres both paths are ~1 m.
    direct = _run(hall, 2, [(1.0, 0.0)] * 30)
    waiting = _run(hall, 2, [(0.0, 0.0)] * 3 + [(1.0, 0.0)] * 27)
    out = [summarize({k: np.asarray(v)[None] for k, v in s[-1].metrics.items()}) for s in (direct, waiting)]
    l = float(direct[-1].metrics["shortest_path_steps"])
    t = [float(s[-1].metrics["t_reach"]) for s in (direct, waiting)]
    assert l == 10.0 and t[1] == t[0] + 3
    assert out[0]["FASPL"] == pytest.approx(100 * l / t[0]) and out[1]["FASPL"] == pytest.approx(100 * l / t[1])
    assert out[0]["FASPL_m"] == pytest.approx(100.0) and out[1]["FASPL_m"] == pytest.approx(100.0)


def test_programs_of_one_env_trace_its_physics_sensor_and_expert_once(hall, monkeypatch):
    """MJX's step and forward, the XLA caster, the colouring and the expert are jitted functions
    of their own: a second program of the env (or a second step in one) reuses their traces
    rather than tracing them again, and building an env program is mostly tracing."""
    from mujoco import mjx

    from conav_jax.envs import panorama
    from conav_jax.envs.agents.expert import make_expert_step
    from conav_jax.nav import expert
    from conav_jax.nav.expert import initial_carry

    env = hall[0]
    calls = dict.fromkeys(("step", "forward", "caster", "colouring", "expert"), 0)

    def counted(name, fn):
        def wrapped(*args, **kwargs):
            calls[name] += 1
            return fn(*args, **kwargs)
        return wrapped

    for module, attr, name in ((mjx, "step", "step"), (mjx, "forward", "forward"), (panorama, "box_terms", "caster"),
                               (panorama, "shading_table", "colouring"), (expert, "_next_phase", "expert")):
        monkeypatch.setattr(module, attr, counted(name, getattr(module, attr)))
    teacher = make_expert_step(env)

    def start(keys):
        return jax.vmap(env.reset_to_episode)(keys, jnp.arange(2)), jax.vmap(lambda _: initial_carry())(keys)

    def step(state, carry):
        action, carry = jax.vmap(teacher)(state, carry)
        return jax.vmap(env.step)(state, action), carry

    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    for program in (lambda k: step(*start(k)), lambda k: step(*step(*start(k)))):
        jax.jit(program).trace(keys)
    # Without their own jit: traced in each program, and per step (three times a step's parts,
    # twice the reset's); with it, at most once (none where an earlier test traced them).
    assert all(n <= 1 for n in calls.values()), calls
