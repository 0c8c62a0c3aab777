"""Scene JSON format: round trip and every rejection names its field."""

import copy
import json

import numpy as np
import pytest

from conav_jax.config import SceneGenConfig
from conav_jax.data.scene import (
    SceneFormatError,
    load_scene,
    scene_boxes,
    scene_from_json_dict,
)
from conav_jax.data.scenegen import generate_scene


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
        (("objects", 0, "category"), "hovercraft", "s: objects[0].category: unknown category 'hovercraft'; valid categories: "),
        (("objects", 1, "center_m"), KeyError, "s: objects[1].center_m: required field is missing"),
        (("name",), KeyError, "s: name: required field is missing"),
        (("objects", 0, "yaw_deg"), 45, "s: objects[0].yaw_deg: must be a multiple of 90"),
        (("objects", 0, "size_m"), [1, -1, 1], "s: objects[0].size_m: must be positive"),
        (("objects", 0, "center_m"), [1, "a", 1], "s: objects[0].center_m: expected finite numbers"),
        (("objects", 1, "center_m"), [5.9, 2, 0.375], "s: objects[1].center_m: table footprint x 5.450..6.350 m"),
        (("objects", 1, "center_m"), [4, 2, -0.2], "s: objects[1].center_m: table extends below the floor"),
        (("objects", 1, "center_m"), [1.2, 0.8, 0.375], "s: objects[1]: table overlaps objects[0] (fridge)"),
        (("objects", 0, "center_m"), [1, 0.42, 0.9], "s: objects[0]: fridge overlaps walls[0]"),
        (("objects", 0, "room"), 3, "s: objects[0].room: must be -1 or an index into rooms"),
        (("rooms", 0, "type"), "ballroom", "s: rooms[0].type: unknown room type 'ballroom'; valid room types: "),
        (("version",), 7, "s: version: unsupported version 7"),
        (("objects", 0, "rgb"), [300, 0, 0], "s: objects[0].rgb: expected three integers 0-255"),
        (("objects",), {}, "s: objects: expected a list"),
        (("objects", 1), "table", "s: objects[1]: expected an object, got str"),
    ],
)
def test_loader_rejects_bad_scene_naming_the_field(path, value, message):
    with pytest.raises(SceneFormatError) as e:
        scene_from_json_dict(_mutated(path, value), source="s")
    assert message in str(e.value)


def test_unknown_category_lists_every_valid_category_and_names_the_file(tmp_path):
    from conav_jax.data.categories import CATEGORY_INDEX

    d = _mutated(("objects", 1, "category"), "sofa2")
    p = tmp_path / "apt.json"
    p.write_text(json.dumps(d))
    with pytest.raises(SceneFormatError) as e:
        load_scene(p)
    assert str(e.value).startswith(f"{p}: objects[1].category: unknown category 'sofa2'; valid categories: ")
    assert (e.value.source, e.value.field) == (str(p), "objects[1].category")
    listed = str(e.value).split("valid categories: ", 1)[1].split(", ")
    assert sorted(listed) == sorted(CATEGORY_INDEX) and len(listed) == 51


def test_out_of_bounds_object_names_its_center_field(tmp_path):
    p = tmp_path / "apt.json"
    p.write_text(json.dumps(_mutated(("objects", 1, "center_m"), [5.9, 2, 0.375])))
    with pytest.raises(SceneFormatError) as e:
        load_scene(p)
    assert e.value.field == "objects[1].center_m"
    assert str(e.value).startswith(f"{p}: objects[1].center_m: table footprint")
    assert "lies outside bounds_m [0.0, 0.0, 6.0, 4.0]" in str(e.value)


def test_loader_reports_missing_file_and_bad_json(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_scene(tmp_path / "nope.json")
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(SceneFormatError) as e:
        load_scene(p)
    assert str(e.value).startswith(f"{p}: not valid JSON")


def test_generator_is_deterministic():
    a = generate_scene(np.random.default_rng(11), SceneGenConfig(), "x")
    b = generate_scene(np.random.default_rng(11), SceneGenConfig(), "x")
    assert a == b
