"""envs.human_crop: the crop around the human holds the human's pixels at any bearing, across
the panorama's seam too, is the panorama's own pixels, batches under vmap, and refuses bad input."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from worlds import make_split

from conav_jax.geometry import to_frame
from conav_jax.motion.skeleton import CAPSULE_BONES, JOINT_NAMES
from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.human_crop import crop_window, default_crop_hw, human_crop

jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})
HW, CROP = (112, 448), (64, 64)
# The hall's human stands at the fridge, (1.25, 2.0), until step 10.
HUMAN_XY = np.array([1.25, 2.0], np.float32)
# Bearings of the human from the robot's heading: ahead, left, right, and behind, where the
# panorama's seam is (pi: the crop straddles it exactly; +-(pi - 0.03): mostly on one side).
BEARINGS = (0.0, 1.2, -2.0, math.pi, math.pi - 0.03, -math.pi + 0.03)
LEGS = np.array([any(k in JOINT_NAMES[i] + JOINT_NAMES[j] for k in ("hip", "knee", "ankle", "foot"))
                 for i, j, _ in CAPSULE_BONES])


@pytest.fixture(scope="module")
def hall():
    return ConavEnv(episodes=make_split([(5.0, 2.0, 0.0)]), config=EnvConfig(sensor=SensorConfig(resolution=HW)))


def _poses(distance_m: float) -> np.ndarray:
    """Robot poses (x, y, yaw) `distance_m` east of the human (three directions) that see it at
    each of BEARINGS."""
    out = []
    for side in (0.0, 0.4, -0.4):
        xy = HUMAN_XY + distance_m * np.array([math.cos(side), math.sin(side)], np.float32)
        to_human = math.atan2(*(HUMAN_XY - xy)[::-1])
        out += [(xy[0], xy[1], to_human - b) for b in BEARINGS]
    return np.asarray(out, np.float32)


def _render(env, poses):
    """(rgbd (P, H, W, 4), geom ids (P, H, W), human_pos (P, 2)) for robot poses (P, 3) at step 0."""

    def one(pose):
        rgbd, ids = env.render_at(0, pose, 0)
        return rgbd, ids, to_frame(env.bank.root_xy[0, 0], pose[:2], pose[2])

    return jit(jax.vmap(one))(jnp.asarray(poses))


def _window_mask(pos):
    """(H, W) bool: the pixels `crop_window` picks for a human at `pos`."""
    first_row, cols = crop_window(HW, pos, CROP)
    mask = np.zeros(HW, bool)
    mask[int(first_row) : int(first_row) + CROP[0], np.asarray(cols)] = True
    return mask


@pytest.mark.parametrize("distance_m", [2.0, 3.0])
def test_every_pixel_of_the_human_is_inside_the_crop(hall, distance_m):
    _, ids, pos = _render(hall, _poses(distance_m))
    human = np.asarray(ids) >= hall.layout.human_start
    for k in range(len(pos)):
        assert human[k].sum() > 100, k  # visible: nothing stands between robot and human
        window = _window_mask(pos[k])
        assert window.sum() == CROP[0] * CROP[1]
        assert not (human[k] & ~window).any(), (k, BEARINGS[k % len(BEARINGS)])
    # Behind the robot the human straddles the seam: its pixels sit in both edge columns.
    behind = human[BEARINGS.index(math.pi)]
    assert behind[:, 0].any() and behind[:, -1].any()


def test_closer_than_the_crop_is_tall_the_head_and_body_stay_inside(hall):
    # At 1.5 m a standing human is ~75 rows tall: the crop keeps the top, the feet may fall out.
    _, ids, pos = _render(hall, _poses(1.5))
    capsule = np.asarray(ids) - hall.layout.human_start
    for k in range(len(pos)):
        upper = (capsule[k] >= 0) & ~LEGS[np.clip(capsule[k], 0, len(LEGS) - 1)]
        assert upper.sum() > 100 and not (upper & ~_window_mask(pos[k])).any(), k


def test_the_crop_is_the_panoramas_own_pixels_and_batches_under_vmap(hall):
    rgbd, _, pos = _render(hall, _poses(2.0)[:6])
    crops = jit(jax.vmap(lambda x, p: human_crop(x, p, CROP)))(rgbd, pos)
    assert crops.shape == (6, *CROP, 4) and crops.dtype == rgbd.dtype
    for k in range(6):
        first_row, cols = crop_window(HW, pos[k], CROP)
        expected = np.asarray(rgbd[k])[int(first_row) : int(first_row) + CROP[0]][:, np.asarray(cols)]
        np.testing.assert_array_equal(crops[k], expected)


def test_rows_frame_the_body_by_distance_and_stay_in_the_panorama():
    rows = [int(crop_window(HW, np.array([d, 0.0], np.float32), CROP)[0]) for d in (1.0, 2.0, 4.0, 50.0)]
    assert rows[0] <= rows[1] and 0 <= min(rows) and max(rows) <= HW[0] - CROP[0]
    # A far human is a short stripe at the horizon (row 55.5): the crop is centred near it.
    assert abs(rows[3] + (CROP[0] - 1) / 2 - 55.5) < 2
    # Ahead: the centre columns (223, 224 face the heading); behind: both edges of the seam.
    cols = np.asarray(crop_window(HW, np.array([2.0, 0.0], np.float32), (8, 4))[1])
    np.testing.assert_array_equal(cols, [222, 223, 224, 225])
    cols = np.asarray(crop_window(HW, np.array([-2.0, 0.0], np.float32), (8, 4))[1])
    np.testing.assert_array_equal(cols, [446, 447, 0, 1])


def test_bad_input_fails_loudly():
    rgbd = jnp.zeros((*HW, 4))
    pos = jnp.array([2.0, 0.0])
    with pytest.raises(ValueError, match="does not fit"):
        human_crop(rgbd, pos, (128, 64))
    with pytest.raises(ValueError, match="does not fit"):
        human_crop(jnp.zeros((32, 128, 4)), pos, (64, 64))
    with pytest.raises(ValueError, match=r"\(H, W, C\)"):
        human_crop(rgbd[0], pos, CROP)
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        human_crop(rgbd, jnp.zeros(3), CROP)
    with pytest.raises(ValueError, match="positive integers"):
        human_crop(rgbd, pos, (0, 64))
    with pytest.raises(ValueError, match="finite"):
        human_crop(rgbd, jnp.array([np.nan, 1.0]), CROP)
    # Traced, a NaN position cannot raise: the crop is NaN throughout, never a made-up view.
    crop = jit(lambda p: human_crop(rgbd, p, CROP))(jnp.array([np.nan, 1.0]))
    assert np.isnan(crop).all()


def test_the_default_crop_fits_the_panorama_the_agents_render():
    assert default_crop_hw((112, 448)) == (64, 64)
    assert default_crop_hw((32, 128)) == (32, 32)
    assert default_crop_hw((20, 80)) == (16, 16)  # rounded down to whole 8-pixel patches
    with pytest.raises(ValueError, match="patch"):
        default_crop_hw((4, 16))
