"""The causal activity graph: 107 household activities, each bound to one object category and one
motion primitive, and links A -> B ("in daily life a person usually does B after A") with a reason.

data/activity_graph.json -> `load_activity_graph` (validates) -> `ActivityGraph` ->
`sample_activity_pair` draws an episode's (A, B) among the links whose objects the scene holds.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from conav_jax.data.categories import CATEGORY_INDEX, category
from conav_jax.motion.primitives import MOTION_PRIMITIVES

DEFAULT_GRAPH_PATH = Path(__file__).parent / "activity_graph.json"
GRAPH_FORMAT_VERSION = 1


@dataclass(frozen=True)
class Activity:
    """One activity: `name` ("a person ..."), done at an instance of category `object` and
    animated with the motion primitive `primitive` (a key of MOTION_PRIMITIVES)."""

    id: int
    name: str
    object: str
    primitive: str

    @property
    def object_index(self) -> int:
        """Index of `object` in CATEGORY_NAMES."""
        return CATEGORY_INDEX[self.object]


@dataclass(frozen=True)
class ActivityLink:
    """Causal link: after activity `a`, a person usually does activity `b`; `reason` says why."""

    a: int
    b: int
    reason: str


@dataclass(frozen=True)
class ActivityGraph:
    """Activities (`activities[i].id == i`) and the causal links between them."""

    activities: tuple[Activity, ...]
    links: tuple[ActivityLink, ...]

    def activity(self, activity_id: int) -> Activity:
        """The activity with id `activity_id`; ValueError when there is none."""
        if not 0 <= activity_id < len(self.activities):
            raise ValueError(f"unknown activity id {activity_id}; ids are 0..{len(self.activities) - 1}")
        return self.activities[activity_id]

    def by_name(self, name: str) -> Activity:
        """The activity called `name`; ValueError when there is none."""
        for act in self.activities:
            if act.name == name:
                return act
        raise ValueError(f"unknown activity name {name!r}")

    def successors(self, activity_id: int) -> tuple[ActivityLink, ...]:
        """The links leaving `activity_id`, in file order."""
        self.activity(activity_id)  # rejects unknown ids
        return tuple(link for link in self.links if link.a == activity_id)

    def object_of(self, activity_id: int) -> int:
        """Category index (into CATEGORY_NAMES) of the object `activity_id` is done at."""
        return self.activity(activity_id).object_index


def load_activity_graph(path: str | Path | None = None) -> ActivityGraph:
    """Load and validate an activity graph JSON; `None` loads the shipped one (cached).

    Raises ValueError naming the offending activity, link or field when the file is malformed.
    """
    if path is None:
        return _load_default_graph()
    try:
        raw = json.loads(Path(path).read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON: {err}") from None
    return _parse_graph(raw, source=str(path))


@functools.lru_cache(maxsize=1)
def _load_default_graph() -> ActivityGraph:
    return load_activity_graph(DEFAULT_GRAPH_PATH)


def available_links(graph: ActivityGraph, available: Mapping[str, int]) -> list[ActivityLink]:
    """The links whose two activities' objects are both in the scene, in file order.

    `available` maps a category name to the number of reachable instances of it in the scene;
    missing names count as 0. Unknown category names raise ValueError.
    """
    for name in available:
        category(name)
    present = {name for name, count in available.items() if count >= 1}
    return [
        link
        for link in graph.links
        if graph.activities[link.a].object in present and graph.activities[link.b].object in present
    ]


def sample_activity_pair(
    rng: np.random.Generator, graph: ActivityGraph, available: Mapping[str, int]
) -> tuple[int, int] | None:
    """Draw an (activity A id, activity B id) pair uniformly among `available_links`.

    Returns None when the scene holds no link's two objects. Deterministic given `rng`'s state.
    """
    links = available_links(graph, available)
    if not links:
        return None
    link = links[int(rng.integers(len(links)))]
    return link.a, link.b


# -- parsing and validation ----------------------------------------------------------------

_ACTIVITY_FIELDS: dict[str, type] = {"id": int, "name": str, "object": str, "primitive": str}
_LINK_FIELDS: dict[str, type] = {"a": int, "b": int, "reason": str}


def _parse_graph(raw: Any, source: str) -> ActivityGraph:
    if not isinstance(raw, dict):
        raise ValueError(f"{source}: top level must be a JSON object")
    if raw.get("version") != GRAPH_FORMAT_VERSION:
        raise ValueError(f"{source}: 'version' must be {GRAPH_FORMAT_VERSION}, got {raw.get('version')!r}")
    for key in ("activities", "links"):
        if not isinstance(raw.get(key), list):
            raise ValueError(f"{source}: missing field {key!r} (a list)")
    activities = _parse_activities(raw["activities"], source)
    links = _parse_links(raw["links"], activities, source)
    return ActivityGraph(activities=activities, links=links)


def _checked_fields(entry: Any, fields: dict[str, type], where: str) -> dict[str, Any]:
    """`entry`'s fields after checking each is present with the right type."""
    if not isinstance(entry, dict):
        raise ValueError(f"{where}: must be a JSON object, got {type(entry).__name__}")
    for name, typ in fields.items():
        if name not in entry:
            raise ValueError(f"{where}: missing field {name!r}")
        value = entry[name]
        # bool is a subclass of int; `true` is not an id.
        if not isinstance(value, typ) or isinstance(value, bool):
            got = f"{type(value).__name__} {value!r}"
            raise ValueError(f"{where}: field {name!r} must be {typ.__name__}, got {got}")
    return entry


