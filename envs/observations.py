"""What an agent can observe: the table of observation keys (shape, dtype, units, frame, and
the privileged input a key is, if any).

The env computes a key only when asked for it (ConavEnv.observe's `keys`); an agent reads the
keys it declares (envs.agents.base), and a privileged key reaches only an agent that lists its
privileged input. Shapes are written in the env config's terms and made concrete by
`observation_shapes`. A new sensor is one row here and one branch in ConavEnv's observation.
"""

from __future__ import annotations

from typing import NamedTuple

from conav_jax.data.activities import NUM_ACTIVITIES
from conav_jax.data.categories import NUM_CATEGORIES
from conav_jax.envs.agents.base import FUTURE_HUMAN_POSITIONS, GROUND_TRUTH_INTENTIONS, ORACLE_SEGMENTATION


class Observation(NamedTuple):
    """One row of the observation table."""

    key: str
    shape: tuple[str | int, ...]  # "H", "W", "W/4" (SensorConfig), "history", "future" (EnvConfig), or sizes
    dtype: str
    units: str
    frame: str
    privileged: str | None  # the privileged input (envs.agents.base) an agent reading it declares; None: a sensor
    description: str


OBSERVATIONS: tuple[Observation, ...] = (
    Observation("rgbd", ("H", "W", 4), "float32", "RGB in [0, 1]; depth in metres", "robot camera, panoramic",
                None, "the 360-degree panorama: colour and depth, column 0 behind the robot"),
    Observation("front", ("H", "W/4", 4), "float32", "as rgbd", "robot camera, forward quarter",
                None, "the panorama's forward quarter"),
    Observation("gps_compass", (3,), "float32", "metres, metres, radians", "the episode's start pose",
                None, "the robot's (x, y, yaw) relative to where it started"),
    Observation("human_pos", (2,), "float32", "metres", "robot (x forward, y left)",
                None, "where the human is now"),
    Observation("human_history", ("history", 2), "float32", "metres", "robot (x forward, y left)",
                None, "the human's last positions, oldest first, the current one last"),
    Observation("segmentation", ("H", "W"), "int32", "object category id, -1 for none", "as rgbd",
                ORACLE_SEGMENTATION, "each pixel's object category (sky, floor, walls and the humanoid: -1)"),
    Observation("activity_probs", (NUM_ACTIVITIES,), "float32", "probability", "none",
                GROUND_TRUTH_INTENTIONS, "one-hot of the human's activity B"),
    Observation("object_probs", (NUM_CATEGORIES,), "float32", "probability", "none",
                GROUND_TRUTH_INTENTIONS, "one-hot of the category of the object of activity B"),
    Observation("future_traj", ("future", 2), "float32", "metres", "robot (x forward, y left)",
                FUTURE_HUMAN_POSITIONS, "the human's next positions"),
)
OBSERVATION_KEYS = tuple(o.key for o in OBSERVATIONS)
SENSOR_KEYS = tuple(o.key for o in OBSERVATIONS if o.privileged is None)  # what any agent may read
PRIVILEGED_KEYS = {o.key: o.privileged for o in OBSERVATIONS if o.privileged is not None}


def observation(key: str) -> Observation:
    """The table's row of `key`; ValueError naming the known keys otherwise."""
    for o in OBSERVATIONS:
        if o.key == key:
            return o
    raise ValueError(f"unknown observation key {key!r}; known: {', '.join(OBSERVATION_KEYS)}")


def observation_shapes(config) -> dict[str, tuple[int, ...]]:
    """Every key's shape for an env of `config` (envs.config.EnvConfig)."""
    sizes = {"H": config.sensor.height, "W": config.sensor.width, "W/4": config.sensor.width // 4,
             "history": config.human_history_steps, "future": config.future_steps}
    return {o.key: tuple(sizes.get(d, d) for d in o.shape) for o in OBSERVATIONS}


def undeclared_privileged(reads, privileged) -> dict[str, str]:
    """{key: privileged input} for the keys of `reads` whose privileged input is not listed in
    `privileged`; ValueError for an unknown key."""
    return {k: observation(k).privileged for k in reads
            if observation(k).privileged is not None and observation(k).privileged not in privileged}
