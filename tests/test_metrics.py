"""envs.metrics on hand-built episode results: every success rule, the paper's SPL in steps beside
the metre version, CR up to the first reach and CR_full up to t_end."""

import numpy as np
import pytest

from conav_jax.envs.metrics import episode_outcomes, path_weight, shortest_path_steps, summarize

NAMES = ("t_reach", "t_arrive", "t_end", "collided_before_reach", "collided", "shortest_path_steps",
         "geodesic_start_goal_m", "path_length_m")


def results(*rows, **extra):
    """Env-style final metrics from rows of NAMES values; `extra` adds whole columns."""
    out = {n: np.array([r[i] for r in rows], np.float32) for i, n in enumerate(NAMES)}
    out.update({k: np.asarray(v, np.float32) for k, v in extra.items()})
    return out


def test_shortest_path_steps_is_the_papers_l_in_control_steps():
    # v_max 1 m/s x 0.1 s = 0.1 m a step; radius 1 m.
    g = np.array([0.5, 1.0, 1.05, 2.0, 3.3, 12.34], np.float32)  # float32, as the episodes store them
    np.testing.assert_array_equal(shortest_path_steps(g, 1.0, 0.1), [0, 0, 1, 10, 23, 114])
    with pytest.raises(ValueError, match="max_step_m > 0"):
        shortest_path_steps(g, 1.0, 0.0)


def test_path_weight_is_one_when_the_robot_starts_inside_the_radius():
    np.testing.assert_allclose(path_weight([0, 10, 10, 10], [7, 10, 20, 5]), [1.0, 1.0, 0.5, 1.0])


def test_a_waiting_robot_scores_a_lower_spl_in_steps_than_a_direct_one():
    # Same start and goal (g = 3 m: l = 20 steps). Both reach before the human: one drives
    # straight (reach at step 20, path 2 m), one waits 20 steps first (reach at 40, path 2 m).
    m = results((20, 60, 90, 0, 0, 20, 3.0, 2.0), (40, 60, 90, 0, 0, 20, 3.0, 2.0))
    out = episode_outcomes(m)
    np.testing.assert_allclose(out["FASR"], [1, 1])
    np.testing.assert_allclose(out["FASPL"], [1.0, 0.5])
    np.testing.assert_allclose(out["FASPL_m"], [1.0, 1.0])  # metres cannot tell them apart
    s = summarize(m)
    assert s["FASPL"] == pytest.approx(75.0) and s["FASPL_m"] == pytest.approx(100.0)


def test_a_touch_before_the_reach_voids_fasr_and_rasr_but_one_on_the_reaching_step_does_not():
    m = results(
        (10, 20, 40, 1, 1, 5, 2.0, 2.0),  # touched the human before reaching in time
        (10, 20, 40, 0, 1, 5, 2.0, 2.0),  # touched it on the reaching step only
        (30, 20, 40, 1, 1, 5, 2.0, 2.0),  # late and touched before
    )
    out = episode_outcomes(m)
    np.testing.assert_array_equal(out["FASR"], [0, 1, 0])
    np.testing.assert_array_equal(out["RASR"], [0, 1, 0])
    np.testing.assert_allclose(out["FASPL"], [0, 5 / 10, 0])
    np.testing.assert_array_equal(out["CR"], [1, 1, 1])


def test_late_and_never_reached_episodes():
    m = results((25, 20, 40, 0, 0, 5, 2.0, 2.5), (41, 20, 40, 0, 0, 5, 2.0, 2.5), (-1, 20, 50, 0, 1, 5, 2.0, 9.0))
    out = episode_outcomes(m)
    np.testing.assert_array_equal(out["FASR"], [0, 0, 0])
    np.testing.assert_array_equal(out["RASR"], [1, 0, 0])
    np.testing.assert_allclose(out["RASPL"], [5 / 25, 0, 0])
    np.testing.assert_allclose(out["RASPL_m"], [2.0 / 2.5, 0, 0])
    np.testing.assert_array_equal(out["AS"], [25, 41, 50])  # t_end when never reached


def test_cr_full_counts_contacts_after_the_reach_only_when_episodes_ran_to_the_end():
    m = results((10, 20, 40, 0, 0, 5, 2.0, 2.0), (10, 20, 40, 0, 0, 5, 2.0, 2.0), collided_full=[1, 0])
    s = summarize(m)
    assert s["CR"] == 0.0 and s["CR_full"] == 50.0 and s["FASR"] == 100.0
    del m["collided_full"]
    assert "CR_full" not in summarize(m)
