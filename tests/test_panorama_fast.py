"""The fused caster (both ways of writing its min) and its Pallas kernel (interpreted on CPU,
compiled on a GPU) against each other and against mujoco.mjx.ray: through ConavEnv in the
hand-built hall with the humanoid close to the camera, around it and inside it, and on a
SceneGeometry built by hand, with and without capsules, next to an MJCF model of the same shapes."""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from worlds import make_split

from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.mjcf import UD
from conav_jax.data.materials import Material
from conav_jax.envs.panorama import SceneGeometry, caster_for, fast_depth_ids, reference_depth_ids, shade
from conav_jax.envs.panorama_pallas import pallas_depth_ids

RES = dict(resolution=(16, 64))
T = 15  # the human walks along y = 2 through the middle of the hall
# (x, y, yaw): facing the human from 1-2 m, beside it, from behind, a corner, and the camera
# beside the torso, inside the arms' bounding circles (their culling cannot skip any column).
POSES = [(5.0, 3.2, -1.57), (3.6, 2.0, 0.3), (6.4, 1.1, 2.2), (0.9, 0.9, 0.8), (5.0, 2.3, 1.0), (4.6, 2.4, -0.5)]
KINDS = {
    "unroll": dict(kind="fast", fast_min="unroll"),
    "reduce": dict(kind="fast", fast_min="reduce"),
    # On a GPU the Triton kernel itself runs (compiled); elsewhere Pallas interprets it.
    "pallas": dict(kind="pallas", pallas_block_w=8, pallas_interpret=jax.default_backend() != "gpu"),
    "reference": dict(kind="reference"),
}


@pytest.fixture(scope="module")
def images():
    split = make_split([(1.5, 2.0, 0.0)], t_arrive=20, t_end=40)
    envs = {k: ConavEnv(episodes=split, config=EnvConfig(sensor=SensorConfig(**RES, **kw))) for k, kw in KINDS.items()}
    env = envs["unroll"]
    ep = jnp.int32(0)
    d0 = jax.jit(env.reset_to_episode)(jax.random.PRNGKey(0), ep).pipeline_state
    human_x = float(env.bank.root_xy[0, T, 0])
    states = []
    for x, y, yaw in POSES:
        qpos = jnp.array([x - 5.0 + human_x, y, yaw], jnp.float32)
        d = d0.replace(qpos=qpos, userdata=d0.userdata.at[UD["t"]].set(T))
        states.append(env._pose_human(d, ep, jnp.int32(T)))
    out = {}
    for k, e in envs.items():
        # The panorama in the instance materials: depth, ids, and the shaded RGB.
        f = jax.jit(lambda d, e=e: e.render(d, ep))
        out[k] = [(rgbd[..., 3], ids, rgbd[..., :3]) for rgbd, ids in (jax.tree.map(np.asarray, f(d)) for d in states)]
    return out, env.layout.human_start


def _stack(images, kind):
    depth = np.stack([d for d, _, _ in images[kind]])
    ids = np.stack([i for _, i, _ in images[kind]])
    return depth, ids


@pytest.mark.parametrize("kind", ["reduce", "pallas", "reference"])
def test_casters_agree_on_the_shaded_colours(images, kind):
    imgs, _ = images
    rgb = np.stack([c for _, _, c in imgs["unroll"]])
    other = np.stack([c for _, _, c in imgs[kind]])
    # Patterns and shading are smooth in the hit point: depths micrometres apart shade alike.
    assert np.abs(rgb - other).max() < 1.0 / 255.0, np.abs(rgb - other).max()
    assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 50  # patterned and shaded, not flat


def test_humanoid_is_in_view(images):
    imgs, human = images
    _, ids = _stack(imgs, "reference")
    per_image = (ids >= human).sum(axis=(1, 2))
    assert (per_image > 0).sum() >= 4, per_image


@pytest.mark.parametrize("kind", ["reduce", "pallas"])
def test_other_forms_agree_with_fast(images, kind):
    imgs, human = images
    d_new, i_new = _stack(imgs, "unroll")
    d, i = _stack(imgs, kind)
    np.testing.assert_array_equal(i, i_new)
    # Same arithmetic; only where the compiler contracts a multiply-add into an FMA may the
    # capsule depths differ in the last bits. Boxes and floor have no such chains: identical.
    assert np.abs(d - d_new).max() < 1e-4
    scene = i < human
    np.testing.assert_array_equal(d[scene], d_new[scene])


