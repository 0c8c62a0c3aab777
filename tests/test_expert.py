"""conav_jax.nav.expert on the hand-built hall, driven by a kinematic unicycle (no MJX: the
simulator-side tests are in test_imitation.py): it approaches, observes K steps, reaches the goal,
stays in free space and gets out of the way of a human walking at it; batches in one jit."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from worlds import make_split

from conav_jax.config import TaskConfig
from conav_jax.motion.phases import PHASE_ACTIVITY_A
from conav_jax.nav.expert import (
    APPROACH,
    GO,
    OBSERVE,
    ExpertConfig,
    ExpertMaps,
    clearance_map,
    expert_action,
    initial_carry,
)
from conav_jax.nav.planning import fill_blocked

jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})
CFG = ExpertConfig()
TASK = TaskConfig()
T = 181
T_ARRIVE = 140  # the human walks the 7.25 m from the fridge to the table in steps 70-140
# Robot centre to human root at which the two touch (robot 0.3 m + a standing body's ~0.25 m).
CONTACT_M = 0.55


def _head_on_track() -> np.ndarray:
    """A human walking west along the hall's centre line at 1.1 m/s, from the table to x = 1."""
    x = np.maximum(8.6 - 0.11 * np.arange(T), 1.0)
    return np.stack([x, np.full(T, 2.0)], -1).astype(np.float32)


@pytest.fixture(scope="module")
def hall():
    """Starts: west of the human at the fridge, in the north-west corner, mid-hall facing the
    wall, the east end facing back west; episode 4 has the human walking head-on at the robot."""
    starts = [(2.5, 2.0, 0.0), (1.6, 3.3, 0.0), (3.5, 1.0, 1.5), (7.5, 3.0, np.pi), (2.2, 2.0, 0.0)]
    default = make_split(starts[:1], t_arrive=T_ARRIVE, t_end=T - 1).episodes["root_xy"][0]
    split = make_split(starts, human_xy=[default] * 4 + [_head_on_track()], t_arrive=T_ARRIVE, t_end=T - 1)
    nav = split.navs[0]
    fields = np.stack([fill_blocked(f, nav.grid.free, nav.grid.cell_m) for f in nav.fields])
    maps = ExpertMaps(
        jnp.asarray(fields[1]), jnp.asarray(fields[0]), jnp.asarray(clearance_map(nav.grid.free, nav.grid.cell_m)),
        jnp.asarray(nav.grid.origin, jnp.float32),
    )
    e = split.episodes
    # The head-on human never does activity A.
    at_a = (e["phase"] == PHASE_ACTIVITY_A) & (np.arange(len(starts)) < 4)[:, None]
    return split, maps, nav.grid.cell_m, run_unicycle(maps, nav.grid.cell_m, e["robot_start"], e["root_xy"], at_a)


@functools.partial(jit, static_argnums=1)
def _unicycle(maps, cell_m, starts, human, at_a):
    """Kinematic rollouts: poses (B, T, 3), actions (B, T, 2), expert phases (B, T)."""
    look = jnp.asarray(CFG.human_lookahead_steps)
    dt = TASK.control_dt_s

    def one(start, human, at_a):
        def body(c, t):
            pose, carry = c
            ts = jnp.clip(t + look, 0, T - 1)
            a, carry = expert_action(CFG, maps, cell_m, pose, human[ts], at_a[t], carry)
            v, w = a[0] * TASK.v_max_mps, a[1] * TASK.w_max_radps
            yaw = pose[2] + w * dt
            nxt = jnp.stack([pose[0] + v * jnp.cos(yaw) * dt, pose[1] + v * jnp.sin(yaw) * dt, yaw])
            return (nxt, carry), (pose, a, carry.phase)

        _, out = jax.lax.scan(body, (start, initial_carry()), jnp.arange(T))
        return out

    return jax.vmap(one)(starts, human, at_a)


def run_unicycle(maps, cell_m, starts, human, at_a):
    return tuple(np.asarray(x) for x in _unicycle(maps, cell_m, jnp.asarray(starts), jnp.asarray(human), jnp.asarray(at_a)))


def _clearance_along(maps, cell_m, xy):
    origin = np.asarray(maps.origin)
    ix = np.floor((xy[..., 0] - origin[0]) / cell_m).astype(int)
    iy = np.floor((xy[..., 1] - origin[1]) / cell_m).astype(int)
    return np.asarray(maps.clearance)[iy, ix]


