"""The fast caster against mujoco.mjx.ray on generated scenes, random poses, with the human;
the panorama's ray layout; the depth / geom id keys the casters take their min over."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.mjcf import UD
from conav_jax.envs.panorama import (
    NO_HIT_KEY,
    front_view,
    pack_depth_id,
    ray_angles,
    unpack_depth_id,
)

RES = SensorConfig(resolution=(12, 48))


@pytest.fixture(scope="module")
def envs_pair(tiny_data):
    fast = ConavEnv(tiny_data, "train", EnvConfig(sensor=RES))
    ref = ConavEnv(tiny_data, "train", EnvConfig(sensor=SensorConfig(resolution=(12, 48), kind="reference")))
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


def test_reference_sensor_runs_its_geometry_at_full_float32_precision(envs_pair):
    """Every matrix product of the reference panorama (kinematics and rays) asks for HIGHEST
    precision: on GPUs the default, TF32, puts millimetres of error on depths of a few metres."""
    import re

    _, ref = envs_pair
    d = jax.jit(ref.reset_to_episode)(jax.random.PRNGKey(0), 0).pipeline_state
    text = jax.jit(lambda d: ref.panorama(d, jnp.int32(0))).lower(d).as_text()
    dots = re.findall(r"stablehlo.dot_general[^\n]*", text)
    assert dots and all("precision = [HIGHEST, HIGHEST]" in x for x in dots), len(dots)


def test_fast_caster_matches_mjx_ray(envs_pair):
    fast, ref = envs_pair

    def both(ep, d):
        return fast.panorama(d, ep), ref.panorama(d, ep)

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
    az, el = ray_angles(SensorConfig(resolution=(8, 32)))
    assert abs(az[15] + az[16]) < 1e-6 and abs(az[15]) < 2 * np.pi / 32
    assert el[0] > 0 > el[-1] and abs(el[0] - np.pi / 4 + np.pi / 32) < 1e-6  # 90 deg fov
    x = jnp.zeros((8, 32, 4)).at[:, 12:20].set(1.0)
    np.testing.assert_array_equal(np.asarray(front_view(x)), 1.0)


@pytest.mark.parametrize("max_depth_m", [10.0, 8.0, 3.5])
def test_depth_id_keys_round_trip(max_depth_m):
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.0, max_depth_m, 4096).astype(np.float32)
    depth[:3] = [0.0, np.nextafter(np.float32(max_depth_m), np.float32(0)), max_depth_m / 2]
    ids = rng.integers(0, 256, 4096).astype(np.int32)
    key = pack_depth_id(jnp.asarray(depth), jnp.asarray(ids), max_depth_m)
    assert key.dtype == jnp.uint32
    d, i = unpack_depth_id(key, max_depth_m)
    np.testing.assert_array_equal(np.asarray(i), ids)
    # Half a quantum from the bin's centre, one more for float32 rounding of depth * quanta/m,
    # and the float32 spacing of the result.
    quantum_m = max_depth_m / ((1 << 24) - 2)
    err = np.abs(np.asarray(d) - depth)
    assert (err <= 1.5 * quantum_m + np.spacing(depth)).all(), err.max()


def test_depth_id_keys_order_as_depth_then_id():
    max_depth_m = 10.0
    depth = np.sort(np.random.default_rng(1).uniform(0.0, 9.99, 512).astype(np.float32))
    depth = depth[np.diff(depth, prepend=-1.0) > 1e-5]  # distinct beyond a quantum
    # The nearer hit has the larger id: the order must come from depth, not from id.
    ids = np.arange(len(depth))[::-1] % 256
    key = np.asarray(pack_depth_id(jnp.asarray(depth), jnp.asarray(ids, jnp.int32), max_depth_m))
    assert (np.diff(key.astype(np.int64)) > 0).all()
    # Equal depths: the lower id wins the min.
    tie = np.asarray(pack_depth_id(jnp.full(2, 3.0), jnp.array([7, 5]), max_depth_m))
    assert tie[1] < tie[0]
    # A min over geoms' keys is the nearest hit with its id.
    stack = pack_depth_id(jnp.array([[4.0, 9.0], [2.5, np.inf], [6.0, 1.0]]), jnp.array([[3], [200], [9]]), max_depth_m)
    d, i = unpack_depth_id(jnp.min(stack, axis=0), max_depth_m)
    np.testing.assert_array_equal(np.asarray(i), [200, 9])
    np.testing.assert_allclose(np.asarray(d), [2.5, 1.0], atol=1e-5)


@pytest.mark.parametrize("max_depth_m", [10.0, 8.0, 3.5])
def test_depths_at_or_beyond_max_depth_pack_to_no_hit(max_depth_m):
    below = np.nextafter(np.float32(max_depth_m), np.float32(0))
    depth = jnp.array([below, max_depth_m, np.nextafter(np.float32(max_depth_m), np.float32(np.inf)), 1e9, np.inf])
    key = np.asarray(pack_depth_id(depth, jnp.full(5, 255), max_depth_m))
    # The last float32 below max_depth is still a hit, and its key (with the largest id) is
    # below NO_HIT_KEY, so any hit wins a min against a miss.
    assert key[0] < NO_HIT_KEY
    np.testing.assert_array_equal(key[1:], NO_HIT_KEY)
    d, i = unpack_depth_id(jnp.asarray(key), max_depth_m)
    np.testing.assert_array_equal(np.asarray(i), [255, -1, -1, -1, -1])
    np.testing.assert_array_equal(np.asarray(d)[1:], max_depth_m)


def test_the_panorama_size_is_one_field_read_as_height_and_width():
    cfg = SensorConfig(resolution=[16, 64])  # as read back from JSON
    assert cfg.resolution == (16, 64) and (cfg.height, cfg.width) == (16, 64)
    assert hash(cfg) == hash(SensorConfig(resolution=(16, 64)))  # a static argument of jit
    for wrong in ((16, 64, 3), 16):  # SensorConfig(16, 64) reads 16 as the resolution: refused
        with pytest.raises(ValueError, match=r"resolution is \(height, width\)"):
            SensorConfig(resolution=wrong)
    with pytest.raises(ValueError, match="width a multiple of 8"):
        SensorConfig(resolution=(16, 60))
