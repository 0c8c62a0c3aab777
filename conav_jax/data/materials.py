"""Surface materials: a base colour, a second colour and a procedural pattern per instance.

Every object instance, the walls and the floor of a scene carry a `Material`; the renderer
(conav_jax.envs.panorama.shade) mixes the two colours by the pattern evaluated at the hit point
and shades the result. Colours come from one palette shared by all categories (doors, walls and
floors from palettes of their own), so two instances of a category usually look different and
two categories may look alike: colour is not a segmentation. Draws are deterministic from a
seed (the scene generator's, or the scene's name for scenes stored without materials).
Data flows: seed -> `draw_scene_materials` -> Scene (JSON) -> `material_rows` -> the env's
per-geom material table.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np

# Pattern kinds by index, as the renderer's material rows encode them. "plain": the base colour.
PATTERNS = ("plain", "stripes", "checks", "noise")
PATTERN_INDEX = {p: i for i, p in enumerate(PATTERNS)}
# One material as a float row: base rgb (3, in [0, 1]), second rgb (3), pattern index, pattern
# period (m), pattern orientation (rad).
MATERIAL_WIDTH = 9

# Object colours, shared by every category.
PALETTE: tuple[tuple[int, int, int], ...] = (
    (200, 60, 50), (225, 120, 40), (235, 190, 60), (150, 170, 60), (70, 140, 70), (40, 110, 100),
    (60, 150, 190), (50, 90, 160), (90, 70, 150), (150, 80, 150), (200, 110, 150), (120, 70, 50),
    (170, 130, 90), (210, 180, 140), (240, 235, 220), (190, 190, 195), (130, 130, 135), (70, 70, 75),
    (30, 30, 35), (160, 40, 60), (100, 160, 140), (220, 150, 120), (110, 110, 60), (180, 200, 230),
)
DOOR_PALETTE = ((120, 80, 40), (150, 105, 65), (90, 60, 35), (200, 195, 185), (170, 140, 100))
WALL_PALETTE = ((205, 200, 190), (225, 220, 205), (190, 200, 205), (215, 200, 180), (200, 205, 190), (235, 235, 235))
FLOOR_PALETTE = ((120, 110, 100), (150, 115, 80), (105, 80, 60), (170, 165, 155), (90, 95, 100), (180, 150, 110))
SKIN_PALETTE = ((240, 200, 170), (220, 170, 135), (180, 130, 95), (130, 90, 60), (90, 60, 45))
# Pattern periods drawn per instance (m): long enough that a millimetre of disagreement in
# where two sensors put a hit changes its colour by well under one level in 255.
PERIOD_RANGE_M = (0.3, 0.9)
# The second colour is the base mixed this far toward another palette colour: patterns read as
# texture on the instance's colour rather than as a second object.
SECOND_COLOUR_MIX = 0.5


@dataclass(frozen=True)
class Material:
    """A surface: `rgb` base colour and `rgb2` second colour (0-255 each), the pattern mixing
    them (PATTERNS), its period in metres and its orientation in degrees (about z)."""

    rgb: tuple[int, int, int]
    rgb2: tuple[int, int, int]
    pattern: str = "plain"
    period_m: float = 0.5
    angle_deg: float = 0.0

    def __post_init__(self):
        if self.pattern not in PATTERNS:
            raise ValueError(f"material pattern must be one of {PATTERNS}, got {self.pattern!r}")
        if not self.period_m > 0:
            raise ValueError(f"material period_m must be positive, got {self.period_m}")

    def to_json_dict(self) -> dict:
        return {"rgb": list(self.rgb), "rgb2": list(self.rgb2), "pattern": self.pattern,
                "period_m": round(self.period_m, 4), "angle_deg": round(self.angle_deg, 2)}

    def row(self) -> np.ndarray:
        """The material as a float32 row of MATERIAL_WIDTH (the renderer's layout)."""
        return np.array([*(np.asarray(self.rgb) / 255.0), *(np.asarray(self.rgb2) / 255.0),
                         PATTERN_INDEX[self.pattern], self.period_m, math.radians(self.angle_deg)], np.float32)


def flat_material(rgb) -> Material:
    """One colour, no pattern."""
    rgb = tuple(int(v) for v in rgb)
    return Material(rgb, rgb)


@dataclass(frozen=True)
class SceneMaterials:
    """A scene's materials: its floor, its walls (all wall boxes share one) and one per object."""

    floor: Material
    walls: Material
    objects: tuple[Material, ...]


def draw_material(rng: np.random.Generator, palette=PALETTE) -> Material:
    """A patterned material: base colour from `palette`, second colour the base mixed toward
    another colour of PALETTE, a pattern kind, period and orientation."""
    base = np.asarray(palette[int(rng.integers(len(palette)))], np.float64)
    other = np.asarray(PALETTE[int(rng.integers(len(PALETTE)))], np.float64)
    second = np.round(base + SECOND_COLOUR_MIX * (other - base)).astype(int)
    return Material(tuple(int(v) for v in base), tuple(int(v) for v in second),
                    PATTERNS[1 + int(rng.integers(len(PATTERNS) - 1))],
                    round(float(rng.uniform(*PERIOD_RANGE_M)), 4), round(float(rng.uniform(0.0, 180.0)), 2))


def draw_scene_materials(rng: np.random.Generator, categories: list[str]) -> SceneMaterials:
    """Materials for a scene whose objects have `categories`, in order: doors from DOOR_PALETTE,
    other objects from PALETTE, walls and floor from their own palettes."""
    floor = draw_material(rng, FLOOR_PALETTE)
    walls = draw_material(rng, WALL_PALETTE)
    objects = tuple(draw_material(rng, DOOR_PALETTE if c == "door" else PALETTE) for c in categories)
    return SceneMaterials(floor, walls, objects)


def name_seed(name: str) -> int:
    """A seed from a scene's name (for scenes stored without materials)."""
    return zlib.crc32(name.encode())


def _hash(x: np.ndarray) -> np.ndarray:
    """A 32-bit integer mix (lowbias32) of uint32 `x`, elementwise."""
    x = np.asarray(x, np.uint32)
    with np.errstate(over="ignore"):
        x = (x ^ (x >> np.uint32(16))) * np.uint32(0x7FEB352D)
        x = (x ^ (x >> np.uint32(15))) * np.uint32(0x846CA68B)
    return x ^ (x >> np.uint32(16))


def clothing_rgb(episode: np.ndarray) -> np.ndarray:
    """(N, 3, 3) uint8 colours of the humanoid's (skin, shirt, trousers) in episodes `episode`
    (N,) (indices into a split): a pure function of the index, shirt and trousers distinct."""
    e = np.asarray(episode, np.uint32)
    h = [_hash(e * np.uint32(3) + np.uint32(k) + np.uint32(0x9E3779B9)) for k in range(3)]
    n = len(PALETTE)
    skin = np.asarray(SKIN_PALETTE)[h[0] % len(SKIN_PALETTE)]
    shirt_i = h[1] % n
    trousers_i = (shirt_i + 1 + h[2] % (n - 1)) % n
    return np.stack([skin, np.asarray(PALETTE)[shirt_i], np.asarray(PALETTE)[trousers_i]], axis=1).astype(np.uint8)


__all__ = [
    "DOOR_PALETTE", "FLOOR_PALETTE", "MATERIAL_WIDTH", "Material", "PALETTE", "PATTERNS", "PATTERN_INDEX",
    "SKIN_PALETTE", "SceneMaterials", "WALL_PALETTE", "clothing_rgb", "draw_material", "draw_scene_materials", "flat_material",
    "name_seed",
]