def test_fast_matches_mjx_ray(images):
    imgs, human = images
    d_new, i_new = _stack(imgs, "unroll")
    d_ref, i_ref = _stack(imgs, "reference")
    err = np.abs(d_new - d_ref)
    # Edge pixels where a ray grazes two surfaces could differ; none do in these images. (A
    # camera inside a capsule is left out: mjx.ray reports the capsule from inside, we do not.)
    assert err.max() < 1e-3, np.quantile(err, [0.5, 0.99, 1.0])
    np.testing.assert_array_equal(i_new, i_ref)
    assert np.median(err[i_ref >= human]) < 1e-4


# -- casters over a SceneGeometry built by hand -----------------------------------------------
# Geom ids as MuJoCo numbers the MJCF below: floor 0, boxes 1-3, capsules 4-5. A fourth box,
# padding (box_valid False), stands right in front of the camera: no caster may see it.
BOXES_M = [
    ((3.0, -2.0, 0.0), (3.2, 2.0, 2.5)),  # a wall
    ((1.0, 0.8, 0.0), (1.8, 1.6, 0.75)),  # a table
    ((-1.5, -1.5, 0.0), (-1.0, -1.0, 2.0)),  # a pillar
]
PADDING_BOX_M = ((0.3, -0.5, 0.0), (0.5, 0.5, 2.0))
CAPSULES_M = [((1.5, -0.8, 0.2), (1.5, -0.8, 1.4), 0.15), ((-0.8, 0.9, 0.5), (-0.3, 1.3, 1.2), 0.08)]
# (x, y, z, yaw): cameras looking at the boxes and capsules from several sides.
CAMERAS = [(0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 1.0, 2.4), (2.2, -0.5, 0.6, -1.0), (0.8, -1.6, 1.2, 1.9)]
GEOMETRY_RES = dict(resolution=(16, 64))
# Materials by geom id: the floor in value noise, the boxes striped, checked and noisy at the
# shortest period drawn, the padding box and the capsules plain.
MATERIALS = jnp.asarray(np.stack([
    Material((150, 115, 80), (90, 60, 35), "noise", 0.3).row(),
    Material((200, 60, 50), (40, 110, 100), "stripes", 0.3, 30.0).row(),
    Material((235, 190, 60), (30, 30, 35), "checks", 0.3, 60.0).row(),
    Material((60, 150, 190), (240, 235, 220), "noise", 0.3, 10.0).row(),
    *[Material((220, 170, 135), (220, 170, 135)).row()] * 3,
]))


def _geometry(with_capsules: bool) -> SceneGeometry:
    lo = np.array([b[0] for b in BOXES_M] + [PADDING_BOX_M[0]], np.float32)
    hi = np.array([b[1] for b in BOXES_M] + [PADDING_BOX_M[1]], np.float32)
    caps = CAPSULES_M if with_capsules else []
    return SceneGeometry(
        box_lo_m=jnp.asarray(lo),
        box_hi_m=jnp.asarray(hi),
        box_ids=jnp.array([1, 2, 3, 6], jnp.int32),
        box_valid=jnp.array([True, True, True, False]),
        capsule_p0_m=jnp.asarray(np.array([c[0] for c in caps], np.float32).reshape(-1, 3)),
        capsule_p1_m=jnp.asarray(np.array([c[1] for c in caps], np.float32).reshape(-1, 3)),
        capsule_radius_m=jnp.asarray(np.array([c[2] for c in caps], np.float32)),
        capsule_ids=jnp.arange(4, 4 + len(caps), dtype=jnp.int32),
        floor_id=0,
    )


def _mjcf(with_capsules: bool) -> str:
    geoms = ['<geom type="plane" size="0 0 1"/>']
    for lo, hi in BOXES_M:
        c = " ".join(str((a + b) / 2) for a, b in zip(lo, hi))
        h = " ".join(str((b - a) / 2) for a, b in zip(lo, hi))
        geoms.append(f'<geom type="box" pos="{c}" size="{h}"/>')
    for p0, p1, r in CAPSULES_M if with_capsules else []:
        geoms.append(f'<geom type="capsule" fromto="{" ".join(map(str, p0 + p1))}" size="{r}"/>')
    # MJX's kinematics needs a degree of freedom (a body with no geom, invisible to rays) and
    # mjx.ray a material table (it reads geoms' material alpha even where none is used).
    body = '<body><joint type="slide"/><inertial pos="0 0 0" mass="1" diaginertia="1 1 1"/></body>'
    asset = '<asset><material name="unused" rgba="1 1 1 1"/></asset>'
    return f"<mujoco>{asset}<worldbody>{''.join(geoms)}{body}</worldbody></mujoco>"


