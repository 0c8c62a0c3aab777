"""The fast caster against mujoco.mjx.ray on generated scenes, random poses, with the human."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import ConavEnv, EnvConfig, SensorConfig
from envs.mjcf import UD
from envs.panorama import front_view, ray_angles

RES = SensorConfig(height=12, width=48)


@pytest.fixture(scope="module")
def envs_pair(tiny_data):
    fast = ConavEnv(tiny_data, "train", EnvConfig(sensor=RES))
    ref = ConavEnv(tiny_data, "train", EnvConfig(sensor=SensorConfig(height=12, width=48, kind="reference")))
    return fast, ref


def _random_states(env, n, seed):
    """States at random free poses in random episodes at random times, human in view often."""
    rng = np.random.default_rng(seed)
    reset = jax.jit(env.reset_to_episode)
    out = []
    for _ in range(n):
        ep = int(rng.integers(env.num_episodes))
        s = reset(jax.random.PRNGKey(0), ep)
        t = int(rng.integers(0, int(env.bank.t_end[ep])))
        human = np.asarray(env.bank.root_xy[ep, t])
        # Near the human half of the time, so capsules are in the picture.
        # Only poses the robot can occupy (its centre in a free cell of the inflated grid).
        grid = env.split.navs[int(env.bank.scene_index[ep])].grid
        xy = np.asarray(env.bank.robot_start[ep, :2])
        for _ in range(100):
            if rng.random() < 0.5:
                ang = rng.uniform(-np.pi, np.pi)
                cand = human + rng.uniform(0.7, 2.0) * np.array([np.cos(ang), np.sin(ang)])
            else:
                cand = xy + rng.uniform(-1, 1, 2)
            if grid.is_free(cand):
                xy = cand
                break
        d = s.pipeline_state
        ud = d.userdata.at[UD["t"]].set(t)
        qpos = jnp.array([xy[0], xy[1], rng.uniform(-np.pi, np.pi)], jnp.float32)
        d = env._pose_human(d.replace(qpos=qpos, userdata=ud), jnp.int32(ep), jnp.int32(t))
        out.append((ep, d))
    return out


def test_fast_caster_matches_mjx_ray(envs_pair):
    fast, ref = envs_pair

    def both(ep, d):
        m = fast._episode_model(ep, d.qpos[:2])
        return fast.panorama(m, d, ep), ref.panorama(m, d, ep)

    both = jax.jit(both)
    depth_err, same_id, human_px = [], [], 0
    for ep, d in _random_states(fast, 12, seed=1):
        (df, idf), (dr, idr) = both(jnp.int32(ep), d)
        depth_err.append(np.abs(np.asarray(df) - np.asarray(dr)).ravel())
        same_id.append((np.asarray(idf) == np.asarray(idr)).ravel())
        human_px += int((np.asarray(idr) >= fast.layout.human_start).sum())
    err = np.concatenate(depth_err)
    same = np.concatenate(same_id)
    assert human_px > 0, "the human must appear in some test panoramas"
    # Stated tolerance: depth within 1 mm on 99.5% of pixels, ids equal on 99.5%; the rest are
    # edge pixels where a ray grazes two surfaces.
    assert np.mean(err < 1e-3) >= 0.995, np.quantile(err, [0.5, 0.99, 1.0])
    assert np.mean(same) >= 0.995
    assert np.median(err) < 1e-4


def test_panorama_layout_centre_column_faces_forward():
    az, el = ray_angles(SensorConfig(height=8, width=32))
    assert abs(az[15] + az[16]) < 1e-6 and abs(az[15]) < 2 * np.pi / 32
    assert el[0] > 0 > el[-1] and abs(el[0] - np.pi / 4 + np.pi / 32) < 1e-6  # 90 deg fov
    x = jnp.zeros((8, 32, 4)).at[:, 12:20].set(1.0)
    np.testing.assert_array_equal(np.asarray(front_view(x)), 1.0)
