"""Humanoid motion on the 22-joint HumanML3D skeleton, at the control rate (offline, numpy).

skeleton (joints, rest pose, capsules) -> rig (pose parameters -> joints) -> clips (activity
clips) and gait (walking along a path) -> compose (an episode: activity A, walk, activity B) ->
HumanMotion. humanml3d imports recorded clips that replace the procedural ones.
"""

from conav_jax.motion.clips import activity_clip
from conav_jax.motion.compose import HumanMotion, compose_episode_motion
from conav_jax.motion.gait import walk_along, walk_cycle
from conav_jax.motion.humanml3d import load_humanml3d_joints
from conav_jax.motion.phases import (
    PHASE_ACTIVITY_A,
    PHASE_ACTIVITY_B,
    PHASE_DONE,
    PHASE_WALK,
)

__all__ = [
    "PHASE_ACTIVITY_A",
    "PHASE_ACTIVITY_B",
    "PHASE_DONE",
    "PHASE_WALK",
    "HumanMotion",
    "activity_clip",
    "compose_episode_motion",
    "load_humanml3d_joints",
    "walk_along",
    "walk_cycle",
]
