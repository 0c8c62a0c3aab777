"""Occupancy grid, geodesic fields and A* on hand-built grids."""

import math

import numpy as np
import pytest

from conav_jax.data.scene import scene_from_json_dict
from conav_jax.nav.navigation import (
    OccupancyGrid,
    astar,
    descend,
    geodesic_field,
    line_of_sight,
    occupancy_grid,
    path_length,
    smooth_path,
)

S2 = math.sqrt(2)


def _grid(rows):
    free = np.array([[c == "." for c in r] for r in rows[::-1]])  # first string is the top row
    return OccupancyGrid(free, (0.0, 0.0), 1.0)


def test_geodesic_field_matches_hand_computed_distances():
    g = _grid(
        [
            ".....",
            ".###.",
            ".....",
        ]
    )
    f = geodesic_field(g, (0.5, 0.5))  # goal: bottom-left cell
    expected_bottom = [0, 1, 2, 3, 4]
    np.testing.assert_allclose(f[0], expected_bottom, atol=1e-6)
    # left column goes straight up; the top row then runs right, diagonal into (2, 1) is allowed
    # only where no corner is cut: (2,1) is reached from (2,0) in one straight step.
    assert f[1, 0] == pytest.approx(1) and f[2, 0] == pytest.approx(2)
    assert f[2, 1] == pytest.approx(3)
    assert f[1, 4] == pytest.approx(5)  # up the right column from (0, 4)
    assert f[2, 4] == pytest.approx(6)
    assert np.isinf(f[1, 1:4]).all()  # walls


def test_diagonal_steps_cost_sqrt2_and_never_cut_corners():
    g = _grid(["...", "...", "..."])
    f = geodesic_field(g, (0.5, 0.5))
    assert f[2, 2] == pytest.approx(2 * S2)
    g2 = _grid(["..", "#."])  # bottom-left blocked
    f2 = geodesic_field(g2, (1.5, 0.5))  # goal bottom-right
    # top-left to bottom-right diagonal would cut the blocked corner: must go around
    assert f2[1, 0] == pytest.approx(2.0)


def test_unreachable_cells_are_inf_and_goal_in_wall_gives_all_inf():
    g = _grid([".#.", ".#.", ".#."])
    f = geodesic_field(g, (0.5, 0.5))
    assert np.isinf(f[:, 2]).all()
    assert np.isinf(geodesic_field(g, (1.5, 1.5))).all()


def test_astar_length_equals_geodesic_and_descend_reaches_goal():
    rng = np.random.default_rng(0)
    free = rng.random((30, 40)) > 0.25
    free[0], free[-1], free[:, 0], free[:, -1] = False, False, False, False
    g = OccupancyGrid(free, (0.0, 0.0), 0.1)
    goal = g.to_world(np.argwhere(free)[:1])[0]
    f = geodesic_field(g, goal)
    for cell in np.argwhere(np.isfinite(f))[::37]:
        start = g.to_world(cell[None])[0]
        p = astar(g, start, goal)
        assert p is not None
        assert path_length(p) == pytest.approx(f[tuple(cell)], abs=1e-4)
        d = descend(g, f, start)
        assert np.allclose(d[-1], goal) and path_length(d) == pytest.approx(f[tuple(cell)], abs=1e-4)
    blocked = np.argwhere(~np.isfinite(f) & free)
    if len(blocked):
        assert astar(g, g.to_world(blocked[:1])[0], goal) is None


def test_occupancy_inflates_boxes_by_clearance():
    scene = scene_from_json_dict(
        {
            "format": "conav-scene", "version": 1, "name": "box", "bounds_m": [0, 0, 4, 4],
            "wall_height_m": 2.5, "rooms": [], "walls": [],
            "objects": [{"category": "cabinet", "center_m": [2, 2, 0.45], "size_m": [1, 0.5, 0.9], "yaw_deg": 0}],
        }
    )
    g = occupancy_grid(scene, clearance_m=0.3, cell_m=0.1, robot_height_m=1.25)
    # yaw 0: depth 0.5 along x -> box x in [1.75, 2.25], y in [1.5, 2.5]
    assert not g.is_free((1.5, 2.0))  # 0.25 m from the box
    assert g.is_free((1.35, 2.0))  # 0.4 m from the box
    assert not g.is_free((2.0, 1.25))
    assert g.is_free((2.0, 1.15))


def test_smoothed_path_keeps_line_of_sight_and_is_shorter():
    g = _grid(["......", "..##..", "..##..", "......"])
    p = astar(g, (0.5, 0.5), (5.5, 3.5))
    s = smooth_path(g, p)
    assert path_length(s) <= path_length(p) + 1e-9
    for a, b in zip(s[:-1], s[1:]):
        assert line_of_sight(g, a, b)
