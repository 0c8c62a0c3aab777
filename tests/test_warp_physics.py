"""MJX's Warp backend (PhysicsConfig.impl="warp") against its JAX backend: the same robot motion
and contact counts under the same random drives on the tiny preset's val episodes; States that
brax's auto-reset and the evaluator's lane refill merge with jnp.where; lost contacts reported;
the implementation resolver. Skipped without warp-lang (CI); runs on the CPU, where Warp
compiles its kernels too."""

import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("warp")

from brax.envs.wrappers import training  # noqa: E402
from worlds import make_split  # noqa: E402

from conav_jax.envs import ConavEnv, EnvConfig, PhysicsConfig, SensorConfig  # noqa: E402
from conav_jax.envs.config import resolve_physics_impl  # noqa: E402
from conav_jax.envs.mjcf import UD  # noqa: E402
from conav_jax.envs.rollout import Agent, make_pool_rollout  # noqa: E402

SMALL = SensorConfig(resolution=(8, 32))
STEPS = 60


def _config(impl: str, **physics) -> EnvConfig:
    return EnvConfig(sensor=SMALL, physics=PhysicsConfig(impl=impl, **physics))


@pytest.fixture(scope="module")
def drives(tiny_data):
    """Each implementation driven by the same uniform random actions for STEPS steps from every
    val episode: {impl: (env, robot poses (STEPS, B, 3) after each step, final State)}."""
    out = {}
    for impl in ("jax", "warp"):
        env = ConavEnv(str(tiny_data), "val", _config(impl, warp_max_worlds=8))
        n = env.num_episodes
        actions = jax.random.uniform(jax.random.PRNGKey(1), (STEPS, n, 2), minval=-1.0, maxval=1.0)

        @jax.jit
        def run(actions):
            s = jax.vmap(env.reset_to_episode)(jax.random.split(jax.random.PRNGKey(0), n), jnp.arange(n))

            def body(s, a):
                s = jax.vmap(env.step)(s, a)
                return s, s.pipeline_state.qpos

            return jax.lax.scan(body, s, actions)

        state, qpos = run(actions)
        out[impl] = (env, np.asarray(qpos), state)
    return out


def test_warp_drives_the_robot_where_jax_does(drives):
    (env, q_jax, _), (env_w, q_warp, _) = drives["jax"], drives["warp"]
    assert env.config.physics.impl == "jax" and env_w.config.physics.impl == "warp"
    assert np.linalg.norm(q_warp[..., :2] - q_jax[..., :2], axis=-1).max() < 1e-3  # metres
    assert np.abs(q_warp[..., 2] - q_jax[..., 2]).max() < 1e-3  # radians


def test_warp_counts_the_same_contacts_as_jax(drives):
    m_jax, m_warp = drives["jax"][2].metrics, drives["warp"][2].metrics
    for name in ("human_contact_steps", "wall_contact_steps"):
        np.testing.assert_array_equal(np.asarray(m_warp[name]), np.asarray(m_jax[name]), err_msg=name)
    # The drives press into walls: the physics slots (placed per step) are exercised.
    assert float(np.asarray(m_jax["wall_contact_steps"]).sum()) > 0
    np.testing.assert_array_equal(np.asarray(m_warp["physics_overflow"]), 0.0)
    assert "physics_overflow" not in m_jax


def test_every_leaf_of_a_warp_state_is_per_world(drives):
    # MuJoCo Warp's all-worlds contact buffers stay out of the State: what lets brax and the
    # evaluator merge States leaf by leaf with jnp.where.
    env, _, state = drives["warp"]
    n = env.num_episodes
    shapes = {jax.tree_util.keystr(p): x.shape for p, x in jax.tree_util.tree_leaves_with_path(state)}
    assert all(s[:1] == (n,) for s in shapes.values()), {k: s for k, s in shapes.items() if s[:1] != (n,)}
    assert state.pipeline_state._impl.contact__dist is None


