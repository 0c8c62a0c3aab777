"""CoNav metrics from per-episode results (../shared/DESIGN.md "Task definition").

Per episode (the env's final `State.metrics`): `t_reach` (first step within the success radius,
-1 if never), `collided_before_reach`, `collided`, `path_length_m` (up to t_reach), `t_arrive`,
`t_end`, `geodesic_start_goal_m`. Then
  FASR  = t_reach <= t_arrive and no human contact before t_reach
  RASR  = t_reach <= t_end, same contact rule
  FASPL, RASPL = success * l / max(l, p)    (l geodesic start->goal, p path length to t_reach)
  CR    = share of episodes with at least one robot-human contact
  AS    = mean steps taken: t_reach if reached, else t_end
Rates are reported in percent, AS in steps.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

METRIC_NAMES = ("FASR", "RASR", "FASPL", "RASPL", "CR", "AS")


def episode_outcomes(m: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per-episode values (arrays over episodes) of every metric: 0/1, SPL weights, steps."""
    t_reach = np.asarray(m["t_reach"], np.float64)
    reached = t_reach >= 0
    clean = np.asarray(m["collided_before_reach"]) < 0.5
    fa = reached & (t_reach <= np.asarray(m["t_arrive"])) & clean
    ra = reached & (t_reach <= np.asarray(m["t_end"])) & clean
    l = np.asarray(m["geodesic_start_goal_m"], np.float64)
    p = np.asarray(m["path_length_m"], np.float64)
    spl = np.where(reached, l / np.maximum(np.maximum(l, p), 1e-9), 0.0)
    return {
        "FASR": fa.astype(np.float64),
        "RASR": ra.astype(np.float64),
        "FASPL": fa * spl,
        "RASPL": ra * spl,
        "CR": (np.asarray(m["collided"]) > 0.5).astype(np.float64),
        "AS": np.where(reached, t_reach, np.asarray(m["t_end"], np.float64)),
    }


def summarize(m: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Mean of each metric over episodes; rates in percent, AS in steps."""
    out = episode_outcomes(m)
    return {k: float(out[k].mean() * (1.0 if k == "AS" else 100.0)) for k in METRIC_NAMES}
