"""The phases of an episode's human, one per control step: the single definition of their codes.

compose.py writes them into HumanMotion.phase; the episode arrays (conav_jax.data.episodes) store
them, padded past the episode's end with PHASE_DONE; the simulator and the metrics read them.
"""

from __future__ import annotations

PHASE_ACTIVITY_A = 0  # doing activity A at its standing point
PHASE_WALK = 1  # turning away from A and walking the path to B's standing point
PHASE_ACTIVITY_B = 2  # at the goal: turning to B, then doing activity B
PHASE_DONE = 3  # past the episode's last step (padding)