@pytest.fixture(scope="module")
def hall():
    """Short episodes (10 steps) in the hand-built hall on Warp, its contact buffer sized for
    one world (warp_max_worlds=1: 38 contacts in all). Episode 0 faces the south wall 0.5 m
    away; 1 faces the human at the fridge; 2 stands in the open."""
    split = make_split([(8.0, 0.9, -np.pi / 2), (2.0, 2.0, np.pi), (6.5, 2.0, 0.0)], t_arrive=6, t_end=10)
    return ConavEnv(episodes=split, config=_config("warp", warp_max_worlds=1))


def test_brax_auto_reset_restarts_warp_episodes(hall):
    w = training.wrap(hall, episode_length=4)
    reset, step = jax.jit(w.reset), jax.jit(w.step)
    state = reset(jax.random.split(jax.random.PRNGKey(0), 2))
    for k in range(6):
        state = step(state, jnp.tile(jnp.array([1.0, 0.3]), (2, 1)))
        t = np.asarray(state.pipeline_state.userdata[:, UD["t"]])
        assert (t == (k + 1) % 4).all(), (k, t)
    assert np.isfinite(np.asarray(state.pipeline_state.qpos)).all()


def test_refilled_lanes_run_warp_episodes_to_their_end(hall):
    forward = Agent("forward", lambda key, obs: (), lambda carry, obs, key: (carry, jnp.array([1.0, 0.0])), reads=())
    run = make_pool_rollout(hall, lambda _: forward, slots=2, chunk=4)  # 3 episodes on 2 lanes: one refill
    m = run(None, jax.random.PRNGKey(0), jnp.arange(3, dtype=jnp.int32), jnp.int32(3))
    m = {k: np.asarray(v) for k, v in m.items()}
    np.testing.assert_array_equal(m["t"], 10.0)  # each ran to t_end and stayed there
    assert m["wall_contact_steps"][0] > 0  # episode 0 drove into the wall ...
    np.testing.assert_array_equal(m["physics_overflow"], 0.0)  # ... with room for its contacts
    # The refilled lane restarted episode 2 from its start: 10 steps of forward driving.
    assert 0.8 < m["path_length_m"][2] < 1.0


def test_lost_contacts_are_reported(hall):
    # 24 robots pressed into the wall make 48 contacts; the buffer holds 38: MuJoCo Warp drops
    # the rest (and prints "narrowphase overflow"), and every episode's metrics say so.
    n = 24
    reset = jax.jit(jax.vmap(hall.reset_to_episode))
    full_ahead = jnp.tile(jnp.array([1.0, 0.0]), (n, 1))

    @jax.jit
    def drive(s):
        return jax.lax.scan(lambda s, _: (jax.vmap(hall.step)(s, full_ahead), None), s, None, 8)[0]

    s = drive(reset(jax.random.split(jax.random.PRNGKey(0), n), jnp.zeros(n, jnp.int32)))
    np.testing.assert_array_equal(np.asarray(s.metrics["physics_overflow"]), 1.0)


def test_physics_impl_resolves_and_is_checked(monkeypatch):
    from conav_jax.eval.cli import parse_physics_override

    assert resolve_physics_impl("jax") == "jax" and resolve_physics_impl("warp") == "warp"
    if jax.default_backend() == "cpu":
        assert resolve_physics_impl("auto") == "jax"
    with pytest.raises(ValueError, match="physics impl"):
        PhysicsConfig(impl="cuda")
    assert parse_physics_override("impl=warp") == ("impl", "warp")
    assert parse_physics_override("warp_max_worlds=4096") == ("warp_max_worlds", 4096)
    monkeypatch.setitem(sys.modules, "warp", None)  # as without warp-lang
    assert resolve_physics_impl("auto") == "jax"
    with pytest.raises(ImportError, match=r'pip install -e "\.\[warp\]"'):
        resolve_physics_impl("warp")
