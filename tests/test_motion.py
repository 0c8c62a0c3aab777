"""conav_jax.motion: the skeleton, procedural activity clips (clips.py), the walking gait
(gait.py) and whole-episode human motion (compose.py)."""

from __future__ import annotations

import numpy as np
import pytest

from conav_jax.config import DatasetConfig, MotionConfig
from conav_jax.geometry import wrap_angle_np
from conav_jax.motion.clips import activity_clip
from conav_jax.motion.compose import HumanMotion, compose_episode_motion
from conav_jax.motion.gait import walk_along, walk_cycle
from conav_jax.motion.phases import (
    PHASE_ACTIVITY_A,
    PHASE_ACTIVITY_B,
    PHASE_DONE,
    PHASE_WALK,
)
from conav_jax.motion.primitives import MOTION_PRIMITIVES
from conav_jax.motion.skeleton import (
    NUM_JOINTS,
    PARENTS,
    REST_POSE,
    J,
    capsule_segments,
)

_CHILD = np.array([j for j, p in enumerate(PARENTS) if p >= 0])
_PARENT = np.array([PARENTS[j] for j in _CHILD])
_FEET = [J["left_ankle"], J["right_ankle"], J["left_foot"], J["right_foot"]]
L_PATH = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0]])


def _bone_lengths(joints):
    return np.linalg.norm(joints[..., _CHILD, :] - joints[..., _PARENT, :], axis=-1)


def _max_step_m(joints):
    return float(np.linalg.norm(np.diff(joints, axis=0), axis=-1).max())


def test_rest_pose_stands_on_the_floor_facing_x_about_175cm_tall():
    assert REST_POSE.shape == (NUM_JOINTS, 3) and REST_POSE.dtype == np.float32
    assert abs(REST_POSE[_FEET, 2].min()) < 0.03
    assert REST_POSE[J["left_hip"], 1] > 0 > REST_POSE[J["right_hip"], 1]  # left at +y
    assert REST_POSE[J["head"], 0] >= REST_POSE[J["neck"], 0]  # faces +x
    p0, p1, r = capsule_segments(REST_POSE)
    assert p0.shape == p1.shape == (len(r), 3)
    crown = float((p1[:, 2] + r).max())
    assert 1.70 < crown < 1.80


@pytest.mark.parametrize("primitive", sorted(MOTION_PRIMITIVES))
def test_every_primitive_gives_a_clip_with_rigid_bones_and_feet_above_the_floor(primitive):
    for activity_id in (0, 17, 58):
        clip = activity_clip(activity_id, primitive, 60, np.random.default_rng(activity_id))
        assert clip.shape == (60, NUM_JOINTS, 3) and clip.dtype == np.float32
        assert np.isfinite(clip).all()
        lengths = _bone_lengths(clip)
        assert np.ptp(lengths, axis=0).max() < 1e-3  # constant within the clip, up to 1 mm
        assert clip[:, _FEET, 2].min() >= -0.01
        assert clip[..., 2].min() >= -0.01
        assert _max_step_m(clip) < 0.35
        # Starts and ends in the same neutral standing pose: clips loop and blend.
        np.testing.assert_allclose(clip[0], clip[-1], atol=1e-5)
        np.testing.assert_allclose(clip[0], REST_POSE, atol=0.03)


def test_two_activities_sharing_a_primitive_give_different_clips():
    for primitive in ("wipe", "sit", "stand_idle"):
        a = activity_clip(3, primitive, 80, np.random.default_rng(0))
        b = activity_clip(40, primitive, 80, np.random.default_rng(0))
        assert np.abs(a - b).mean() > 0.01, primitive


def test_same_activity_and_seed_give_identical_bytes_and_a_new_seed_only_a_small_variation():
    a = activity_clip(12, "stir", 70, np.random.default_rng(5))
    b = activity_clip(12, "stir", 70, np.random.default_rng(5))
    c = activity_clip(12, "stir", 70, np.random.default_rng(6))
    other = activity_clip(13, "stir", 70, np.random.default_rng(5))
    assert a.tobytes() == b.tobytes()
    assert not np.array_equal(a, c)
    assert np.abs(a - c).mean() < np.abs(a - other).mean()


def test_unknown_primitive_or_empty_clip_is_rejected():
    with pytest.raises(ValueError, match="unknown motion primitive"):
        activity_clip(0, "juggle", 10, np.random.default_rng(0))
    with pytest.raises(ValueError, match="n_steps"):
        activity_clip(0, "sit", 0, np.random.default_rng(0))


