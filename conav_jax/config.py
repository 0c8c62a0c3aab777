"""Every tunable number of the benchmark's data side, as frozen dataclasses with defaults.

One place per number: the simulator, trainers and evaluators read these; nothing repeats them.
Units are in the field names (`_m` metres, `_s` seconds, `_mps` m/s, `_radps` rad/s).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

# Dataset splits in generation order: a scene's seed is its index in this order, so a split
# added at the end (minival) leaves the scenes and episodes of the ones before it unchanged.
SPLITS = ("train", "val", "minival")


@dataclass(frozen=True)
class TaskConfig:
    """The CoNav task itself (paper sec. 3.1 and 5.2; ../shared/DESIGN.md "Task definition")."""

    control_dt_s: float = 0.1  # one env step
    robot_radius_m: float = 0.3
    robot_height_m: float = 1.25
    camera_height_m: float = 1.25
    # Actions (v_lin, v_ang) are clipped to [-1, 1] and scaled by these. The paper's
    # "40 m/s, 30 rad/s" is not a physical figure; recorded here, not used.
    v_max_mps: float = 1.0
    w_max_radps: float = 1.57
    paper_v_max_mps: float = 40.0
    paper_w_max_radps: float = 30.0
    success_radius_m: float = 1.0  # robot centre to goal
    # Robot start: placed near the human (facing it) at this distance range.
    robot_start_distance_m: tuple[float, float] = (1.5, 3.0)


@dataclass(frozen=True)
class MotionConfig:
    """Humanoid motion: activity clips and walking (conav_jax.motion)."""

    control_dt_s: float = 0.1  # keyframes are stored at the control rate
    walk_speed_mps: tuple[float, float] = (1.0, 1.3)
    activity_clip_s: tuple[float, float] = (4.0, 12.0)
    # An activity is its clip played this many times (inclusive range). The paper preset
    # loops clips to reach the paper's mean episode length (~539 steps).
    activity_loops: tuple[int, int] = (1, 1)
    transition_s: float = 0.5  # blend between activity pose and gait
    humanml3d_fps: float = 20.0  # HumanML3D `new_joints` frame rate
    human_radius_m: float = 0.25  # clearance of the walking human from furniture


@dataclass(frozen=True)
class SceneGenConfig:
    """Procedural apartments (conav_jax.scenegen)."""

    rooms: tuple[int, int] = (3, 5)  # inclusive range of rooms per apartment
    room_size_m: tuple[float, float] = (3.0, 5.5)
    wall_height_m: float = 2.6
    wall_thickness_m: float = 0.1
    door_width_m: float = 1.0
    objects_per_room: tuple[int, int] = (4, 8)
    standing_offset_m: float = 0.45  # standing point distance in front of an object's face
    max_boxes: int = 96  # pad size of the simulator's geometry arrays


@dataclass(frozen=True)
class NavConfig:
    """Occupancy grid and geodesic fields (conav_jax.navigation)."""

    cell_m: float = 0.1
    unreachable_m: float = 1.0e4  # geodesic value of cells no path reaches


@dataclass(frozen=True)
class DatasetConfig:
    """Episode dataset generation (conav_jax.episodes); presets in conav_jax.presets."""

    name: str = "tiny"
    train_scenes: int = 2
    val_scenes: int = 1
    train_episodes: int = 8
    val_episodes: int = 4
    # `minival`: extra scenes, disjoint from train and val, for choosing hyper-parameters
    # without touching the reported val split. Generated after val, so adding it leaves
    # train and val unchanged. 0 scenes = no minival split (datasets written before it existed).
    minival_scenes: int = 0
    minival_episodes: int = 0
    episodes_per_shard: int = 256
    seed: int = 0
    task: TaskConfig = field(default_factory=TaskConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    scenes: SceneGenConfig = field(default_factory=SceneGenConfig)
    nav: NavConfig = field(default_factory=NavConfig)

    def split_sizes(self) -> dict[str, tuple[int, int]]:
        """split -> (scenes, episodes) in SPLITS order; minival only when it has scenes or episodes."""
        sizes = {sp: (getattr(self, f"{sp}_scenes"), getattr(self, f"{sp}_episodes")) for sp in SPLITS}
        if sizes["minival"] == (0, 0):
            del sizes["minival"]
        return sizes

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "DatasetConfig":
        def tup(x):
            return tuple(x) if isinstance(x, list) else x

        sub = {
            "task": TaskConfig,
            "motion": MotionConfig,
            "scenes": SceneGenConfig,
            "nav": NavConfig,
        }
        kwargs = {}
        for k, v in d.items():
            if k in sub:
                kwargs[k] = sub[k](**{kk: tup(vv) for kk, vv in v.items()})
            else:
                kwargs[k] = v
        return DatasetConfig(**kwargs)
