"""The `demo` preset: the paper preset's episodes (activity durations, walks, apartments) in a
few scenes, so `conav demo` shows the shipped policy, trained on the paper preset, on the kind of
episode it knows."""

import dataclasses
import warnings

import numpy as np
import pytest

from conav_jax.data.episodes import MIN_HUMAN_PATH_M, BlockedStandingPoint, generate_dataset, load_split
from conav_jax.data.presets import preset
from conav_jax.eval.demo import DEMO_PRESET


@pytest.fixture(scope="module")
def demo_train(tmp_path_factory):
    """One train scene of the demo preset, six episodes (and the one val episode a dataset needs)."""
    cfg = dataclasses.replace(preset("demo"), train_scenes=1, train_episodes=6, val_episodes=1, val_scenes=1,
                              minival_scenes=0, minival_episodes=0)
    out = tmp_path_factory.mktemp("demo")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BlockedStandingPoint)
        generate_dataset(cfg, out)
    return load_split(out, "train")


def test_demo_is_the_paper_preset_in_a_few_scenes():
    demo, paper = preset(DEMO_PRESET), preset("paper")
    assert (demo.task, demo.motion, demo.scenes, demo.nav) == (paper.task, paper.motion, paper.scenes, paper.nav)
    sizes = demo.split_sizes()
    assert sum(n for n, _ in sizes.values()) <= 6 and sum(n for _, n in sizes.values()) <= 40
    assert sizes["val"][1] >= 12  # enough val episodes that the shipped agent's successes show


def test_demo_activities_last_as_long_as_the_papers(demo_train):
    motion, dt = preset("paper").motion, preset("paper").motion.control_dt_s
    shortest_s = motion.activity_loops[0] * motion.activity_clip_s[0]
    longest_s = motion.activity_loops[1] * motion.activity_clip_s[1]
    e = demo_train.episodes
    activity_a_s = e["t_walk_start"] * dt
    activity_b_s = (e["t_end"] - e["t_arrive"]) * dt  # the clip, after a turn of at most a few steps
    assert np.all((activity_a_s >= shortest_s - dt) & (activity_a_s <= longest_s + dt)), activity_a_s
    assert np.all((activity_b_s >= shortest_s - dt) & (activity_b_s <= longest_s + 2.0)), activity_b_s
    # tiny's activities last at most 6 s; the paper's average some 24 s
    assert activity_a_s.mean() > 2 * preset("tiny").motion.activity_clip_s[1]


def test_demo_walks_and_episodes_are_paper_sized(demo_train):
    e, nav = demo_train.episodes, demo_train.navs[0]
    human_path_m = [nav.fields[fb][nav.grid.to_cell(nav.stand_poses[fa][:2])] for fa, fb in zip(e["field_a"], e["field_b"])]
    assert min(human_path_m) >= MIN_HUMAN_PATH_M
    assert np.mean(e["geodesic_start_goal_m"]) > 4.0  # the paper preset's start-goal mean is some 9 m
    assert np.mean(e["t_end"] + 1) > 300  # steps; tiny's longest episode is some 220
