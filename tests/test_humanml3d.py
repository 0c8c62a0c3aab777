"""Import of HumanML3D `new_joints` arrays into our Z-up world frame."""

from __future__ import annotations

import numpy as np
import pytest

from conav_jax.config import MotionConfig
from conav_jax.motion.compose import compose_episode_motion
from conav_jax.motion.humanml3d import load_humanml3d_joints
from conav_jax.motion.skeleton import NUM_JOINTS, REST_POSE, J

_FEET = [J["left_ankle"], J["right_ankle"], J["left_foot"], J["right_foot"]]


def _synthetic_humanml3d(frames=41, yaw=0.7, offset=(1.5, 0.3, -2.0), step_m=0.01):
    """REST_POSE turned by `yaw`, walking slowly forward and bobbing, written in HumanML3D's
    frame (x left, y up, z forward), lifted and shifted off the origin."""
    t = np.arange(frames)
    c, s = np.cos(yaw), np.sin(yaw)
    rest = REST_POSE.astype(np.float64)
    turned = np.stack([c * rest[:, 0] - s * rest[:, 1], s * rest[:, 0] + c * rest[:, 1], rest[:, 2]], -1)
    ours = np.repeat(turned[None], frames, axis=0)
    ours[..., 0] += (step_m * t * c)[:, None]
    ours[..., 1] += (step_m * t * s)[:, None]
    ours[:, J["left_wrist"], 2] += 0.05 * np.sin(t / 5.0)  # some motion of the arms, too
    ours[:, :, 2] += 0.02 * (1 - np.cos(t / 3.0))[:, None]  # bob up, never below the start
    y_up = ours[..., [1, 2, 0]] + np.asarray(offset)  # ours (x fwd, y left, z up) -> (left, up, fwd)
    return y_up.astype(np.float32)


def test_a_y_up_clip_arrives_standing_on_our_floor_facing_x_at_the_origin():
    clip = load_humanml3d_joints(_synthetic_humanml3d(), fps=20.0, dt_s=0.1)
    assert clip.dtype == np.float32 and clip.shape[1:] == (NUM_JOINTS, 3)
    first = clip[0]
    np.testing.assert_allclose(first[0, :2], 0.0, atol=1e-5)  # root's first xy at the origin
    assert clip[:, _FEET, 2].min() == pytest.approx(0.0, abs=1e-6)  # floor at the lowest foot
    # Height is along z and the first frame is the rest pose (moved down onto the floor).
    floor = REST_POSE[_FEET, 2].min()
    np.testing.assert_allclose(first, REST_POSE - np.array([0, 0, floor], np.float32), atol=1e-5)
    # Facing +x: the person walks forward along +x.
    assert clip[-1, 0, 0] > 0.15 and abs(clip[-1, 0, 1]) < 1e-4


def test_resampling_20_fps_to_10_hz_halves_the_frame_count():
    assert len(load_humanml3d_joints(_synthetic_humanml3d(41), fps=20.0, dt_s=0.1)) == 21
    assert len(load_humanml3d_joints(_synthetic_humanml3d(40), fps=20.0, dt_s=0.1)) == 20
    # Linear interpolation: frame k at 10 Hz is source frame 2k at 20 fps.
    data = _synthetic_humanml3d(41)
    src = load_humanml3d_joints(data, fps=20.0, dt_s=0.05)
    np.testing.assert_allclose(load_humanml3d_joints(data, fps=20.0, dt_s=0.1), src[::2], atol=1e-6)
    between = load_humanml3d_joints(data, fps=20.0, dt_s=0.075)
    np.testing.assert_allclose(between[1], 0.5 * (src[1] + src[2]), atol=1e-5)


def test_a_npy_file_loads_like_the_array(tmp_path):
    data = _synthetic_humanml3d()
    path = tmp_path / "clip.npy"
    np.save(path, data)
    np.testing.assert_array_equal(load_humanml3d_joints(path), load_humanml3d_joints(data))
    np.testing.assert_array_equal(load_humanml3d_joints(str(path)), load_humanml3d_joints(data))


def test_an_imported_clip_drops_into_an_episode():
    clip = load_humanml3d_joints(_synthetic_humanml3d(step_m=0.0))
    hm = compose_episode_motion(
        np.random.default_rng(0),
        (0, "stand_idle"),
        (1, "sit"),
        (1.0, 1.0, 0.0),
        (4.0, 1.0, np.pi),
        np.array([[1.0, 1.0], [4.0, 1.0]]),
        MotionConfig(),
        clip_a=clip,
    )
    assert hm.t_walk_start == len(clip)
    assert np.linalg.norm(hm.root_xy[: len(clip)] - (1.0, 1.0), axis=1).max() < 1e-4
    assert np.linalg.norm(np.diff(hm.joints, axis=0), axis=-1).max() < 0.35


def test_wrong_shapes_are_rejected_with_the_shape_received():
    with pytest.raises(ValueError, match=r"shape \(T, 22, 3\), got \(10, 66\)"):
        load_humanml3d_joints(np.zeros((10, 66)))
    with pytest.raises(ValueError, match=r"got \(10, 24, 3\)"):
        load_humanml3d_joints(np.zeros((10, 24, 3)))


def test_fewer_than_two_frames_are_rejected():
    with pytest.raises(ValueError, match="at least 2 frames, got 1"):
        load_humanml3d_joints(_synthetic_humanml3d()[:1])


def test_non_finite_values_are_rejected_with_count_and_first_frame():
    data = _synthetic_humanml3d()
    data[3, 5, 1] = np.nan
    data[3, 7, 0] = np.inf
    data[9, 0, 0] = np.nan
    with pytest.raises(ValueError, match="3 non-finite values, the first in frame 3"):
        load_humanml3d_joints(data)


def test_non_positive_fps_and_missing_files_are_rejected(tmp_path):
    with pytest.raises(ValueError, match="fps must be positive"):
        load_humanml3d_joints(_synthetic_humanml3d(), fps=0.0)
    with pytest.raises(ValueError, match="fps must be positive"):
        load_humanml3d_joints(_synthetic_humanml3d(), fps=-20.0)
    with pytest.raises(ValueError, match="not found"):
        load_humanml3d_joints(tmp_path / "missing.npy")
