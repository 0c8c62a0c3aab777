"""The shipped activity graph, its validating loader and the activity-pair sampler."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

from conav_jax.data.activities import (
    DEFAULT_GRAPH_PATH,
    NUM_ACTIVITIES,
    ActivityGraph,
    available_links,
    load_activity_graph,
    sample_activity_pair,
)
from conav_jax.data.categories import CATEGORY_INDEX, CATEGORY_NAMES
from conav_jax.motion.primitives import MOTION_PRIMITIVES

# A sample of the paper's appendix table (tab:activity): activity name -> object category.
PAPER_ACTIVITIES = {
    "a person cleans near the ceiling_lamp": "ceiling_lamp",
    "a person gardens near the potted_plant": "potted_plant",
    "a person hangs the artwork on the picture": "picture",
    "a person styles their hair in front of the mirror": "mirror",
    "a person does laundry with the washer_dryer": "washer_dryer",
    "a person does laundry in the washer_dryer": "washer_dryer",
    "a person rearranges the books in the chest_of_drawers": "chest_of_drawers",
    "a person sets up on the stand": "stand",
    "a person goes to sleep in the bed": "bed",
    "a person reads near the wall_lamp": "wall_lamp",
    "a person works on the puzzle under the floor_lamp": "floor_lamp",
    "a person selects a movie from the shelves": "shelves",
    "a person sits on the bench": "bench",
    "a person turns off the table_lamp": "table_lamp",
    "a person brews coffee in the coffee_maker": "coffee_maker",
    "a person disposes of the wrapper in the trashcan": "trashcan",
    "a person enjoys the snack on the couch": "couch",
    "a person enjoys snacks on the couch": "couch",
    "a person assembles ingredients from the fridge": "fridge",
}


@pytest.fixture(scope="module")
def graph() -> ActivityGraph:
    return load_activity_graph()


def test_shipped_graph_has_107_activities_covering_all_51_categories(graph: ActivityGraph) -> None:
    assert len(graph.activities) == NUM_ACTIVITIES == 107
    assert [a.id for a in graph.activities] == list(range(NUM_ACTIVITIES))
    assert {a.object for a in graph.activities} == set(CATEGORY_NAMES)
    assert all(a.primitive in MOTION_PRIMITIVES for a in graph.activities)
    assert all(a.name.startswith("a person ") for a in graph.activities)


def test_paper_activities_are_present_with_their_objects(graph: ActivityGraph) -> None:
    for name, obj in PAPER_ACTIVITIES.items():
        assert graph.by_name(name).object == obj, name


def test_every_activity_has_two_successors_and_a_predecessor(graph: ActivityGraph) -> None:
    out_degree = Counter(link.a for link in graph.links)
    in_degree = Counter(link.b for link in graph.links)
    assert all(out_degree[a.id] >= 2 for a in graph.activities)
    assert all(in_degree[a.id] >= 1 for a in graph.activities)
    assert 300 <= len(graph.links) <= 450
    assert all(link.reason.strip() and "\n" not in link.reason for link in graph.links)


def test_default_graph_is_loaded_once() -> None:
    assert load_activity_graph() is load_activity_graph()


def test_graph_lookups_agree(graph: ActivityGraph) -> None:
    act = graph.by_name("a person cleans near the ceiling_lamp")
    assert graph.activity(act.id) == act
    assert graph.object_of(act.id) == act.object_index == CATEGORY_INDEX["ceiling_lamp"]
    successors = graph.successors(act.id)
    assert successors and all(link.a == act.id for link in successors)
    with pytest.raises(ValueError, match="unknown activity id"):
        graph.activity(NUM_ACTIVITIES)
    with pytest.raises(ValueError, match="unknown activity name"):
        graph.by_name("a person flies")


# -- loader rejections: each breaks one thing in a copy of the shipped file ----------------


def _shipped() -> dict[str, Any]:
    return json.loads(DEFAULT_GRAPH_PATH.read_text(encoding="utf-8"))


def _wrong_version(raw: dict[str, Any]) -> None:
    raw["version"] = 2


def _no_links(raw: dict[str, Any]) -> None:
    del raw["links"]


def _drop_field(raw: dict[str, Any]) -> None:
    del raw["activities"][3]["object"]


def _wrong_type(raw: dict[str, Any]) -> None:
    raw["activities"][3]["id"] = "3"


def _unknown_category(raw: dict[str, Any]) -> None:
    raw["activities"][3]["object"] = "sofa"


def _unknown_primitive(raw: dict[str, Any]) -> None:
    raw["activities"][3]["primitive"] = "moonwalk"


def _duplicate_id(raw: dict[str, Any]) -> None:
    raw["activities"][4]["id"] = 3


def _duplicate_name(raw: dict[str, Any]) -> None:
    raw["activities"][4]["name"] = raw["activities"][3]["name"]


def _ids_not_dense(raw: dict[str, Any]) -> None:
    raw["activities"][-1]["id"] = 500


def _link_to_unknown_id(raw: dict[str, Any]) -> None:
    raw["links"][0]["b"] = 500


def _self_link(raw: dict[str, Any]) -> None:
    raw["links"][0]["b"] = raw["links"][0]["a"]


def _duplicate_link(raw: dict[str, Any]) -> None:
    raw["links"].append(dict(raw["links"][0]))


def _link_missing_reason(raw: dict[str, Any]) -> None:
    del raw["links"][0]["reason"]


def _link_within_one_category(raw: dict[str, Any]) -> None:
    by_object: dict[str, list[int]] = {}
    for act in raw["activities"]:
        by_object.setdefault(act["object"], []).append(act["id"])
    a, b = next(ids for ids in by_object.values() if len(ids) >= 2)[:2]
    raw["links"][0].update(a=a, b=b)


@pytest.mark.parametrize(
    ("breakage", "message"),
    [
        (_wrong_version, r"'version' must be 1, got 2"),
        (_no_links, r"missing field 'links'"),
        (_drop_field, r"activity #3: missing field 'object'"),
        (_wrong_type, r"activity #3: field 'id' must be int"),
        (_unknown_category, r"activity 3 .*unknown object category 'sofa'"),
        (_unknown_primitive, r"activity 3 .*unknown motion primitive 'moonwalk'"),
        (_duplicate_id, r"duplicate activity id 3"),
        (_duplicate_name, r"activity 4 .*duplicate activity name"),
        (_ids_not_dense, r"ids must be 0\.\.106 in order; found id 500"),
        (_link_to_unknown_id, r"link #0 .*unknown activity id 500"),
        (_self_link, r"link #0 .*self link"),
        (_duplicate_link, r"duplicate link"),
        (_link_missing_reason, r"link #0: missing field 'reason'"),
        (_link_within_one_category, r"link #0 .*same object category"),
    ],
)
def test_loader_rejects_broken_graph_naming_the_problem(
    tmp_path: Path, breakage: Callable[[dict[str, Any]], None], message: str
) -> None:
    raw = _shipped()
    breakage(raw)
    path = tmp_path / "graph.json"
    path.write_text(json.dumps(raw), encoding="utf-8")
    with pytest.raises(ValueError, match=message):
        load_activity_graph(path)


def test_loader_rejects_text_that_is_not_json(tmp_path: Path) -> None:
    path = tmp_path / "graph.json"
    path.write_text('{"version": 1,', encoding="utf-8")
    with pytest.raises(ValueError, match="graph.json: not valid JSON"):
        load_activity_graph(path)


def test_loader_accepts_an_unbroken_copy(tmp_path: Path, graph: ActivityGraph) -> None:
    path = tmp_path / "graph.json"
    path.write_text(json.dumps(_shipped()), encoding="utf-8")
    assert load_activity_graph(path) == graph


# -- sampler ----------------------------------------------------------------------------------

KITCHEN = {"counter": 1, "fridge": 2, "sink": 1, "stove": 1, "trashcan": 1, "table": 1, "oven": 0}


def test_sampler_returns_only_links_whose_objects_are_available(graph: ActivityGraph) -> None:
    present = {name for name, count in KITCHEN.items() if count >= 1}
    candidates = {(link.a, link.b) for link in available_links(graph, KITCHEN)}
    assert candidates
    rng = np.random.default_rng(0)
    drawn = [sample_activity_pair(rng, graph, KITCHEN) for _ in range(2000)]
    for pair in drawn:
        assert pair in candidates
        assert graph.activity(pair[0]).object in present
        assert graph.activity(pair[1]).object in present
    assert set(drawn) == candidates  # uniform over the candidates: every one turns up


def test_available_links_ignore_categories_with_zero_instances(graph: ActivityGraph) -> None:
    assert all(
        graph.activity(link.a).object != "oven" and graph.activity(link.b).object != "oven"
        for link in available_links(graph, KITCHEN)
    )


def test_sampler_returns_none_when_no_link_is_available(graph: ActivityGraph) -> None:
    rng = np.random.default_rng(0)
    assert sample_activity_pair(rng, graph, {}) is None
    assert sample_activity_pair(rng, graph, {"bed": 1, "couch": 0}) is None


def test_sampler_rejects_unknown_category_names(graph: ActivityGraph) -> None:
    with pytest.raises(ValueError, match="unknown object category 'sofa'"):
        available_links(graph, {"sofa": 1})


def test_sampler_is_deterministic_given_the_seed(graph: ActivityGraph) -> None:
    everything = dict.fromkeys(CATEGORY_NAMES, 1)

    def draws(seed: int) -> list[tuple[int, int] | None]:
        rng = np.random.default_rng(seed)
        return [sample_activity_pair(rng, graph, everything) for _ in range(50)]

    assert draws(7) == draws(7)
    assert draws(7) != draws(8)
