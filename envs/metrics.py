"""CoNav metrics from per-episode results, as the paper defines them (../shared/DESIGN.md).

Per episode (the env's final `State.metrics`): `t_reach` (the first control step with the robot
within the success radius, -1 if never), `t_arrive` (the human reaches the goal), `t_end` (the
human ends activity B), `collided_before_reach` (a robot-human contact at a step before
t_reach; a touch on the reaching step itself does not count), `collided` (a contact at any step
up to the first reach, or to t_end if never reached), `collided_full` (a contact at any step up
to t_end, the robot still acting after it reached; only when the env runs episodes to t_end),
`shortest_path_steps` (l below), `geodesic_start_goal_m` and `path_length_m` (the robot's path
up to t_reach). Then, per episode:

  FASR    = t_reach <= t_arrive and no contact before t_reach
  RASR    = t_reach <= t_end, same contact rule
  FASPL   = FASR * w,  RASPL = RASR * w,  with the paper's path weight in steps:
            l = ceil(max(g - r, 0) / (v_max * control_dt))   the fewest control steps that can
                bring the robot from its start to within r of the goal (g: the geodesic
                start-to-goal distance in metres, r: the success radius)
            p = t_reach                                       the control steps the robot took
            w = 1 if l == 0 else l / max(l, p)
  FASPL_m, RASPL_m = the same with metres: w = g / max(g, path length to t_reach)
            (kept beside the paper's: a path up to ~r longer than the geodesic, or a robot that
            waits in place, still scores 1 in metres, but not in steps)
  CR      = a contact up to the first reach (the paper's headline: its episodes end when the
            robot arrives)
  CR_full = a contact at any step up to t_end (what happens once the robot parks at the human's
            destination)
  AS      = t_reach if reached, else t_end (steps)

Rates and SPLs are reported in percent, AS in steps.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

# The paper's Table 2 columns, and the columns we report beside them.
METRIC_NAMES = ("FASR", "RASR", "FASPL", "RASPL", "CR", "AS")
EXTRA_METRIC_NAMES = ("CR_full", "FASPL_m", "RASPL_m")
# Geodesic lengths are stored in float32 (resolution ~2e-6 m at 30 m): a length that is a whole
# number of steps must not round up to the next step. 1e-4 steps is 1e-5 m at 0.1 m per step.
_STEP_ROUNDING = 1e-4


def shortest_path_steps(geodesic_m, success_radius_m: float, max_step_m: float) -> np.ndarray:
    """The paper's SPL `l` in control steps: ceil(max(g - r, 0) / (v_max * control_dt)), with
    `max_step_m` = v_max * control_dt, the farthest the robot moves in one control step."""
    if not success_radius_m >= 0 or not max_step_m > 0:
        raise ValueError(f"need success_radius_m >= 0 and max_step_m > 0, got {success_radius_m}, {max_step_m}")
    steps = np.maximum(np.asarray(geodesic_m, np.float64) - success_radius_m, 0.0) / max_step_m
    return np.maximum(np.ceil(steps - _STEP_ROUNDING), 0.0)


def path_weight(shortest: np.ndarray, taken: np.ndarray) -> np.ndarray:
    """SPL's weight l / max(l, p), 1 where l == 0 (the robot starts inside the radius)."""
    shortest, taken = np.asarray(shortest, np.float64), np.asarray(taken, np.float64)
    return np.where(shortest <= 0.0, 1.0, shortest / np.maximum(np.maximum(shortest, taken), 1e-12))


def episode_outcomes(m: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per-episode values (arrays over episodes) of every metric: 0/1, SPL weights, steps.
    CR_full only when the results hold `collided_full` (episodes run to t_end)."""
    t_reach = np.asarray(m["t_reach"], np.float64)
    reached = t_reach >= 0
    clean = np.asarray(m["collided_before_reach"]) < 0.5
    fa = reached & (t_reach <= np.asarray(m["t_arrive"])) & clean
    ra = reached & (t_reach <= np.asarray(m["t_end"])) & clean
    spl_steps = np.where(reached, path_weight(m["shortest_path_steps"], t_reach), 0.0)
    g = np.asarray(m["geodesic_start_goal_m"], np.float64)
    p = np.asarray(m["path_length_m"], np.float64)
    spl_m = np.where(reached, g / np.maximum(np.maximum(g, p), 1e-9), 0.0)
    out = {
        "FASR": fa.astype(np.float64),
        "RASR": ra.astype(np.float64),
        "FASPL": fa * spl_steps,
        "RASPL": ra * spl_steps,
        "CR": (np.asarray(m["collided"]) > 0.5).astype(np.float64),
        "AS": np.where(reached, t_reach, np.asarray(m["t_end"], np.float64)),
        "FASPL_m": fa * spl_m,
        "RASPL_m": ra * spl_m,
    }
    if "collided_full" in m:
        out["CR_full"] = (np.asarray(m["collided_full"]) > 0.5).astype(np.float64)
    return out


def reported_metrics(outcomes: Mapping[str, np.ndarray]) -> tuple[str, ...]:
    """The metric names present in `outcomes`, in report order: the paper's, then ours."""
    return tuple(k for k in METRIC_NAMES + EXTRA_METRIC_NAMES if k in outcomes)


def summarize(m: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Mean of each metric over episodes; rates in percent, AS in steps."""
    out = episode_outcomes(m)
    return {k: float(out[k].mean() * (1.0 if k == "AS" else 100.0)) for k in reported_metrics(out)}