def test_walking_an_l_shaped_path_keeps_the_speed_and_ends_exactly_at_the_path_end():
    cfg = MotionConfig()
    lo, hi = cfg.walk_speed_mps
    for speed in (lo, (lo + hi) / 2, hi):
        joints, root_xy, yaw = walk_along(L_PATH, speed, cfg.control_dt_s)
        n = len(joints)
        assert joints.shape == (n, NUM_JOINTS, 3) and root_xy.shape == (n, 2) and yaw.shape == (n,)
        np.testing.assert_allclose(root_xy[0], L_PATH[0], atol=1e-6)
        np.testing.assert_allclose(root_xy[-1], L_PATH[-1], atol=1e-5)
        step_mps = np.linalg.norm(np.diff(root_xy, axis=0), axis=1) / cfg.control_dt_s
        # Constant speed along the arc (a chord across the corner is a little shorter);
        # whole frames nudge the speed by under a percent or two on a 7 m path.
        assert step_mps.max() <= hi * 1.02
        assert lo * 0.98 <= np.median(step_mps) <= hi * 1.02
        assert abs(7.0 / ((n - 1) * cfg.control_dt_s) - speed) < 0.03 * speed
        assert abs(yaw[0]) < 0.05 and abs(yaw[-1] - np.pi / 2) < 0.05
        assert np.abs(np.diff(np.unwrap(yaw))).max() < 0.35  # the corner is rounded, not snapped


def test_walking_keeps_bones_rigid_feet_above_the_floor_and_planted_feet_still():
    joints, _, _ = walk_along(L_PATH, 1.2, 0.1)
    assert np.ptp(_bone_lengths(joints), axis=0).max() < 1e-3
    assert joints[..., 2].min() >= -0.01
    assert _max_step_m(joints) < 0.35
    # A toe on the floor in two consecutive frames barely moves (no skating).
    toes = joints[:, [J["left_foot"], J["right_foot"]]]
    down = (toes[1:, :, 2] < 0.025) & (toes[:-1, :, 2] < 0.025)
    slide_mps = np.linalg.norm(np.diff(toes[..., :2], axis=0), axis=-1) / 0.1
    assert down.any() and slide_mps[down].max() < 0.3
    # Feet alternate: each foot swings (is lifted) at some point.
    assert (joints[:, J["left_ankle"], 2] > 0.12).any() and (joints[:, J["right_ankle"], 2] > 0.12).any()


def test_walk_cycle_is_root_relative_and_loops():
    cycle = walk_cycle(1.2, 0.1)
    assert cycle.ndim == 3 and cycle.shape[1:] == (NUM_JOINTS, 3)
    np.testing.assert_allclose(cycle[:, 0, :2], 0.0, atol=1e-6)
    wrap_step = np.linalg.norm(cycle[0] - cycle[-1], axis=-1).max()
    assert wrap_step < 0.35


def test_the_gait_reads_its_numbers_from_the_motion_config():
    default = walk_cycle(1.2, 0.1)
    assert walk_cycle(1.2, 0.1, MotionConfig()).tobytes() == default.tobytes()
    # Longer steps at the same speed: a longer stride, so more frames in one cycle.
    assert len(walk_cycle(1.2, 0.1, MotionConfig(walk_step_length_m=0.7))) > len(default)
    low = walk_cycle(1.2, 0.1, MotionConfig(walk_pelvis_height_m=0.88))
    pelvis_drop_m = default[:, J["pelvis"], 2].mean() - low[:, J["pelvis"], 2].mean()
    assert abs(pelvis_drop_m - 0.05) < 1e-5


def test_a_dataset_config_written_before_the_gait_fields_loads_with_their_defaults():
    d = DatasetConfig().to_dict()
    added = [k for k in d["motion"] if k.startswith("walk_") and k != "walk_speed_mps"]
    for k in added + ["turn_in_place_max_radps"]:
        del d["motion"][k]
    assert DatasetConfig.from_dict(d) == DatasetConfig()


def test_numpy_angle_wrap_lies_in_minus_pi_to_pi_and_agrees_with_the_arctan2_one():
    a = np.linspace(-20.0, 20.0, 4001)
    w = wrap_angle_np(a)
    assert (w >= -np.pi).all() and (w < np.pi).all()
    # geometry.wrap_angle's formula, in numpy: calling the jax one here would start a jax backend
    # in the test process before the dataset tests fork their workers.
    by_arctan2 = np.arctan2(np.sin(a), np.cos(a))
    away_from_pi = np.abs(np.abs(w) - np.pi) > 1e-9  # there the two may pick opposite ends
    np.testing.assert_allclose(w[away_from_pi], by_arctan2[away_from_pi], atol=1e-12)