def test_expert_reaches_the_goal_in_the_hall_through_free_space(hall):
    split, maps, cell_m, (poses, _, _) = hall
    goal = split.episodes["goal_xy"][0]
    dist = np.linalg.norm(poses[:, :, :2] - goal, axis=-1)
    assert (dist.min(axis=1) <= TASK.success_radius_m).all(), dist.min(axis=1)
    reached = np.argmax(dist <= TASK.success_radius_m, axis=1)
    # The first four beat the human (the head-on one first lets them pass).
    assert (reached[:4] < T_ARRIVE).all(), reached
    for b, t in enumerate(reached):
        # The robot centre stays in the inflated free space (clearance > 0, one cell of slack).
        assert _clearance_along(maps, cell_m, poses[b, :t, :2]).min() >= -cell_m, b


def test_expert_approaches_then_observes_for_k_steps_then_goes(hall):
    split, _, _, (poses, actions, phases) = hall
    human = split.episodes["root_xy"]
    for b in range(4):
        seq = phases[b]
        assert seq[0] in (APPROACH, OBSERVE) and seq[-1] == GO
        assert (np.diff(seq) >= 0).all()  # phases only advance
        observing = seq == OBSERVE
        assert observing.sum() == CFG.observe_steps
        assert np.abs(actions[b, observing, 0]).max() == 0.0  # stands still while observing
        t_obs = np.argmax(observing)
        # It observes from within the approach distance (or after giving up approaching).
        d = np.linalg.norm(poses[b, t_obs, :2] - human[b, t_obs])
        assert d < CFG.approach_m or t_obs >= CFG.approach_max_steps


def test_expert_gets_out_of_the_way_of_a_human_walking_head_on(hall):
    split, _, _, (poses, actions, _) = hall
    human = split.episodes["root_xy"][4]
    gap = np.linalg.norm(poses[4, :, :2] - human, axis=-1)
    assert gap.min() > CONTACT_M + 0.1, gap.min()
    # The human came straight down the centre line: the robot had to leave it.
    assert np.abs(poses[4, :, 1] - 2.0).max() > 0.5


def test_expert_actions_for_a_batch_come_from_one_jitted_call(hall):
    _, maps, cell_m, _ = hall
    rng = np.random.default_rng(0)
    b = 16
    poses = np.stack([rng.uniform(1, 9, b), rng.uniform(0.8, 3.2, b), rng.uniform(-np.pi, np.pi, b)], -1)
    human = np.repeat(rng.uniform([1, 1], [9, 3], (b, 1, 2)), len(CFG.human_lookahead_steps), axis=1)
    carry = initial_carry()._replace(phase=jnp.asarray(rng.integers(0, 3, b), jnp.int32), steps=jnp.zeros(b, jnp.int32))
    at_a = rng.random(b) < 0.5
    batched = jit(jax.vmap(functools.partial(expert_action, CFG, maps, cell_m)))
    actions, new = batched(jnp.asarray(poses, jnp.float32), jnp.asarray(human, jnp.float32), jnp.asarray(at_a), carry)
    assert actions.shape == (b, 2) and new.phase.shape == (b,)
    assert np.abs(np.asarray(actions)).max() <= 1.0
    single = jit(functools.partial(expert_action, CFG, maps, cell_m))
    for i in (0, 7, 15):
        a, c = single(jnp.asarray(poses[i], jnp.float32), jnp.asarray(human[i], jnp.float32), jnp.asarray(at_a[i]),
                      jax.tree.map(lambda x: x[i], carry))
        np.testing.assert_allclose(np.asarray(a), np.asarray(actions[i]), atol=1e-5)
        assert int(c.phase) == int(new.phase[i])


def test_clearance_map_is_positive_in_free_space_and_negative_in_walls():
    free = np.zeros((7, 9), bool)
    free[2:5, 2:7] = True
    c = clearance_map(free, 0.1)
    assert (c[free] > 0).all() and (c[~free] < 0).all()
    assert c[3, 4] > c[2, 4]  # deeper inside, more clearance


def test_expert_config_rejects_inconsistent_numbers():
    with pytest.raises(ValueError, match="stop_m"):
        ExpertConfig(stop_m=2.5)
    with pytest.raises(ValueError, match="human_lookahead_steps"):
        ExpertConfig(human_lookahead_steps=(5, 10))


def test_expert_config_takes_any_sequence_of_lookahead_steps_as_a_hashable_tuple():
    # The config is a static argument of the jitted expert step (envs.agents.expert): hashed.
    listed = ExpertConfig(human_lookahead_steps=[0, 5, 10])
    assert listed == ExpertConfig(human_lookahead_steps=(0, 5, 10)) and listed.human_lookahead_steps == (0, 5, 10)
    assert hash(listed) == hash(ExpertConfig(human_lookahead_steps=(0, 5, 10)))
