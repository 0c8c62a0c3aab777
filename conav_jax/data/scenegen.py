"""Procedural apartments: rooms by binary space partition, walls with door openings, furniture.

Deterministic from a numpy Generator. The apartment is split recursively into rooms; every split
wall gets one door gap, so all rooms are connected. Each room gets a room type and furniture of
the categories that type holds, placed against walls (or free-standing, or on a wall, ceiling or
supporting surface, as the category says) with an access area in front of each object kept
clear. Output is a `Scene`, the same structure the JSON loader produces, validated the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from conav_jax.config import SceneGenConfig
from conav_jax.data.categories import (
    CATEGORIES,
    ROOM_TYPES,
    SUPPORT_CATEGORIES,
    Category,
    category,
)
from conav_jax.data.materials import draw_scene_materials
from conav_jax.data.scene import Box, Room, Scene, SceneObject, validate_geometry

# Room types in the order a growing apartment adds them.
_ROOM_ORDER = ("living_room", "kitchen", "bedroom", "bathroom", "study", "bedroom", "living_room", "study")
_MIN_ROOM_M = 2.6
_DOOR_END_CLEARANCE_M = 0.35  # a door gap keeps this far from wall junctions
_ACCESS_DEPTH_M = 0.8  # kept free in front of each object's front face
_FREE_STANDING = {"carpet": 1.0, "table": 0.6, "treadmill": 0.3, "armchair": 0.3}


@dataclass
class _Door:
    axis: int  # 0: the wall is the line x = coord; 1: the line y = coord
    coord: float
    lo: float  # the gap along the other axis
    hi: float


def _split_rooms(rng: np.random.Generator, n_rooms: int, cfg: SceneGenConfig):
    """Rectangles of a binary space partition and the door gap of each split."""
    mean_side = float(np.mean(cfg.room_size_m))
    area = n_rooms * mean_side**2 * rng.uniform(0.9, 1.15)
    aspect = rng.uniform(1.0, 1.6)
    width, height = math.sqrt(area * aspect), math.sqrt(area / aspect)
    if rng.random() < 0.5:
        width, height = height, width
    rects = [(0.0, 0.0, width, height)]
    doors: list[_Door] = []
    while len(rects) < n_rooms:
        rects.sort(key=lambda r: (r[2] - r[0]) * (r[3] - r[1]))
        x0, y0, x1, y1 = rects.pop()
        axis = 0 if (x1 - x0) >= (y1 - y0) else 1  # split the longer side
        lo, hi = (x0, x1) if axis == 0 else (y0, y1)
        if hi - lo < 2 * _MIN_ROOM_M:
            rects.append((x0, y0, x1, y1))
            break
        # The new wall's ends meet the walls along the other axis; keep it off their door gaps.
        for _ in range(50):
            s = rng.uniform(max(lo + _MIN_ROOM_M, lo + 0.35 * (hi - lo)), min(hi - _MIN_ROOM_M, lo + 0.65 * (hi - lo)))
            if not any(
                d.axis != axis and d.lo - _DOOR_END_CLEARANCE_M < s < d.hi + _DOOR_END_CLEARANCE_M
                and (d.coord in ((y0, y1) if axis == 0 else (x0, x1)))
                for d in doors
            ):
                break
        span = (y0, y1) if axis == 0 else (x0, x1)
        g0 = rng.uniform(span[0] + _DOOR_END_CLEARANCE_M, span[1] - _DOOR_END_CLEARANCE_M - cfg.door_width_m)
        doors.append(_Door(axis, s, g0, g0 + cfg.door_width_m))
        if axis == 0:
            rects += [(x0, y0, s, y1), (s, y0, x1, y1)]
        else:
            rects += [(x0, y0, x1, s), (x0, s, x1, y1)]
    return (width, height), rects, doors


def _walls(size, rects, doors, cfg: SceneGenConfig) -> list[Box]:
    """Outer walls and split walls (with their door gaps) as boxes centred on their lines."""
    t, h = cfg.wall_thickness_m, cfg.wall_height_m
    width, height = size
    walls = [
        Box((width / 2, 0.0, h / 2), (width / 2 + t / 2, t / 2, h / 2)),
        Box((width / 2, height, h / 2), (width / 2 + t / 2, t / 2, h / 2)),
        Box((0.0, height / 2, h / 2), (t / 2, height / 2 - t / 2, h / 2)),
        Box((width, height / 2, h / 2), (t / 2, height / 2 - t / 2, h / 2)),
    ]
    # Recover each split wall's extent from the rectangles it separates.
    for d in doors:
        a, b = _split_extent(d, rects)
        for s0, s1 in ((a, d.lo), (d.hi, b)):
            if s1 - s0 <= 1e-6:
                continue
            mid, half = (s0 + s1) / 2, (s1 - s0) / 2
            if d.axis == 0:
                walls.append(Box((d.coord, mid, h / 2), (t / 2, half, h / 2)))
            else:
                walls.append(Box((mid, d.coord, h / 2), (half, t / 2, h / 2)))
    return walls


def _split_extent(d: _Door, rects) -> tuple[float, float]:
    """The full length of the split line through the door: union of touching rect edges."""
    if d.axis == 0:
        edges = [(r[1], r[3]) for r in rects if abs(r[2] - d.coord) < 1e-9 or abs(r[0] - d.coord) < 1e-9]
    else:
        edges = [(r[0], r[2]) for r in rects if abs(r[3] - d.coord) < 1e-9 or abs(r[1] - d.coord) < 1e-9]
    # Grow from the door's interval through contiguous edges.
    lo, hi = d.lo, d.hi
    changed = True
    while changed:
        changed = False
        for a, b in edges:
            if a <= hi + 1e-9 and b >= lo - 1e-9 and (a < lo - 1e-9 or b > hi + 1e-9):
                lo, hi = min(lo, a), max(hi, b)
                changed = True
    return lo, hi


@dataclass
class _Placed:
    obj: SceneObject
    access: tuple[float, float, float, float] | None  # x0, y0, x1, y1 kept clear in front


def _rect_overlap(a, b) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _box_rect(box: Box, pad: float = 0.0):
    (cx, cy, _), (hx, hy, _) = box.center, box.half_extents
    return (cx - hx - pad, cy - hy - pad, cx + hx + pad, cy + hy + pad)


def _boxes_overlap(a: Box, b: Box, tol: float = 0.0005) -> bool:
    # Stricter than the validator (1 mm) by more than the 4-decimal rounding of the JSON.
    return all(abs(a.center[k] - b.center[k]) < a.half_extents[k] + b.half_extents[k] - tol for k in range(3))


class _RoomFurnisher:
    """Places objects in one room, rejecting candidates that collide or block access."""

    def __init__(self, rng, room_index: int, interior, doors, cfg: SceneGenConfig, placed: list[_Placed]):
        self.rng, self.room, self.cfg, self.placed = rng, room_index, cfg, placed
        self.interior = interior  # x0, y0, x1, y1 inside the walls
        x0, y0, x1, y1 = interior
        t = cfg.wall_thickness_m
        # Door keep-out: the gap plus a margin, 1.2 m deep on both sides of the wall.
        self.keepout = []
        for d in doors:
            if d.axis == 0 and (abs(d.coord - (x0 - t / 2)) < 1e-6 or abs(d.coord - (x1 + t / 2)) < 1e-6):
                if d.hi > y0 and d.lo < y1:
                    self.keepout.append((d.coord - 1.2, d.lo - 0.25, d.coord + 1.2, d.hi + 0.25))
            if d.axis == 1 and (abs(d.coord - (y0 - t / 2)) < 1e-6 or abs(d.coord - (y1 + t / 2)) < 1e-6):
                if d.hi > x0 and d.lo < x1:
                    self.keepout.append((d.lo - 0.25, d.coord - 1.2, d.hi + 0.25, d.coord + 1.2))

    def _jitter(self, cat: Category):
        return tuple(float(v * self.rng.uniform(0.85, 1.15)) for v in cat.size_m)

    def _access_rect(self, obj: SceneObject):
        b = obj.box
        (cx, cy, _), (hx, hy, _) = b.center, b.half_extents
        yaw = obj.yaw_deg % 360
        a, half_w = _ACCESS_DEPTH_M, 0.35
        if yaw == 0:
            return (cx + hx, cy - max(hy, half_w), cx + hx + a, cy + max(hy, half_w))
        if yaw == 180:
            return (cx - hx - a, cy - max(hy, half_w), cx - hx, cy + max(hy, half_w))
        if yaw == 90:
            return (cx - max(hx, half_w), cy + hy, cx + max(hx, half_w), cy + hy + a)
        return (cx - max(hx, half_w), cy - hy - a, cx + max(hx, half_w), cy - hy)

    def _fits(self, obj: SceneObject, access, floor_level: bool) -> bool:
        box = obj.box
        x0, y0, x1, y1 = self.interior
        r = _box_rect(box)
        if r[0] < x0 - 1e-6 or r[1] < y0 - 1e-6 or r[2] > x1 + 1e-6 or r[3] > y1 + 1e-6:
            return False
        if access is not None:
            ax0, ay0, ax1, ay1 = access
            if ax0 < x0 or ay0 < y0 or ax1 > x1 or ay1 > y1:
                return False
        for p in self.placed:
            if _boxes_overlap(box, p.obj.box):
                return False
            if floor_level and p.access is not None and _rect_overlap(r, p.access):
                return False
            if access is not None and floor_level is not None and category(p.obj.category).mount == "floor":
                if _rect_overlap(access, _box_rect(p.obj.box)) and category(p.obj.category).collides:
                    return False
        if floor_level and any(_rect_overlap(r, k) for k in self.keepout):
            return False
        return True

    def _against_wall(self, cat: Category, size, z_center: float, free_standing: bool):
        w, d, h = size
        x0, y0, x1, y1 = self.interior
        gap = 0.02
        if free_standing:
            yaw = int(self.rng.integers(0, 4)) * 90
            hx, hy = (d / 2, w / 2) if yaw % 180 == 0 else (w / 2, d / 2)
            if x1 - x0 < 2 * hx + 0.2 or y1 - y0 < 2 * hy + 0.2:
                return None
            cx = self.rng.uniform(x0 + hx + 0.1, x1 - hx - 0.1)
            cy = self.rng.uniform(y0 + hy + 0.1, y1 - hy - 0.1)
            return (cx, cy, z_center), yaw
        side = int(self.rng.integers(0, 4))
        # yaw = where the front faces: away from the wall it stands against.
        if side == 0:  # against the wall at y0
            if x1 - x0 < w:
                return None
            return (self.rng.uniform(x0 + w / 2, x1 - w / 2), y0 + d / 2 + gap, z_center), 90
        if side == 1:
            if x1 - x0 < w:
                return None
            return (self.rng.uniform(x0 + w / 2, x1 - w / 2), y1 - d / 2 - gap, z_center), 270
        if side == 2:
            if y1 - y0 < w:
                return None
            return (x0 + d / 2 + gap, self.rng.uniform(y0 + w / 2, y1 - w / 2), z_center), 0
        if y1 - y0 < w:
            return None
        return (x1 - d / 2 - gap, self.rng.uniform(y0 + w / 2, y1 - w / 2), z_center), 180

    def place(self, cat: Category, tries: int = 30) -> bool:
        for _ in range(tries):
            size = self._jitter(cat)
            w, d, h = size
            if cat.mount == "ceiling":
                x0, y0, x1, y1 = self.interior
                cx = (x0 + x1) / 2 + self.rng.uniform(-0.3, 0.3)
                cy = (y0 + y1) / 2 + self.rng.uniform(-0.3, 0.3)
                z = min(cat.z_bottom_m + h / 2, self.cfg.wall_height_m - h / 2)
                obj = SceneObject(cat.name, (cx, cy, z), size, int(self.rng.integers(0, 4)) * 90, self.room, cat.rgb)
                if self._fits(obj, None, floor_level=False):
                    self.placed.append(_Placed(obj, None))
                    return True
                continue
            if cat.mount == "surface":
                supports = [
                    p for p in self.placed
                    if p.obj.room == self.room and p.obj.category in SUPPORT_CATEGORIES
                    and p.obj.size[0] >= w and p.obj.size[1] >= d
                ]
                if not supports:
                    return False
                sup = supports[int(self.rng.integers(0, len(supports)))].obj
                yaw = sup.yaw_deg
                fx, fy = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
                along = self.rng.uniform(-(sup.size[0] - w) / 2, (sup.size[0] - w) / 2)
                # Flush with the support's front so both share the standing point's distance.
                fwd = sup.size[1] / 2 - d / 2
                cx = sup.center[0] + fwd * fx - along * fy
                cy = sup.center[1] + fwd * fy + along * fx
                z = sup.box.z_max + h / 2
                obj = SceneObject(cat.name, (cx, cy, z), size, yaw, self.room, cat.rgb)
                if self._fits(obj, None, floor_level=False):
                    self.placed.append(_Placed(obj, None))
                    return True
                continue
            if cat.mount == "wall":
                z = cat.z_bottom_m + h / 2
                if z + h / 2 > self.cfg.wall_height_m:
                    continue
                spot = self._against_wall(cat, size, z, free_standing=False)
                if spot is None:
                    continue
                center, yaw = spot
                center = (center[0] - 0.018 * math.cos(math.radians(yaw)), center[1] - 0.018 * math.sin(math.radians(yaw)), center[2])
                obj = SceneObject(cat.name, center, size, yaw, self.room, cat.rgb)
                # A door object reaches the floor: it needs the floor in front kept clear.
                floor_level = cat.z_bottom_m < 0.5
                if self._fits(obj, self._access_rect(obj), floor_level=floor_level) and not self._on_door_gap(obj):
                    self.placed.append(_Placed(obj, self._access_rect(obj)))
                    return True
                continue
            free = self.rng.random() < _FREE_STANDING.get(cat.name, 0.0)
            spot = self._against_wall(cat, size, h / 2, free_standing=free)
            if spot is None:
                continue
            center, yaw = spot
            obj = SceneObject(cat.name, center, size, yaw, self.room, cat.rgb)
            access = None if not cat.collides else self._access_rect(obj)
            if self._fits(obj, access, floor_level=cat.collides):
                self.placed.append(_Placed(obj, access))
                return True
        return False

    def _on_door_gap(self, obj: SceneObject) -> bool:
        r = _box_rect(obj.box, pad=0.05)
        return any(_rect_overlap(r, k) for k in self.keepout)


def _room_types(rng: np.random.Generator, n: int) -> list[str]:
    types = list(_ROOM_ORDER[:n])
    rng.shuffle(types)
    return types


def _choose_categories(rng: np.random.Generator, room_type: str, k: int) -> list[Category]:
    """Up to k distinct categories a room of this type holds; supports before surface objects."""
    candidates = [c for c in CATEGORIES if room_type in c.rooms]
    idx = rng.permutation(len(candidates))[:k]
    chosen = [candidates[i] for i in idx]
    order = {"floor": 0, "wall": 1, "ceiling": 2, "surface": 3}
    return sorted(chosen, key=lambda c: order[c.mount])


def generate_scene(rng: np.random.Generator, cfg: SceneGenConfig, name: str) -> Scene:
    """A random apartment; raises RuntimeError only if the partition cannot be built."""
    n_rooms = int(rng.integers(cfg.rooms[0], cfg.rooms[1] + 1))
    size, rects, doors = _split_rooms(rng, n_rooms, cfg)
    walls = _walls(size, rects, doors, cfg)
    types = _room_types(rng, len(rects))
    t = cfg.wall_thickness_m
    rooms = [Room(types[i], (r[0], r[1], r[2], r[3])) for i, r in enumerate(rects)]
    placed: list[_Placed] = []
    for i, r in enumerate(rects):
        interior = (r[0] + t / 2, r[1] + t / 2, r[2] - t / 2, r[3] - t / 2)
        furnisher = _RoomFurnisher(rng, i, interior, doors, cfg, placed)
        k = int(rng.integers(cfg.objects_per_room[0], cfg.objects_per_room[1] + 1))
        for cat in _choose_categories(rng, types[i], k):
            furnisher.place(cat)
    objects = tuple(p.obj for p in placed)
    # Round to the precision the JSON stores, so a written and re-read scene is identical.
    objects = tuple(
        SceneObject(o.category, tuple(round(v, 4) for v in o.center), tuple(round(v, 4) for v in o.size), o.yaw_deg, o.room, o.rgb)
        for o in objects
    )
    walls = [Box(tuple(round(v, 4) for v in w.center), tuple(round(v, 4) for v in w.half_extents)) for w in walls]
    width, height = size
    bounds = (round(-t / 2, 4), round(-t / 2, 4), round(width + t / 2, 4), round(height + t / 2, 4))
    rooms = tuple(Room(r.type, tuple(round(v, 4) for v in r.rect)) for r in rooms)
    # Materials from a child of the generator's seed: drawing them leaves its own stream as it was.
    materials = draw_scene_materials(rng.spawn(1)[0], [o.category for o in objects])
    scene = Scene(name, bounds, cfg.wall_height_m, rooms, tuple(walls), objects, materials)
    validate_geometry(scene, name)
    return scene


__all__ = ["generate_scene", "ROOM_TYPES"]
