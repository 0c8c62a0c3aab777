"""The 51 object categories of the benchmark and the rooms that hold them.

The paper's activity table names 24 categories; the rest are common household objects that
complete the set to 51 (paper sec. 5.2). Each category says how the generator places it:
`floor` (stands on the floor against a wall or free), `wall` (mounted on a wall at a height),
`ceiling` (hangs from the ceiling), `surface` (stands on a supporting floor object), and its
nominal size (width along the wall, depth from the wall, height), in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

ROOM_TYPES = ("living_room", "kitchen", "bedroom", "bathroom", "study")


@dataclass(frozen=True)
class Category:
    name: str
    mount: str  # floor | wall | ceiling | surface
    size_m: tuple[float, float, float]  # nominal (width, depth, height)
    rgb: tuple[int, int, int]
    rooms: tuple[str, ...]
    z_bottom_m: float = 0.0  # wall / ceiling mounts: bottom edge height
    # The robot drives over flat things (carpets); mounted things above it never touch it.
    collides: bool = True


_ALL = ROOM_TYPES
_LIV, _KIT, _BED, _BATH, _STUDY = ROOM_TYPES

CATEGORIES: tuple[Category, ...] = (
    # -- the paper's 24 ---------------------------------------------------------------
    Category("ceiling_lamp", "ceiling", (0.5, 0.5, 0.25), (250, 240, 180), _ALL, z_bottom_m=2.25, collides=False),
    Category("potted_plant", "floor", (0.5, 0.5, 1.0), (40, 140, 50), (_LIV, _STUDY, _BED, _KIT)),
    Category("picture", "wall", (0.8, 0.04, 0.6), (200, 90, 160), (_LIV, _BED, _STUDY), z_bottom_m=1.35),
    Category("carpet", "floor", (2.0, 1.4, 0.02), (150, 60, 60), (_LIV, _BED, _STUDY), collides=False),
    Category("table", "floor", (1.4, 0.9, 0.75), (150, 100, 50), (_LIV, _KIT, _STUDY)),
    Category("window", "wall", (1.2, 0.06, 1.2), (150, 210, 250), _ALL, z_bottom_m=0.9),
    Category("mirror", "wall", (0.6, 0.03, 0.9), (210, 225, 235), (_BATH, _BED), z_bottom_m=1.0),
    Category("door", "wall", (0.9, 0.06, 2.05), (120, 80, 40), (_LIV, _KIT, _STUDY)),
    Category("cabinet", "floor", (1.0, 0.5, 0.9), (170, 130, 90), (_KIT, _LIV, _BATH, _STUDY)),
    Category("counter", "floor", (1.8, 0.6, 0.92), (220, 220, 210), (_KIT,)),
    Category("couch", "floor", (2.1, 0.9, 0.85), (80, 90, 170), (_LIV,)),
    Category("fridge", "floor", (0.8, 0.7, 1.8), (235, 235, 240), (_KIT,)),
    Category("washer_dryer", "floor", (0.65, 0.65, 0.9), (245, 245, 245), (_BATH, _KIT)),
    Category("shower", "floor", (0.9, 0.9, 2.0), (180, 220, 230), (_BATH,)),
    Category("chest_of_drawers", "floor", (1.0, 0.5, 1.0), (130, 90, 60), (_BED, _LIV)),
    Category("stand", "floor", (0.6, 0.45, 0.7), (90, 70, 60), (_LIV, _BED, _STUDY)),
    Category("bed", "floor", (1.6, 2.0, 0.55), (200, 200, 240), (_BED,)),
    Category("wall_lamp", "wall", (0.25, 0.15, 0.3), (255, 220, 120), (_LIV, _BED, _STUDY), z_bottom_m=1.6),
    Category("floor_lamp", "floor", (0.4, 0.4, 1.6), (240, 210, 140), (_LIV, _BED, _STUDY)),
    Category("shelves", "floor", (1.0, 0.35, 1.8), (160, 120, 80), (_LIV, _STUDY, _KIT)),
    Category("bench", "floor", (1.2, 0.4, 0.45), (110, 80, 50), (_LIV, _BED)),
    Category("table_lamp", "surface", (0.3, 0.3, 0.45), (250, 200, 100), (_LIV, _BED, _STUDY)),
    Category("coffee_maker", "surface", (0.3, 0.3, 0.35), (40, 40, 40), (_KIT,)),
    Category("trashcan", "floor", (0.35, 0.35, 0.6), (90, 90, 90), _ALL),
    # -- completing the set to 51 ------------------------------------------------------
    Category("chair", "floor", (0.5, 0.5, 0.9), (140, 110, 70), (_KIT, _STUDY, _LIV)),
    Category("desk", "floor", (1.3, 0.7, 0.75), (120, 100, 80), (_STUDY, _BED)),
    Category("armchair", "floor", (0.9, 0.9, 0.9), (170, 70, 90), (_LIV, _STUDY)),
    Category("tv", "wall", (1.2, 0.08, 0.7), (20, 20, 25), (_LIV, _BED), z_bottom_m=1.0),
    Category("sink", "floor", (0.8, 0.55, 0.85), (225, 235, 240), (_BATH, _KIT)),
    Category("toilet", "floor", (0.45, 0.7, 0.75), (250, 250, 250), (_BATH,)),
    Category("bathtub", "floor", (1.7, 0.8, 0.6), (235, 240, 245), (_BATH,)),
    Category("stove", "floor", (0.75, 0.65, 0.9), (60, 60, 65), (_KIT,)),
    Category("oven", "floor", (0.65, 0.65, 0.9), (80, 80, 90), (_KIT,)),
    Category("microwave", "surface", (0.5, 0.38, 0.3), (190, 190, 200), (_KIT,)),
    Category("dishwasher", "floor", (0.6, 0.6, 0.85), (200, 200, 205), (_KIT,)),
    Category("nightstand", "floor", (0.5, 0.45, 0.6), (150, 110, 80), (_BED,)),
    Category("wardrobe", "floor", (1.4, 0.6, 2.0), (140, 100, 70), (_BED,)),
    Category("bookcase", "floor", (0.9, 0.35, 1.9), (100, 70, 45), (_STUDY, _LIV)),
    Category("piano", "floor", (1.5, 0.6, 1.2), (15, 15, 15), (_LIV,)),
    Category("treadmill", "floor", (0.8, 1.8, 1.3), (70, 75, 80), (_STUDY, _LIV, _BED)),
    Category("coat_rack", "floor", (0.5, 0.5, 1.8), (90, 60, 40), (_LIV,)),
    Category("shoe_rack", "floor", (0.9, 0.35, 0.5), (130, 110, 90), (_LIV,)),
    Category("laundry_basket", "floor", (0.5, 0.4, 0.55), (210, 190, 150), (_BATH, _BED)),
    Category("ironing_board", "floor", (1.3, 0.4, 0.9), (180, 200, 220), (_BED, _KIT)),
    Category("toy_chest", "floor", (0.9, 0.5, 0.55), (230, 150, 40), (_BED, _LIV)),
    Category("aquarium", "surface", (0.8, 0.35, 0.5), (60, 150, 220), (_LIV, _STUDY)),
    Category("fireplace", "floor", (1.4, 0.45, 1.1), (150, 70, 50), (_LIV,)),
    Category("towel_rack", "wall", (0.6, 0.12, 0.6), (240, 200, 200), (_BATH,), z_bottom_m=1.1),
    Category("clock", "wall", (0.35, 0.05, 0.35), (230, 230, 200), (_KIT, _LIV, _STUDY), z_bottom_m=1.7),
    Category("radiator", "floor", (1.0, 0.12, 0.6), (235, 235, 225), _ALL),
    Category("laptop", "surface", (0.35, 0.25, 0.03), (70, 70, 80), (_STUDY, _LIV, _BED)),
)

assert len(CATEGORIES) == 51, len(CATEGORIES)
CATEGORY_NAMES: tuple[str, ...] = tuple(c.name for c in CATEGORIES)
CATEGORY_INDEX: dict[str, int] = {n: i for i, n in enumerate(CATEGORY_NAMES)}
NUM_CATEGORIES = len(CATEGORIES)
# Floor objects that a `surface` object may stand on.
SUPPORT_CATEGORIES = ("table", "counter", "desk", "nightstand", "cabinet", "chest_of_drawers", "stand", "shelves")

# Structural geometry that is not an object category (walls, floor), with its colour.
WALL_RGB = (205, 200, 190)
FLOOR_RGB = (120, 110, 100)


def category(name: str) -> Category:
    """The category called `name`; a clear error names the unknown one."""
    try:
        return CATEGORIES[CATEGORY_INDEX[name]]
    except KeyError:
        raise ValueError(f"unknown object category {name!r}; known: {', '.join(CATEGORY_NAMES)}") from None
