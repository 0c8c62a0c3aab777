"""Instance materials: drawn per instance from the scene's seed, stored in the scene JSON, and
shaded by the surface normal (envs.panorama.shade); `segmentation` and `flat` in the env."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.base import State
from worlds import make_split

from conav_jax.config import SceneGenConfig
from conav_jax.data.categories import CATEGORIES, FLOOR_RGB
from conav_jax.data.materials import MATERIAL_WIDTH, Material, clothing_rgb
from conav_jax.data.scene import default_materials, scene_boxes, scene_from_json_dict
from conav_jax.data.scenegen import generate_scene
from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.bench import with_materials
from conav_jax.envs.panorama import SKY_RGB, SceneGeometry, fast_depth_ids, shade


def _scene(seed: int, name: str = "apt"):
    return generate_scene(np.random.default_rng(seed), SceneGenConfig(), name)


def test_instances_of_a_category_differ_and_categories_share_colours():
    same_cat_differ = share_across_cats = False
    for seed in range(4):
        scene = _scene(seed)
        pairs = list(zip(scene.objects, scene.materials.objects))
        for i, (a, ma) in enumerate(pairs):
            for b, mb in pairs[:i]:
                same_cat_differ |= a.category == b.category and ma != mb
                share_across_cats |= a.category != b.category and ma.rgb == mb.rgb
    assert same_cat_differ and share_across_cats


def test_materials_follow_the_seed_and_survive_the_json_round_trip():
    a, b, other = _scene(3), _scene(3), _scene(4)
    assert a.materials == b.materials and a.materials != other.materials
    assert len({_scene(seed).materials.walls for seed in range(4)}) > 1  # drawn from each scene's seed
    assert {m.pattern for m in a.materials.objects} == {"stripes", "checks", "noise"}
    back = scene_from_json_dict(json.loads(json.dumps(a.to_json_dict())))
    assert back == a
    rows = scene_boxes(back, 1.25).material
    assert rows.shape == (len(a.walls) + len(a.objects), MATERIAL_WIDTH)
    np.testing.assert_array_equal(rows[-1], a.materials.objects[-1].row())


def test_scene_json_without_materials_draws_them_from_its_name():
    d = _scene(5, "old_apt").to_json_dict()
    del d["materials"]
    for o in d["objects"]:
        del o["material"]
    d["objects"][0]["material"] = {"rgb": [1, 2, 3], "pattern": "stripes", "period_m": 0.4}  # a user's own
    s = scene_from_json_dict(d)
    drawn = default_materials("old_apt", s.objects)
    assert s.materials.objects[0] == Material((1, 2, 3), (1, 2, 3), "stripes", 0.4, 0.0)
    assert s.materials.objects[1:] == drawn.objects[1:] and s.materials.floor == drawn.floor
    assert scene_from_json_dict(d) == s
    d["objects"][0]["material"]["pattern"] = "zigzag"
    with pytest.raises(ValueError, match=r"objects\[0\]\.material\.pattern"):
        scene_from_json_dict(d)


def test_clothing_is_a_function_of_the_episode():
    a = clothing_rgb(np.arange(50))
    np.testing.assert_array_equal(a, clothing_rgb(np.arange(50)))
    assert len({tuple(x.ravel()) for x in a}) > 40 and (a[:, 1] != a[:, 2]).any(axis=-1).all()


# -- shading ----------------------------------------------------------------------------------
RES = SensorConfig(resolution=(8, 32), kind="fast")
PLAIN = Material((200, 100, 50), (200, 100, 50)).row()


def _box_geometry(lo, hi) -> SceneGeometry:
    empty = jnp.zeros((0, 3))
    return SceneGeometry(jnp.asarray([lo], jnp.float32), jnp.asarray([hi], jnp.float32), jnp.array([1]),
                         jnp.array([True]), empty, empty, jnp.zeros((0,)), jnp.zeros((0,), jnp.int32), 0)


@jax.jit
def _centre_pixel(cam, yaw, lo, hi):
    """The colour and geom id of the forward pixel just below the horizon of a plain box."""
    geometry = _box_geometry(lo, hi)
    depth, ids = fast_depth_ids(RES, cam, yaw, geometry)
    table = jnp.stack([jnp.asarray(PLAIN)] * 2)
    rgbd = shade(RES, cam, yaw, depth, ids, geometry, table)
    return rgbd[RES.height // 2, RES.width // 2], ids[RES.height // 2, RES.width // 2]


def test_shading_follows_the_surface_normal_not_the_distance():
    lo, hi = jnp.array([2.0, -1.0, 0.0]), jnp.array([3.0, 1.0, 2.0])
    near, i1 = _centre_pixel(jnp.array([4.5, 0.0, 1.0]), np.pi, lo, hi)  # the +x face from 1.5 m
    far, i2 = _centre_pixel(jnp.array([8.0, 0.0, 1.0]), np.pi, lo, hi)  # the same face from 5 m
    side, i3 = _centre_pixel(jnp.array([2.5, 3.0, 1.0]), -np.pi / 2, lo, hi)  # the +y face
    assert int(i1) == int(i2) == int(i3) == 1
    np.testing.assert_allclose(near[:3], far[:3], atol=1e-6)
    assert near[3] < far[3]
    assert np.abs(np.asarray(near[:3]) - np.asarray(side[:3])).max() > 0.02
    # The same colour scaled: shading darkens, it does not tint.
    np.testing.assert_allclose(near[:3] / near[0], side[:3] / side[0], rtol=1e-5)


def test_rows_coloured_in_blocks_or_at_once_give_the_same_colours(monkeypatch):
    from conav_jax.envs import panorama

    res = SensorConfig(resolution=(32, 64), kind="fast")
    lo, hi = jnp.array([[2.0, -1.0, 0.0]]), jnp.array([[3.0, 1.0, 2.0]])
    geometry = _box_geometry(lo[0], hi[0])
    cam, yaw = jnp.array([4.5, 0.5, 1.0]), jnp.float32(np.pi - 0.3)
    depth, ids = fast_depth_ids(res, cam, yaw, geometry)
    table = jnp.stack([jnp.asarray(PLAIN)] * 2)

    def colours():
        program = jax.make_jaxpr(lambda: shade(res, cam, yaw, depth, ids, geometry, table))()
        loops = [e for e in program.jaxpr.eqns if e.primitive.name in ("scan", "while")]
        return np.asarray(jax.jit(lambda: shade(res, cam, yaw, depth, ids, geometry, table))()), loops

    # On the CPU a panorama is coloured at once (no loop over blocks of rows) ...
    whole, loops = colours()
    assert jax.default_backend() == "cpu" and loops == []
    # ... on an accelerator SHADE_BLOCK_ROWS at a time; the colours are the same.
    monkeypatch.setattr(panorama, "_row_block", lambda height, backend: panorama.SHADE_BLOCK_ROWS)
    blocked, loops = colours()
    assert len(loops) == 1 and (ids >= 0).any() and (ids < 0).any()
    np.testing.assert_allclose(blocked, whole, atol=1e-6, rtol=0)


# -- in the env: segmentation, flat colours ------------------------------------------------------


@pytest.fixture(scope="module")
def observed():
    """(env, {materials: (observation, geom ids)}) of one hall episode's first step."""
    split = make_split([(7.5, 2.0, 0.0)], t_arrive=20, t_end=40)  # the table ahead, the fridge behind
    env = ConavEnv(episodes=split, config=EnvConfig(sensor=SensorConfig(resolution=(16, 64))))
    # The episode's start, without the physics' forward pass (the sensor reads positions only).
    state = State(env._data0.replace(qpos=env.bank.robot_start[0]), {}, jnp.zeros(()), jnp.zeros(()), {},
                  {"episode": jnp.int32(0)})
    out = {}
    for materials in ("instance", "flat"):
        e = with_materials(env, materials)
        out[materials] = jax.tree.map(np.asarray, jax.jit(
            lambda s, e=e: (e.observe(s, ("rgbd", "segmentation")).obs, e.render(s.pipeline_state, 0)[1]))(state))
    return env, out