@pytest.fixture(scope="module", params=[True, False], ids=["with_capsules", "boxes_only"])
def geometry_images(request):
    """Panoramas (depth, ids), stacked over CAMERAS, per caster, of one hand-built geometry."""
    with_capsules = request.param
    geometry = _geometry(with_capsules)
    casters = {
        "unroll": (fast_depth_ids, SensorConfig(**GEOMETRY_RES, kind="fast", fast_min="unroll")),
        "reduce": (fast_depth_ids, SensorConfig(**GEOMETRY_RES, kind="fast", fast_min="reduce")),
        "pallas": (pallas_depth_ids, SensorConfig(**GEOMETRY_RES, kind="pallas", pallas_block_w=8,
                                                  pallas_interpret=jax.default_backend() != "gpu")),
    }
    out = {}

    def shaded(cfg, cam, yaw, depth_ids):
        return (*depth_ids, shade(cfg, cam, yaw, *depth_ids, geometry, MATERIALS)[..., :3])

    for name, (caster, cfg) in casters.items():
        f = jax.jit(lambda cam, yaw, caster=caster, cfg=cfg: shaded(cfg, cam, yaw, caster(cfg, cam, yaw, geometry)))
        shots = [f(jnp.array(c[:3], jnp.float32), jnp.float32(c[3])) for c in CAMERAS]
        out[name] = tuple(np.stack([np.asarray(x[i]) for x in shots]) for i in range(3))
    m = mjx.put_model(mujoco.MjModel.from_xml_string(_mjcf(with_capsules)))
    d = mjx.make_data(m)
    cfg = SensorConfig(**GEOMETRY_RES, kind="reference")
    ref = jax.jit(lambda cam, yaw: shaded(cfg, cam, yaw, reference_depth_ids(cfg, m, d, cam, yaw, -1)))
    shots = [ref(jnp.array(c[:3], jnp.float32), jnp.float32(c[3])) for c in CAMERAS]
    out["reference"] = tuple(np.stack([np.asarray(x[i]) for x in shots]) for i in range(3))
    return out, with_capsules


def test_scene_geometry_casters_agree_with_each_other_and_mjx_ray(geometry_images):
    imgs, with_capsules = geometry_images
    depth, ids, rgb = imgs["unroll"]
    seen = set(np.unique(ids).tolist())
    assert {-1, 0, 1, 2, 3} <= seen and 6 not in seen, seen  # sky, floor, every box; no padding
    assert ({4, 5} <= seen) == with_capsules, seen
    for kind in ("reduce", "pallas", "reference"):
        assert np.abs(imgs[kind][2] - rgb).max() < 1.0 / 255.0, kind  # patterns and shading as the hits
    for kind in ("reduce", "pallas"):
        d, i, _ = imgs[kind]
        np.testing.assert_array_equal(i, ids, err_msg=kind)
        # Same arithmetic: boxes and floor bit for bit, capsules up to FMA contraction.
        np.testing.assert_array_equal(d[i < 4], depth[ids < 4], err_msg=kind)
        assert np.abs(d - depth).max() < 1e-4, kind
    d_ref, i_ref, _ = imgs["reference"]
    np.testing.assert_array_equal(ids, i_ref)
    assert np.abs(depth - d_ref).max() < 1e-3, np.quantile(np.abs(depth - d_ref), [0.5, 0.99, 1.0])


def test_caster_for_picks_the_kind_and_refuses_the_reference():
    assert caster_for("fast") is fast_depth_ids
    assert caster_for("pallas") is pallas_depth_ids
    assert caster_for("auto") in (fast_depth_ids, pallas_depth_ids)
    with pytest.raises(ValueError, match="mjx.ray"):
        caster_for("reference")


def test_pallas_colours_in_a_kernel_of_its_own_with_the_xla_colours():
    geometry = _geometry(True)
    cfg = SensorConfig(**GEOMETRY_RES, kind="pallas", pallas_block_w=8,
                       pallas_interpret=jax.default_backend() != "gpu")
    xla = dataclasses.replace(cfg, pallas_shade=False)
    for x, y, z, yaw in CAMERAS[:2]:
        cam = jnp.array([x, y, z], jnp.float32)
        depth, ids = pallas_depth_ids(cfg, cam, jnp.float32(yaw), geometry)
        colour = lambda c: shade(c, cam, jnp.float32(yaw), depth, ids, geometry, MATERIALS)
        assert "panorama_shade" in str(jax.make_jaxpr(lambda: colour(cfg))())
        assert "panorama_shade" not in str(jax.make_jaxpr(lambda: colour(xla))())
        kernel, reference = np.asarray(jax.jit(lambda: colour(cfg))()), np.asarray(jax.jit(lambda: colour(xla))())
        np.testing.assert_array_equal(kernel[..., 3], np.asarray(depth))
        # The same per-pixel function: only float rounding (FMA contraction) may differ.
        assert np.abs(kernel - reference).max() < 1e-4
