"""Named dataset presets: `tiny` (seconds on a laptop CPU, for tests), `small` (enough to train
and compare agents on one GPU), `paper` (the paper's split sizes: 49 scenes, 37 train / 12 val,
20,293 / 4,962 episodes, mean episode length near 539 steps) and `demo` (`conav demo`: the paper
preset's apartments, activities and walks in 5 scenes and 30 episodes, so the shipped policy,
trained on the paper preset, meets the activity durations and distances it knows; tiny's
activities last 4-6 s, once, where the paper's clips of 4-12 s loop 2-4 times).

Every preset adds a `minival` split on scenes of its own, disjoint from train and val, for
choosing hyper-parameters without touching the reported val split: tiny 1 scene / 6 episodes
(one scene is all a smoke test needs), demo 1 / 2 (it validates the demo's own brief
training), small 2 / 200 and paper 4 / 1,000 (a handful of scenes
so a choice does not fit one apartment; episodes per scene near val's: small 100 vs 125, paper
250 vs ~414). Its scenes are generated after val's, so train and val are the same with or
without it (paper: still 37 / 12 scenes and 20,293 / 4,962 episodes)."""

from __future__ import annotations

import dataclasses

from conav_jax.config import DatasetConfig, MotionConfig, SceneGenConfig

PRESETS: dict[str, DatasetConfig] = {
    "tiny": DatasetConfig(
        name="tiny",
        train_scenes=2,
        val_scenes=1,
        train_episodes=12,
        val_episodes=6,
        minival_scenes=1,
        minival_episodes=6,
        scenes=SceneGenConfig(rooms=(3, 4)),
        motion=MotionConfig(activity_clip_s=(4.0, 6.0)),
    ),
    "small": DatasetConfig(
        name="small",
        train_scenes=16,
        val_scenes=4,
        train_episodes=2000,
        val_episodes=500,
        minival_scenes=2,
        minival_episodes=200,
    ),
    "paper": DatasetConfig(
        name="paper",
        train_scenes=37,
        val_scenes=12,
        train_episodes=20293,
        val_episodes=4962,
        minival_scenes=4,
        minival_episodes=1000,
        scenes=SceneGenConfig(rooms=(4, 7), objects_per_room=(5, 8)),
        # Looping activity clips brings the mean episode length to the paper's ~539 steps.
        motion=MotionConfig(activity_loops=(2, 4)),
    ),
}
# The paper preset's apartments, activities and walks in a few scenes and episodes: the
# activity durations, walking distances and episode lengths the shipped policy was trained on.
PRESETS["demo"] = dataclasses.replace(
    PRESETS["paper"],
    name="demo",
    train_scenes=2,
    val_scenes=2,
    train_episodes=16,
    val_episodes=12,
    minival_scenes=1,
    minival_episodes=2,
)


def preset(name: str, seed: int | None = None) -> DatasetConfig:
    """The preset called `name`, with its seed replaced when one is given."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    cfg = PRESETS[name]
    return cfg if seed is None else dataclasses.replace(cfg, seed=seed)
