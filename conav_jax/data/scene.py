"""Scenes: walls and furniture as axis-aligned boxes, the JSON scene format and its validator.

The generator (conav_jax.data.scenegen) writes this format and the loader reads it back, so
hand-made or imported scenes (e.g. annotated real apartments) run unchanged. Data flows:
JSON <-> `Scene` -> navigation grids (conav_jax.nav.navigation) and simulator boxes (envs).

Format (version 1), all lengths in metres, z up, the floor at z = 0:

    {
      "format": "conav-scene", "version": 1, "name": "apt_0001",
      "bounds_m": [x_min, y_min, x_max, y_max],          # everything lies inside
      "wall_height_m": 2.6,
      "rooms": [{"type": "kitchen", "rect_m": [x0, y0, x1, y1]}, ...],   # types: ROOM_TYPES
      "walls": [{"center_m": [x, y, z], "half_extents_m": [hx, hy, hz]}, ...],
      "objects": [{"category": "fridge",                   # one of the 51 categories
                   "center_m": [x, y, z],                  # box centre
                   "size_m": [width, depth, height],       # in the object's own frame
                   "yaw_deg": 90,                          # multiple of 90: where its front faces
                   "room": 1,                              # index into rooms, or -1
                   "rgb": [r, g, b],                       # optional, 0-255; default: category's
                   "material": MATERIAL}, ...],            # optional, see below
      "materials": {"floor": MATERIAL, "walls": MATERIAL}  # optional
    }

`rgb` is the category's flat colour (SensorConfig.materials "flat"); a MATERIAL is what the
instance looks like otherwise (conav_jax.data.materials): {"rgb": [r, g, b], "rgb2": [r, g, b],
"pattern": "plain" | "stripes" | "checks" | "noise", "period_m": 0.5, "angle_deg": 30}.
Materials left out are drawn deterministically from the scene's name (`name_seed`); the
generator stores the ones it drew from its own seed.

An object's front faces `yaw_deg` (0 = +x, 90 = +y); a person uses it from its standing point,
`standing_offset_m` in front of the front face (ceiling objects: straight below), facing it.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from conav_jax.data.categories import (
    CATEGORY_INDEX,
    FLOOR_RGB,
    ROOM_TYPES,
    WALL_RGB,
    category,
)
from conav_jax.data.materials import MATERIAL_WIDTH, PATTERNS, Material, SceneMaterials, draw_scene_materials, name_seed

SCENE_FORMAT = "conav-scene"
SCENE_VERSION = 1
# Boxes may touch (a picture flush on a wall, a lamp on a table) but not interpenetrate.
OVERLAP_TOLERANCE_M = 1e-3


@dataclass(frozen=True)
class Box:
    """An axis-aligned box: centre and half-extents in metres."""

    center: tuple[float, float, float]
    half_extents: tuple[float, float, float]

    @property
    def z_min(self) -> float:
        return self.center[2] - self.half_extents[2]

    @property
    def z_max(self) -> float:
        return self.center[2] + self.half_extents[2]


@dataclass(frozen=True)
class SceneObject:
    category: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]  # (width, depth, height) in the object's frame
    yaw_deg: int  # multiple of 90; the direction its front faces
    room: int
    rgb: tuple[int, int, int]

    @property
    def category_index(self) -> int:
        return CATEGORY_INDEX[self.category]

    @property
    def box(self) -> Box:
        w, d, h = self.size
        # Depth runs along the facing direction: +-x for yaw 0/180, +-y for 90/270.
        if self.yaw_deg % 180 == 0:
            half = (d / 2, w / 2, h / 2)
        else:
            half = (w / 2, d / 2, h / 2)
        return Box(self.center, half)

    @property
    def yaw_rad(self) -> float:
        return math.radians(self.yaw_deg)

    def standing_pose(self, offset_m: float) -> tuple[float, float, float]:
        """Where a person stands to use this object: (x, y, facing yaw in radians)."""
        cx, cy, _ = self.center
        if category(self.category).mount == "ceiling":
            return (cx, cy, self.yaw_rad)
        reach = self.size[1] / 2 + offset_m
        fx, fy = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        facing = math.atan2(-fy, -fx)
        return (cx + reach * fx, cy + reach * fy, facing)

    def blocks_robot(self, robot_height_m: float) -> bool:
        """Whether the robot (a cylinder from the floor to robot_height_m) can run into it."""
        return category(self.category).collides and self.box.z_min < robot_height_m


@dataclass(frozen=True)
class Room:
    type: str
    rect: tuple[float, float, float, float]  # x0, y0, x1, y1


@dataclass(frozen=True)
class Scene:
    name: str
    bounds: tuple[float, float, float, float]  # x_min, y_min, x_max, y_max
    wall_height: float
    rooms: tuple[Room, ...]
    walls: tuple[Box, ...]
    objects: tuple[SceneObject, ...]
    # None: drawn from the name (`default_materials`), so every Scene has them.
    materials: SceneMaterials | None = None

    def __post_init__(self):
        if self.materials is None:
            object.__setattr__(self, "materials", default_materials(self.name, self.objects))
        elif len(self.materials.objects) != len(self.objects):
            raise ValueError(f"scene {self.name}: {len(self.materials.objects)} object materials for "
                             f"{len(self.objects)} objects")

    def category_counts(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for o in self.objects:
            counts[o.category] = counts.get(o.category, 0) + 1
        return counts

    # -- JSON -------------------------------------------------------------------------------
    def to_json_dict(self) -> dict[str, Any]:
        return {
            "format": SCENE_FORMAT,
            "version": SCENE_VERSION,
            "name": self.name,
            "bounds_m": [round(v, 4) for v in self.bounds],
            "wall_height_m": self.wall_height,
            "rooms": [{"type": r.type, "rect_m": [round(v, 4) for v in r.rect]} for r in self.rooms],
            "walls": [
                {"center_m": [round(v, 4) for v in w.center], "half_extents_m": [round(v, 4) for v in w.half_extents]}
                for w in self.walls
            ],
            "objects": [
                {
                    "category": o.category,
                    "center_m": [round(v, 4) for v in o.center],
                    "size_m": [round(v, 4) for v in o.size],
                    "yaw_deg": o.yaw_deg,
                    "room": o.room,
                    "rgb": list(o.rgb),
                    "material": m.to_json_dict(),
                }
                for o, m in zip(self.objects, self.materials.objects)
            ],
            "materials": {"floor": self.materials.floor.to_json_dict(), "walls": self.materials.walls.to_json_dict()},
        }


def default_materials(name: str, objects) -> SceneMaterials:
    """The materials of a scene stored without them: drawn from its name (name_seed)."""
    return draw_scene_materials(np.random.default_rng(name_seed(name)), [o.category for o in objects])


class SceneFormatError(ValueError):
    """A scene that does not follow the format. The message is `SOURCE: FIELD: PROBLEM`:
    `source` names the file (or dict), `field` the offending field as a path into the document
    (`objects[3].category`; empty when the document itself is at fault)."""

    def __init__(self, source: str, field: str, problem: str):
        self.source, self.field, self.problem = source, field, problem
        super().__init__(f"{source}: {field}: {problem}" if field else f"{source}: {problem}")

    def __reduce__(self):  # picklable across worker processes despite the three-argument init
        return type(self), (self.source, self.field, self.problem)


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _field(d: dict, key: str, source: str, where: str = "") -> Any:
    """`d[key]`; `where` is the path of `d` in the document ("" for the document itself)."""
    if not isinstance(d, dict):
        raise SceneFormatError(source, where, f"expected an object, got {type(d).__name__}")
    if key not in d:
        raise SceneFormatError(source, _join(where, key), "required field is missing")
    return d[key]


def _numbers(v: Any, n: int, source: str, field: str) -> tuple[float, ...]:
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise SceneFormatError(source, field, f"expected a list of {n} numbers, got {v!r}")
    out = []
    for x in v:
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise SceneFormatError(source, field, f"expected finite numbers, got {v!r}")
        out.append(float(x))
    return tuple(out)


def _list(d: dict, key: str, source: str) -> list:
    v = _field(d, key, source)
    if not isinstance(v, list):
        raise SceneFormatError(source, key, f"expected a list, got {type(v).__name__}")
    return v


def _rgb(v: Any, source: str, field: str) -> tuple[int, int, int]:
    if (
        not isinstance(v, list)
        or len(v) != 3
        or not all(isinstance(x, int) and not isinstance(x, bool) and 0 <= x <= 255 for x in v)
    ):
        raise SceneFormatError(source, field, f"expected three integers 0-255, got {v!r}")
    return tuple(v)


def _material(d: Any, source: str, where: str) -> Material:
    """A MATERIAL object of the format (see the module docstring)."""
    rgb = _rgb(_field(d, "rgb", source, where), source, f"{where}.rgb")
    rgb2 = _rgb(d.get("rgb2", list(rgb)), source, f"{where}.rgb2")
    pattern = d.get("pattern", "plain")
    if pattern not in PATTERNS:
        raise SceneFormatError(source, f"{where}.pattern", f"must be one of {', '.join(PATTERNS)}, got {pattern!r}")
    period = _numbers([d.get("period_m", 0.5)], 1, source, f"{where}.period_m")[0]
    if period <= 0:
        raise SceneFormatError(source, f"{where}.period_m", f"must be positive, got {period}")
    angle = _numbers([d.get("angle_deg", 0.0)], 1, source, f"{where}.angle_deg")[0]
    return Material(rgb, rgb2, pattern, period, angle)


def _materials(d: dict, objects: list, given: list, source: str, name: str) -> SceneMaterials:
    """The scene's materials: those the document gives (`given[i]` per object, None where left
    out; its "materials" object for floor and walls), the rest drawn from the name."""
    drawn = default_materials(name, objects)
    top = d.get("materials", {})
    if not isinstance(top, dict):
        raise SceneFormatError(source, "materials", f"expected an object, got {type(top).__name__}")
    floor = _material(top["floor"], source, "materials.floor") if "floor" in top else drawn.floor
    walls = _material(top["walls"], source, "materials.walls") if "walls" in top else drawn.walls
    return SceneMaterials(floor, walls, tuple(g or m for g, m in zip(given, drawn.objects)))


def scene_from_json_dict(d: dict[str, Any], source: str = "scene") -> Scene:
    """Parse and validate a scene dict; raises SceneFormatError naming the source and the field."""
    fmt = _field(d, "format", source)
    if fmt != SCENE_FORMAT:
        raise SceneFormatError(source, "format", f"must be {SCENE_FORMAT!r}, got {fmt!r}")
    version = _field(d, "version", source)
    if version != SCENE_VERSION:
        raise SceneFormatError(source, "version", f"unsupported version {version!r} (this reader knows {SCENE_VERSION})")
    name = _field(d, "name", source)
    if not isinstance(name, str) or not name:
        raise SceneFormatError(source, "name", f"must be a non-empty string, got {name!r}")
    bounds = _numbers(_field(d, "bounds_m", source), 4, source, "bounds_m")
    if not (bounds[0] < bounds[2] and bounds[1] < bounds[3]):
        raise SceneFormatError(source, "bounds_m", f"need x_min < x_max and y_min < y_max, got {bounds}")
    wall_height = _numbers([_field(d, "wall_height_m", source)], 1, source, "wall_height_m")[0]
    if wall_height <= 0:
        raise SceneFormatError(source, "wall_height_m", f"must be positive, got {wall_height}")

    rooms = []
    for i, r in enumerate(_list(d, "rooms", source)):
        where = f"rooms[{i}]"
        rtype = _field(r, "type", source, where)
        if rtype not in ROOM_TYPES:
            raise SceneFormatError(
                source, f"{where}.type", f"unknown room type {rtype!r}; valid room types: {', '.join(ROOM_TYPES)}"
            )
        rooms.append(Room(rtype, _numbers(_field(r, "rect_m", source, where), 4, source, f"{where}.rect_m")))

    walls = []
    for i, w in enumerate(_list(d, "walls", source)):
        where = f"walls[{i}]"
        c = _numbers(_field(w, "center_m", source, where), 3, source, f"{where}.center_m")
        h = _numbers(_field(w, "half_extents_m", source, where), 3, source, f"{where}.half_extents_m")
        if min(h) <= 0:
            raise SceneFormatError(source, f"{where}.half_extents_m", f"must be positive, got {h}")
        walls.append(Box(c, h))

    objects, given = [], []
    for i, o in enumerate(_list(d, "objects", source)):
        where = f"objects[{i}]"
        cat = _field(o, "category", source, where)
        if not isinstance(cat, str) or cat not in CATEGORY_INDEX:
            raise SceneFormatError(
                source, f"{where}.category", f"unknown category {cat!r}; valid categories: {', '.join(sorted(CATEGORY_INDEX))}"
            )
        c = _numbers(_field(o, "center_m", source, where), 3, source, f"{where}.center_m")
        size = _numbers(_field(o, "size_m", source, where), 3, source, f"{where}.size_m")
        if min(size) <= 0:
            raise SceneFormatError(source, f"{where}.size_m", f"must be positive, got {size}")
        yaw = _field(o, "yaw_deg", source, where)
        if isinstance(yaw, bool) or not isinstance(yaw, (int, float)) or yaw % 90 != 0:
            raise SceneFormatError(source, f"{where}.yaw_deg", f"must be a multiple of 90, got {yaw!r}")
        room = o.get("room", -1)
        if isinstance(room, bool) or not isinstance(room, int) or not (-1 <= room < len(rooms)):
            raise SceneFormatError(source, f"{where}.room", f"must be -1 or an index into rooms, got {room!r}")
        rgb = _rgb(o.get("rgb", list(category(cat).rgb)), source, f"{where}.rgb")
        objects.append(SceneObject(cat, c, size, int(yaw) % 360, room, rgb))
        given.append(_material(o["material"], source, f"{where}.material") if "material" in o else None)

    materials = _materials(d, objects, given, source, name)
    scene = Scene(name, bounds, wall_height, tuple(rooms), tuple(walls), tuple(objects), materials)
    validate_geometry(scene, source)
    return scene


def _overlap(a: Box, b: Box) -> bool:
    return all(
        abs(a.center[k] - b.center[k]) < a.half_extents[k] + b.half_extents[k] - OVERLAP_TOLERANCE_M for k in range(3)
    )


def validate_geometry(scene: Scene, source: str = "scene") -> None:
    """Reject boxes outside the bounds or below the floor and objects that interpenetrate; a
    misplaced box names its `center_m`, an overlap the two boxes."""
    x0, y0, x1, y1 = scene.bounds
    named = [(f"walls[{i}]", "wall", w) for i, w in enumerate(scene.walls)]
    named += [(f"objects[{i}]", o.category, o.box) for i, o in enumerate(scene.objects)]
    tol = OVERLAP_TOLERANCE_M
    for name, what, b in named:
        (cx, cy, _), (hx, hy, _) = b.center, b.half_extents
        if cx - hx < x0 - tol or cx + hx > x1 + tol or cy - hy < y0 - tol or cy + hy > y1 + tol:
            raise SceneFormatError(
                source,
                f"{name}.center_m",
                f"{what} footprint x {cx - hx:.3f}..{cx + hx:.3f} m, y {cy - hy:.3f}..{cy + hy:.3f} m "
                f"lies outside bounds_m {list(scene.bounds)}",
            )
        if b.z_min < -tol:
            raise SceneFormatError(source, f"{name}.center_m", f"{what} extends below the floor (z_min {b.z_min:.3f} m)")
    walls, objs = named[: len(scene.walls)], named[len(scene.walls) :]
    for i, (na, what, a) in enumerate(objs):
        for nb, what_b, b in walls + objs[:i]:
            if _overlap(a, b):
                other = nb if what_b == "wall" else f"{nb} ({what_b})"
                raise SceneFormatError(source, na, f"{what} overlaps {other}")


def load_scene(path: str | os.PathLike) -> Scene:
    """Read and validate a scene JSON file; errors read `FILE: FIELD: problem`
    (e.g. `apt.json: objects[3].category: unknown category 'sofa2'; valid categories: ...`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scene file not found: {path}")
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise SceneFormatError(str(path), "", f"not valid JSON ({e})") from e
    return scene_from_json_dict(d, source=str(path))


# -- arrays for the simulator and renderers --------------------------------------------------

STRUCTURE_WALL = -1  # category id of wall boxes in the box arrays


@dataclass(frozen=True)
class SceneBoxes:
    """All boxes of a scene as arrays, walls first then objects.

    center (N, 3), half_extents (N, 3) metres; rgb (N, 3) uint8 (flat colours); material
    (N, MATERIAL_WIDTH) float32 rows (conav_jax.data.materials); category (N,) int32 with
    STRUCTURE_WALL for walls; blocks_robot (N,) bool; object_index (N,) int32 (-1 for walls).
    """

    center: np.ndarray
    half_extents: np.ndarray
    rgb: np.ndarray
    material: np.ndarray
    category: np.ndarray
    blocks_robot: np.ndarray
    object_index: np.ndarray


def scene_boxes(scene: Scene, robot_height_m: float) -> SceneBoxes:
    centers, halves, rgbs, cats, blocks, obj_idx = [], [], [], [], [], []
    for w in scene.walls:
        centers.append(w.center)
        halves.append(w.half_extents)
        rgbs.append(WALL_RGB)
        cats.append(STRUCTURE_WALL)
        blocks.append(True)
        obj_idx.append(-1)
    for i, o in enumerate(scene.objects):
        b = o.box
        centers.append(b.center)
        halves.append(b.half_extents)
        rgbs.append(o.rgb)
        cats.append(o.category_index)
        blocks.append(o.blocks_robot(robot_height_m))
        obj_idx.append(i)
    return SceneBoxes(
        center=np.asarray(centers, np.float32).reshape(-1, 3),
        half_extents=np.asarray(halves, np.float32).reshape(-1, 3),
        rgb=np.asarray(rgbs, np.uint8).reshape(-1, 3),
        material=np.asarray([scene.materials.walls.row()] * len(scene.walls)
                            + [m.row() for m in scene.materials.objects], np.float32).reshape(-1, MATERIAL_WIDTH),
        category=np.asarray(cats, np.int32),
        blocks_robot=np.asarray(blocks, bool),
        object_index=np.asarray(obj_idx, np.int32),
    )


__all__ = [
    "Box",
    "FLOOR_RGB",
    "Room",
    "Scene",
    "SceneBoxes",
    "SceneFormatError",
    "SceneObject",
    "load_scene",
    "scene_boxes",
    "scene_from_json_dict",
    "validate_geometry",
]