def _parse_activities(entries: list[Any], source: str) -> tuple[Activity, ...]:
    activities: list[Activity] = []
    ids: set[int] = set()
    names: set[str] = set()
    for pos, entry in enumerate(entries):
        fields = _checked_fields(entry, _ACTIVITY_FIELDS, f"{source}: activity #{pos}")
        act = Activity(fields["id"], fields["name"], fields["object"], fields["primitive"])
        where = f"{source}: activity {act.id} ({act.name!r})"
        if act.object not in CATEGORY_INDEX:
            raise ValueError(f"{where}: unknown object category {act.object!r}")
        if act.primitive not in MOTION_PRIMITIVES:
            raise ValueError(f"{where}: unknown motion primitive {act.primitive!r}")
        if act.id in ids:
            raise ValueError(f"{where}: duplicate activity id {act.id}")
        if act.name in names:
            raise ValueError(f"{where}: duplicate activity name {act.name!r}")
        if act.id != pos:
            raise ValueError(
                f"{where}: activity ids must be 0..{len(entries) - 1} in order; "
                f"found id {act.id} at position {pos}"
            )
        ids.add(act.id)
        names.add(act.name)
        activities.append(act)
    return tuple(activities)


def _parse_links(
    entries: list[Any], activities: tuple[Activity, ...], source: str
) -> tuple[ActivityLink, ...]:
    links: list[ActivityLink] = []
    seen: set[tuple[int, int]] = set()
    for pos, entry in enumerate(entries):
        fields = _checked_fields(entry, _LINK_FIELDS, f"{source}: link #{pos}")
        link = ActivityLink(fields["a"], fields["b"], fields["reason"])
        where = f"{source}: link #{pos} ({link.a} -> {link.b})"
        for end in (link.a, link.b):
            if not 0 <= end < len(activities):
                raise ValueError(f"{where}: link to unknown activity id {end}")
        if link.a == link.b:
            raise ValueError(f"{where}: self link")
        if (link.a, link.b) in seen:
            raise ValueError(f"{where}: duplicate link")
        obj = activities[link.a].object
        if obj == activities[link.b].object:
            raise ValueError(f"{where}: both activities are done at the same object category {obj!r}")
        seen.add((link.a, link.b))
        links.append(link)
    return tuple(links)


# Size of the shipped graph (107): the number of activity classes the intention predictor outputs.
NUM_ACTIVITIES = len(_load_default_graph().activities)