def test_segmentation_is_the_category_of_each_hit_box(observed):
    env, out = observed
    boxes = scene_boxes(env.split.scenes[0], env.task.robot_height_m)
    blocking, visual = boxes.category[boxes.blocks_robot], boxes.category[~boxes.blocks_robot]
    for obs, ids in out.values():
        expected = np.full(ids.shape, -1)
        for start, cats in ((env.layout.col_start, blocking), (env.layout.vis_start, visual)):
            for k, c in enumerate(cats):
                expected[ids == start + k] = c
        np.testing.assert_array_equal(obs["segmentation"], expected)
        assert set(np.unique(expected).tolist()) == {-1, 4, 11}  # nothing, the table, the fridge


def test_flat_draws_each_category_in_its_colour_and_instance_does_not(observed):
    env, out = observed
    (flat, ids), (shaded, _) = out["flat"], out["instance"]
    seg = flat["segmentation"]
    table = np.asarray([c.rgb for c in CATEGORIES], np.float32) / np.float32(255.0)
    objects = seg >= 0
    np.testing.assert_array_equal(flat["rgbd"][objects][:, :3], table[seg[objects]])
    floor = ids == env.layout.floor
    assert floor.any() and (ids < 0).any()
    np.testing.assert_array_equal(flat["rgbd"][floor][:, :3], np.broadcast_to(np.float32(FLOOR_RGB) / np.float32(255.0),
                                                                              (floor.sum(), 3)))
    np.testing.assert_array_equal(flat["rgbd"][ids < 0][:, :3], np.broadcast_to(SKY_RGB, ((ids < 0).sum(), 3)))
    np.testing.assert_array_equal(shaded["rgbd"][..., 3], flat["rgbd"][..., 3])  # depth as before
    assert np.abs(shaded["rgbd"][objects][:, :3] - table[seg[objects]]).max() > 0.1
