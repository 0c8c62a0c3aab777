"""The environment under brax: registry, training wrappers (vmap, episode length, auto-reset)."""

import functools

import brax.envs
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.wrappers import training

import conav_jax.envs  # noqa: F401  (registers 'conav')
from conav_jax.envs import EnvConfig, SensorConfig
from conav_jax.envs.mjcf import UD

CFG = EnvConfig(sensor=SensorConfig(resolution=(8, 32)))
# Compile time dominates on a CPU: without LLVM optimisation and XLA's fusion emitters the env's
# graph compiles several times faster (same results, slower to run).
jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0,
                                                   "xla_cpu_use_fusion_emitters": False})


@pytest.fixture(scope="module")
def wrapped(tiny_data):
    """The registered env under brax's training wrappers, with its jitted reset and step."""
    env = brax.envs.get_environment("conav", data_dir=str(tiny_data), split="train", config=CFG)
    w = training.wrap(env, episode_length=6)
    return env, jit(w.reset), jit(w.step)


def test_registered_env_runs_under_brax_training_wrappers(wrapped):
    env, reset, step = wrapped
    assert env.action_size == 2 and env.backend == "mjx"
    assert env.observation_size["rgbd"] == (8, 32, 4)
    state = reset(jax.random.split(jax.random.PRNGKey(0), 4))
    eps = np.asarray(state.info["episode"])
    assert state.obs["rgbd"].shape == (4, 8, 32, 4)
    action = jnp.tile(jnp.array([0.5, 0.2]), (4, 1))
    for k in range(8):
        state = step(state, action)
        t = np.asarray(state.pipeline_state.userdata[:, UD["t"]])
        # the episode-length wrapper ends every episode at 6 steps; auto-reset restarts it at 0
        assert (t == (k + 1) % 6).all(), (k, t)
        assert np.isfinite(np.asarray(state.obs["rgbd"])).all()
    np.testing.assert_array_equal(np.asarray(state.info["episode"]), eps)


def test_same_seed_same_bytes(wrapped):
    _, reset, step = wrapped

    def rollout(seed):
        key = jax.random.PRNGKey(seed)
        s = reset(jax.random.split(key, 4))
        frames = []
        for k in jax.random.split(key, 4):
            s = step(s, jax.random.uniform(k, (4, 2), minval=-1, maxval=1))
            frames.append(np.asarray(s.obs["rgbd"]))
        return np.stack(frames), np.asarray(s.pipeline_state.qpos)

    a, b, c = rollout(7), rollout(7), rollout(8)
    assert a[0].tobytes() == b[0].tobytes() and a[1].tobytes() == b[1].tobytes()
    assert a[1].tobytes() != c[1].tobytes()


def test_reset_to_episode_visits_the_given_episode(tiny_data):
    env = brax.envs.get_environment("conav", data_dir=str(tiny_data), split="val", config=CFG)
    reset = jit(jax.vmap(env.reset_to_episode))
    idx = jnp.arange(env.num_episodes)
    s = reset(jax.random.split(jax.random.PRNGKey(1), env.num_episodes), idx)
    np.testing.assert_array_equal(np.asarray(s.info["episode"]), np.arange(env.num_episodes))
    np.testing.assert_allclose(np.asarray(s.pipeline_state.qpos), np.asarray(env.bank.robot_start), atol=1e-6)
    # the human stands where the episode's keyframes put it at step 0
    np.testing.assert_allclose(
        np.asarray(s.pipeline_state.mocap_pos[:, 0, :2]).mean(0),
        np.asarray(jax.vmap(lambda e: env.human_joints(e, 0)[0, :2])(idx)).mean(0),
        atol=0.2,
    )
