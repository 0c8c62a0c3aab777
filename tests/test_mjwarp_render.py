"""MuJoCo Warp's batch renderer (envs.mjwarp_render) against our panorama caster on the tiny
preset's val scenes: with our rays loaded into its cameras the two agree per pixel (depth along
the ray, geom ids, colours); its own pinhole cameras look where ours do; `bench_render` and
`conav bench render` report their figures. Skipped without warp-lang (CI); runs on the CPU,
where Warp compiles its kernels too."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("warp")

from conav_jax.envs import ConavEnv, EnvConfig, PhysicsConfig, SensorConfig  # noqa: E402
from conav_jax.envs import mjwarp_render  # noqa: E402
from conav_jax.envs.mjcf import build_model  # noqa: E402

# Tolerances on identical rays: both cast in float32, so depths differ by rounding: below 0.3 mm
# on boxes and the floor, up to 1.6 mm where a ray grazes a capsule's silhouette (the root of a
# near-zero discriminant); a ray grazing a box's edge may hit the box in one and pass it in the
# other (1 pixel in 300k seen), which moves its depth by metres and its id.
DEPTH_SAME_ID_TOL_M = 5e-3
MISMATCH_SHARE = 1e-4


@pytest.fixture(scope="module")
def env(tiny_data):
    # Flat colours: MuJoCo Warp's renderer shows each geom's RGB, unshaded (envs.mjwarp_render).
    return ConavEnv(str(tiny_data), "val", EnvConfig(sensor=SensorConfig(kind="fast", materials="flat")))  # 112x448


def _frames(env):
    """Every val episode: start position, yaws around the circle, the humanoid mid-episode."""
    n = env.num_episodes
    episodes = jnp.arange(n)
    poses = env.bank.robot_start[episodes].at[:, 2].set(jnp.linspace(-3.1, 3.1, n))
    return episodes, poses, env.bank.t_end[episodes] // 2


def test_mjwarp_depth_and_ids_match_our_caster_on_shared_rays(env):
    frames = _frames(env)
    r = mjwarp_render.make_renderer(env, int(frames[0].shape[0]), "panorama", segmentation=True)
    agree = mjwarp_render.compare_with_caster(r, *frames)
    assert agree["share_of_panorama_compared"] == 1.0
    assert agree["geom_id_agreement"] >= 1.0 - MISMATCH_SHARE
    assert agree["depth_within_1cm"] >= 1.0 - MISMATCH_SHARE
    assert agree["depth_abs_diff_median_m"] < 1e-4
    assert agree["depth_abs_diff_max_same_id_m"] < DEPTH_SAME_ID_TOL_M
    assert agree["rgb_abs_diff_max_same_id"] <= 1.0 / 255.0 + 1e-6  # 8-bit quantisation
    # The scenes are seen: walls and furniture, the floor and some sky, not one thing.
    rgbd, ids = jax.jit(lambda e, p, t: mjwarp_render.render_panorama(r, e, p, t))(*frames)
    assert rgbd.shape == (env.num_episodes, 112, 448, 4) and len(np.unique(np.asarray(ids))) > 5


def test_pinhole_cameras_look_where_the_panorama_does(env):
    frames = _frames(env)
    r = mjwarp_render.make_renderer(env, int(frames[0].shape[0]), "pinhole", segmentation=True)
    agree = mjwarp_render.compare_with_caster(r, *frames)
    # Nearest-pixel resampling: ids differ near edges only; the corners of the panorama fall
    # outside the cameras' images.
    assert agree["geom_id_agreement"] > 0.97
    assert 0.9 < agree["share_of_panorama_compared"] < 1.0


def test_renderer_refuses_a_batch_other_than_its_context(env):
    r = mjwarp_render.make_renderer(env, 2, "panorama")
    episodes, poses, t = _frames(env)
    with pytest.raises(ValueError, match="2 worlds"):
        mjwarp_render.render_views(r, episodes[:3], poses[:3], t[:3])


def test_render_cameras_leave_the_env_model_alone(env):
    physics = PhysicsConfig(impl="jax")
    plain, _ = build_model(env.layout, env.task, physics)
    with_cams, _ = build_model(env.layout, env.task, physics, render_cameras_fovy_deg=90.0)
    assert plain.ncam == 0 and with_cams.ncam == 4
    assert plain.ngeom == with_cams.ngeom and plain.geom_group[env.layout.robot] == 0
    np.testing.assert_array_equal(np.delete(plain.geom_group, env.layout.robot),
                                  np.delete(with_cams.geom_group, env.layout.robot))
    assert with_cams.geom_group[env.layout.robot] not in mjwarp_render.RENDER_GEOM_GROUPS


def test_bench_render_reports_both_renderers(tiny_data):
    from conav_jax.envs.bench import bench_render

    small = ConavEnv(str(tiny_data), "val", EnvConfig(sensor=SensorConfig(resolution=(16, 64), kind="fast")))
    res = bench_render(small, batch=4, repeats=1, steps=1, rays=("panorama",), check_batch=4)
    for key in ("panoramas_per_s", "compile_and_first_call_s", "median_call_s", "xla_temp_bytes", "peak_bytes_in_use"):
        assert key in res["ours"] and key in res["mjwarp_panorama"], key
    mj = res["mjwarp_panorama"]
    assert mj["panoramas_per_s"] > 0 and res["ours"]["panoramas_per_s"] > 0
    assert mj["warp_context_bytes"] > 0 and mj["context_create_s"] >= 0
    assert mj["agreement"]["geom_id_agreement"] >= 1.0 - MISMATCH_SHARE
    assert {"depth_abs_diff_max_m", "depth_abs_diff_median_m", "depth_within_1cm"} <= set(mj["agreement"])


def test_bench_render_command_line():
    from conav_jax.eval.cli import build_parser

    args = build_parser().parse_args(["bench", "render", "--batch", "1024", "4096", "--resolution", "112x448",
                                      "--rays", "panorama", "--json"])
    assert args.batch == [1024, 4096] and args.resolution == [(112, 448)] and args.rays == "panorama"
    assert args.func.__name__ == "_run_bench_render" and args.data is None and args.split == "val"
