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
    """Humanoid motion: activity clips, walking and the turns between them (conav_jax.motion)."""

    control_dt_s: float = 0.1  # keyframes are stored at the control rate
    walk_speed_mps: tuple[float, float] = (1.0, 1.3)
    activity_clip_s: tuple[float, float] = (4.0, 12.0)
    # An activity is its clip played this many times (inclusive range). The paper preset
    # loops clips to reach the paper's mean episode length (~539 steps).
    activity_loops: tuple[int, int] = (1, 1)
    transition_s: float = 0.5  # blend between activity pose and gait
    humanml3d_fps: float = 20.0  # HumanML3D `new_joints` frame rate
    human_radius_m: float = 0.25  # clearance of the walking human from furniture
    # Transitions turn the body in place no faster than this; a bigger turn takes longer than
    # transition_s.
    turn_in_place_max_radps: float = 4.0

    # Walking gait (conav_jax.motion.gait). Step length grows with speed, as people's does:
    # walk_step_length_m * (speed / walk_step_ref_speed_mps) ** walk_step_speed_exponent, with
    # speeds below walk_step_min_speed_mps taking that speed's step; the cadence (steps/s) is
    # speed / step length. A stride is two steps, snapped so the path holds a whole number.
    walk_step_length_m: float = 0.56
    walk_step_ref_speed_mps: float = 1.2
    walk_step_speed_exponent: float = 0.6
    walk_step_min_speed_mps: float = 0.2
    walk_step_width_m: float = 0.105  # footprint's distance sideways from the path
    walk_arm_swing_rad: float = 0.3  # arm pitch amplitude, forward with the opposite leg
    walk_arm_hang_scale: float = 0.97  # wrist-to-shoulder distance vs rest: elbows a little bent
    # Per-walker style within these ranges when the walk has an rng (every episode does): a step
    # length multiplier, the arm swing and the step width. The averages above otherwise.
    walk_step_length_scale_range: tuple[float, float] = (0.93, 1.07)
    walk_arm_swing_range_rad: tuple[float, float] = (0.22, 0.38)
    walk_step_width_range_m: tuple[float, float] = (0.09, 0.12)
    # A foot's cycle as shares of a stride. The stance share is on the short side, so that the
    # swinging foot (whose speed is speed / (1 - stance)) moves at most ~0.3 m per 0.1 s frame
    # at 1.3 m/s. Within stance: flat by walk_foot_flat_share after heel strike, heel off and
    # rolling on the toe after walk_heel_off_share.
    walk_stance_share: float = 0.5
    walk_foot_flat_share: float = 0.12
    walk_heel_off_share: float = 0.33
    walk_heel_strike_pitch_rad: float = -0.25  # toe up at heel strike
    walk_toe_off_pitch_rad: float = 0.9  # toe down at toe off
    walk_ankle_ahead_share: float = 0.4  # ankle ahead of the hip at heel strike, share of a step
    walk_clearance_m: float = 0.06  # swing foot's lift at mid-swing
    walk_pelvis_height_m: float = 0.93  # mean, a little below standing (knees soft)
    walk_pelvis_bob_m: float = 0.015  # up and down, highest at each mid-stance
    walk_pelvis_twist_rad: float = 0.07  # yaw: the hip of the leading leg forward
    walk_pelvis_roll_rad: float = 0.03
    walk_spine_twist_rad: float = 0.1  # yaw: the shoulders counter-rotate against the pelvis
    walk_spine_lean_rad: float = 0.06  # forward
    walk_head_pitch_rad: float = 0.05  # looking slightly down
    # The walking heading turns a right-angle corner over +-this much arc (more for sharper turns).
    walk_turn_half_arc_m: float = 0.6


@dataclass(frozen=True)
class SceneGenConfig:
    """Procedural apartments (conav_jax.data.scenegen)."""

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
    """Occupancy grid and geodesic fields (conav_jax.nav.navigation)."""

    cell_m: float = 0.1
    unreachable_m: float = 1.0e4  # geodesic value of cells no path reaches


@dataclass(frozen=True)
class DatasetConfig:
    """Episode dataset generation (conav_jax.data.episodes); presets in conav_jax.data.presets."""

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
