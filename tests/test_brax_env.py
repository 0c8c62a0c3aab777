"""The environment under brax: registry, training wrappers (vmap, episode length, auto-reset)."""

import brax.envs
import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.wrappers import training

import envs  # noqa: F401  (registers 'conav')
from envs import EnvConfig, SensorConfig
from envs.mjcf import UD

CFG = EnvConfig(sensor=SensorConfig(height=8, width=32))


def test_registered_env_runs_under_brax_training_wrappers(tiny_data):
    env = brax.envs.get_environment("conav", data_dir=str(tiny_data), split="train", config=CFG)
    assert env.action_size == 2 and env.backend == "mjx"
    assert env.observation_size["rgbd"] == (8, 32, 4)
    wrapped = training.wrap(env, episode_length=6)
    reset, step = jax.jit(wrapped.reset), jax.jit(wrapped.step)
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


def test_reset_to_episode_visits_the_given_episode(tiny_data):
    env = brax.envs.get_environment("conav", data_dir=str(tiny_data), split="val", config=CFG)
    reset = jax.jit(jax.vmap(env.reset_to_episode))
    idx = jnp.arange(env.num_episodes)
    s = reset(jax.random.split(jax.random.PRNGKey(1), env.num_episodes), idx)
    np.testing.assert_array_equal(np.asarray(s.info["episode"]), np.arange(env.num_episodes))
    np.testing.assert_allclose(np.asarray(s.pipeline_state.qpos), np.asarray(env.bank.robot_start), atol=1e-6)


def test_same_seed_same_bytes(tiny_data):
    env = brax.envs.get_environment("conav", data_dir=str(tiny_data), split="train", config=CFG)
    wrapped = training.wrap(env, episode_length=50)

    def rollout(key):
        s = wrapped.reset(jax.random.split(key, 3))

        def body(s, k):
            a = jax.random.uniform(k, (3, 2), minval=-1, maxval=1)
            s = wrapped.step(s, a)
            return s, s.obs["rgbd"]

        return jax.lax.scan(body, s, jax.random.split(key, 5))[1]

    run = jax.jit(rollout)
    a, b = run(jax.random.PRNGKey(7)), run(jax.random.PRNGKey(7))
    assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