def test_phase_codes_are_one_set_ordered_as_an_episode_runs():
    codes = (PHASE_ACTIVITY_A, PHASE_WALK, PHASE_ACTIVITY_B, PHASE_DONE)
    assert codes == (0, 1, 2, 3)  # stored in the recorded datasets
    # One home: no other module of the project assigns phase codes of its own.
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    homes = {str(p.relative_to(root)) for pkg in ("conav_jax", "envs", "train", "eval") for p in (root / pkg).rglob("*.py")
             if re.search(r"^PHASE_\w+(?:\s*,\s*PHASE_\w+)*\s*=\s*\d", p.read_text(), re.M)}
    assert homes == {"conav_jax/motion/phases.py"}


def _episode(seed, prim_a="wipe", prim_b="sit", cfg=None, **kw) -> HumanMotion:
    return compose_episode_motion(
        np.random.default_rng(seed),
        (5, prim_a),
        (60, prim_b),
        (0.0, 0.0, 2.5),
        (4.0, 3.0, -0.5),
        L_PATH,
        cfg or MotionConfig(),
        **kw,
    )


def test_episode_phases_run_a_walk_b_in_order_with_consistent_times():
    hm = _episode(0)
    T = len(hm.joints)
    assert hm.joints.shape == (T, NUM_JOINTS, 3) and hm.joints.dtype == np.float32
    assert hm.root_xy.shape == (T, 2) and hm.root_yaw.shape == (T,) and hm.phase.dtype == np.int8
    assert hm.t_end == T - 1
    assert 0 < hm.t_walk_start < hm.t_arrive < hm.t_end
    assert (np.diff(hm.phase) >= 0).all()
    assert hm.phase[0] == PHASE_ACTIVITY_A and hm.phase[-1] == PHASE_ACTIVITY_B
    assert hm.phase[hm.t_walk_start - 1] == PHASE_ACTIVITY_A and hm.phase[hm.t_walk_start] == PHASE_WALK
    assert hm.phase[hm.t_arrive - 1] == PHASE_WALK and hm.phase[hm.t_arrive] == PHASE_ACTIVITY_B
    np.testing.assert_allclose(hm.root_xy, hm.joints[:, 0, :2])


def test_episode_human_stays_at_the_standing_points_during_the_activities():
    hm = _episode(1)
    a = hm.phase == PHASE_ACTIVITY_A
    b = hm.phase == PHASE_ACTIVITY_B
    assert np.linalg.norm(hm.root_xy[a] - (0.0, 0.0), axis=1).max() < 0.3
    assert np.linalg.norm(hm.root_xy[b] - (4.0, 3.0), axis=1).max() < 0.3
    np.testing.assert_allclose(hm.root_xy[hm.t_arrive], (4.0, 3.0), atol=1e-4)
    np.testing.assert_allclose(hm.root_yaw[a], 2.5, atol=1e-5)
    np.testing.assert_allclose(hm.root_yaw[-1], -0.5, atol=1e-5)


@pytest.mark.parametrize(
    "prim_a, prim_b",
    [("wipe", "sit"), ("lie_down", "reach_up"), ("walk_in_place", "wash_body"), ("crouch", "open_door")],
)
def test_episode_has_no_joint_jumps_and_feet_stay_above_the_floor(prim_a, prim_b):
    cfg = MotionConfig(walk_speed_mps=(1.3, 1.3), activity_loops=(2, 2))
    for seed in range(3):
        hm = _episode(seed, prim_a, prim_b, cfg)
        assert _max_step_m(hm.joints) < 0.35
        assert hm.joints[..., 2].min() >= -0.01
        assert np.abs(np.diff(np.unwrap(hm.root_yaw))).max() < 0.5  # turns are spread out


def test_episode_loops_activity_clips_and_is_deterministic():
    cfg = MotionConfig(activity_clip_s=(4.0, 4.0), activity_loops=(3, 3))
    hm = _episode(2, cfg=cfg)
    assert hm.t_walk_start == 3 * 40
    again = _episode(2, cfg=cfg)
    assert hm.joints.tobytes() == again.joints.tobytes()


def test_episode_accepts_imported_local_clips():
    clip = activity_clip(9, "drink", 30, np.random.default_rng(0))
    hm = _episode(3, clip_a=clip, clip_b=clip[:20])
    assert hm.t_walk_start == 30
    assert hm.t_end - hm.t_arrive >= 20
    with pytest.raises(ValueError, match=r"\(n, 22, 3\)"):
        _episode(3, clip_a=clip[:, :10])
