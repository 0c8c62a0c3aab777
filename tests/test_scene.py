"""Scene JSON format: round trip and every rejection names its field."""

import copy
import json

import numpy as np
import pytest

from conav_jax.config import SceneGenConfig
from conav_jax.scene import SceneFormatError, load_scene, scene_from_json_dict, scene_boxes
from conav_jax.scenegen import generate_scene


def _minimal():
    return {
        "format": "conav-scene",
        "version": 1,
        "name": "hand_made",
        "bounds_m": [0, 0, 6, 4],
        "wall_height_m": 2.5,
        "rooms": [{"type": "kitchen", "rect_m": [0, 0, 6, 4]}],
        "walls": [{"center_m": [3, 0.05, 1.25], "half_extents_m": [3, 0.05, 1.25]}],
        "objects": [
            {"category": "fridge", "center_m": [1, 0.5, 0.9], "size_m": [0.8, 0.7, 1.8], "yaw_deg": 90, "room": 0},
            {"category": "table", "center_m": [4, 2, 0.375], "size_m": [1.4, 0.9, 0.75], "yaw_deg": 0, "room": 0},
        ],
    }


def test_hand_made_scene_loads_with_category_colour_default(tmp_path):
    p = tmp_path / "s.json"
    p.write_text(json.dumps(_minimal()))
    s = load_scene(p)
    assert [o.category for o in s.objects] == ["fridge", "table"]
    assert s.objects[0].rgb == (235, 235, 240)
    # yaw 90: depth 0.7 runs along y
    assert s.objects[0].box.half_extents == pytest.approx((0.4, 0.35, 0.9))
    x, y, face = s.objects[0].standing_pose(0.45)
    assert (x, y) == pytest.approx((1.0, 0.5 + 0.35 + 0.45))
    assert face == pytest.approx(-np.pi / 2)


def test_generated_scene_round_trips_through_json(tmp_path):
    s = generate_scene(np.random.default_rng(3), SceneGenConfig(), "apt")
    p = tmp_path / "apt.json"
    p.write_text(json.dumps(s.to_json_dict()))
    assert load_scene(p) == s
    boxes = scene_boxes(s, robot_height_m=1.25)
    assert boxes.center.shape == (len(s.walls) + len(s.objects), 3)
    # carpets and ceiling lamps never block the robot
    cats = {o.category: b for o, b in zip(s.objects, boxes.blocks_robot[len(s.walls):])}
    assert not cats.get("carpet", False) and not cats.get("ceiling_lamp", False)


def _mutated(path, value):
    d = copy.deepcopy(_minimal())
    target = d
    for k in path[:-1]:
        target = target[k]
    if value is KeyError:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return d


@pytest.mark.parametrize(
    "path, value, message",
    [
        (("objects", 0, "category"), "hovercraft", "objects[0].category: unknown category 'hovercraft'"),
        (("objects", 1, "center_m"), KeyError, "objects[1]: missing field 'center_m'"),
        (("name",), KeyError, "missing field 'name'"),
        (("objects", 0, "yaw_deg"), 45, "objects[0].yaw_deg: must be a multiple of 90"),
        (("objects", 0, "size_m"), [1, -1, 1], "objects[0].size_m: must be positive"),
        (("objects", 0, "center_m"), [1, "a", 1], "objects[0].center_m: expected finite numbers"),
        (("objects", 1, "center_m"), [5.9, 2, 0.375], "objects[1] (table): footprint lies outside bounds_m"),
        (("objects", 1, "center_m"), [1.2, 0.8, 0.375], "objects[1] (table): overlaps objects[0] (fridge)"),
        (("objects", 0, "center_m"), [1, 0.42, 0.9], "objects[0] (fridge): overlaps walls[0]"),
        (("objects", 0, "room"), 3, "objects[0].room: must be -1 or an index into rooms"),
        (("rooms", 0, "type"), "ballroom", "rooms[0].type: unknown room type 'ballroom'"),
        (("version",), 7, "unsupported 'version' 7"),
        (("objects", 0, "rgb"), [300, 0, 0], "objects[0].rgb: expected three integers 0-255"),
    ],
)
def test_loader_rejects_bad_scene_naming_the_field(path, value, message):
    with pytest.raises(SceneFormatError) as e:
        scene_from_json_dict(_mutated(path, value), source="s")
    assert message in str(e.value)


def test_loader_reports_missing_file_and_bad_json(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_scene(tmp_path / "nope.json")
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(SceneFormatError, match="not valid JSON"):
        load_scene(p)


def test_generator_is_deterministic():
    a = generate_scene(np.random.default_rng(11), SceneGenConfig(), "x")
    b = generate_scene(np.random.default_rng(11), SceneGenConfig(), "x")
    assert a == b
