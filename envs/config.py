"""Simulator configuration: physics, sensors and the RL reward, with documented defaults.

Task numbers (radius, speeds, success radius, control step) come from conav_jax.config.TaskConfig
of the dataset being simulated; nothing here repeats them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

SENSOR_KINDS = ("auto", "fast", "pallas", "reference")


def resolve_sensor_kind(kind: str) -> str:
    """The caster `kind` names; "auto" is "pallas" on a single visible GPU (121k env steps/s at
    112x448, batch 4096, on an H100 against 65k for "fast"; BENCHMARKS.md) and "fast" elsewhere:
    Triton needs a GPU, and XLA's partitioner cannot split a Pallas call over a device mesh."""
    if kind != "auto":
        return kind
    import jax

    return "pallas" if jax.default_backend() == "gpu" and jax.device_count() == 1 else "fast"


@dataclass(frozen=True)
class SensorConfig:
    """Panoramic RGB-D camera at the robot's camera height.

    Equirectangular: column j looks at azimuth yaw + pi - 2 pi (j + 0.5) / W (the image centre
    faces forward, the robot's left is on the image's left); rows span a vertical field of view
    of 2 pi H / W (square pixels; 90 degrees at 112x448), row 0 at the top.
    """

    height: int = 112
    width: int = 448
    max_depth_m: float = 10.0  # farther hits and no hit read as max_depth and sky colour
    # "fast": our column caster, one fused min over all geoms (nothing of size geoms x H x W
    # reaches memory); "pallas": the same math as a Pallas (Triton) GPU kernel; "reference":
    # mujoco.mjx.ray per pixel; "auto": pallas on one GPU, else fast (resolve_sensor_kind).
    kind: str = "auto"
    # Fast caster: how the min over geoms is written for XLA. "unroll": a running min unrolled
    # over geoms, elementwise chains that XLA fuses whole (only (H, W) buffers; checked in the
    # CPU HLO); "reduce": min-reductions over (geoms, H, W) expressions, which rely on XLA fusing
    # the producer into the reduction (the CPU backend does not for the boxes).
    fast_min: str = "unroll"
    # Pallas caster: image columns per kernel program (a power of two), Triton warps per program,
    # and whether to run the kernel through the Pallas interpreter (any backend; CPU tests).
    pallas_block_w: int = 16
    pallas_num_warps: int = 4
    pallas_interpret: bool = False

    def __post_init__(self):
        if self.kind not in SENSOR_KINDS:
            raise ValueError(f"sensor kind must be one of {SENSOR_KINDS}, got {self.kind!r}")
        if self.fast_min not in ("reduce", "unroll"):
            raise ValueError(f"fast_min must be 'reduce' or 'unroll', got {self.fast_min!r}")
        if self.pallas_block_w < 1 or self.pallas_block_w & (self.pallas_block_w - 1):
            raise ValueError(f"pallas_block_w must be a power of two, got {self.pallas_block_w}")
        if self.height < 4 or self.width < 8 or self.width % 8:
            raise ValueError(f"panorama must be at least 4x8 with width a multiple of 8, got {self.height}x{self.width}")


@dataclass(frozen=True)
class PhysicsConfig:
    """The robot in MJX: a capsule on x/y slide joints and a yaw hinge, velocity-servoed."""

    # MJX step; control_dt / timestep substeps per env step. MuJoCo stiffens contacts at most to
    # a time constant of 2 timesteps: at 0.02 s a robot hitting a wall at 1 m/s sinks 34 mm into
    # it, at 0.01 s only 2 mm.
    timestep_s: float = 0.01
    robot_mass_kg: float = 20.0
    # Velocity servo gains and force limits: reaches a commanded speed within ~2 substeps and
    # cannot push through a wall (the contact wins against at most this force).
    kv_linear: float = 2000.0
    kv_angular: float = 200.0
    force_limit_n: float = 1000.0
    torque_limit_nm: float = 200.0
    contact_tolerance_m: float = 0.005  # analytic contact counts when gaps are below this
    # MJX collides the robot only with the boxes nearest to it: the robot moves at most
    # v_max * control_dt (0.1 m) per step, so the nearest few are all it can touch.
    collision_slots: int = 8
    # The robot's contacts (walls, furniture, humanoid) are frictionless (condim 1; 3 adds
    # friction): it slides along what it touches, as Habitat's navmesh sliding does, and each
    # contact is one constraint row instead of four, so the solver converges in ~3 iterations.
    # Against a 30-iteration solve on random drives into walls: 3/4 iterations match exactly,
    # 2/4 within 1.4 mm; with friction even 4/8 was 2.8 mm off. 32x128 panoramas at batch
    # 32768 on an H100: 713k env steps/s, against 358k with friction at 4/8 (BENCHMARKS.md).
    contact_condim: int = 1
    # Constraint solver budget per substep (MJX defaults to 100 / 50; three dofs need few).
    solver_iterations: int = 3
    ls_iterations: int = 4
    # Substeps unrolled per iteration of the substep scan (1: a rolled loop). Unrolling lets XLA
    # fuse across substeps, but on an H100 10 was no faster (352k vs 358k env steps/s at 32x128)
    # and compiled 2.6x longer; `conav bench sim --physics substep_unroll=N` times it.
    substep_unroll: int = 1

    def __post_init__(self):
        for name in ("timestep_s", "robot_mass_kg", "kv_linear", "kv_angular", "force_limit_n", "torque_limit_nm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"physics {name} must be positive, got {getattr(self, name)}")
        if self.contact_condim not in (1, 3):
            raise ValueError(f"physics contact_condim must be 1 or 3, got {self.contact_condim}")
        for name in ("collision_slots", "solver_iterations", "ls_iterations", "substep_unroll"):
            if getattr(self, name) < 1:
                raise ValueError(f"physics {name} must be at least 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class RewardConfig:
    """Dense reward for RL (imitation ignores it). Per step:
    progress_scale * (geodesic distance to goal before - after)      [metres of progress]
    + reach_first_bonus  once, if the robot reaches the goal before the human arrives
    + reach_late_bonus   once, if it reaches after the human arrived but before activity B ends
    - human_contact_penalty per step touching the human
    - wall_contact_penalty  per step touching a wall or furniture
    - time_cost             every step
    """

    progress_scale: float = 1.0
    reach_first_bonus: float = 10.0
    reach_late_bonus: float = 4.0
    human_contact_penalty: float = 1.0
    wall_contact_penalty: float = 0.05
    time_cost: float = 0.01


@dataclass(frozen=True)
class EnvConfig:
    sensor: SensorConfig = field(default_factory=SensorConfig)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    human_history_steps: int = 8  # past human positions in the observation (trajectory predictor)
    future_steps: int = 5  # ground-truth future human positions (the short-term intention)
    # Ground-truth intention observations (activity/object one-hots, future trajectory), as the
    # paper feeds them during training; agents replace them with predictions at evaluation.
    intention_obs: bool = True
    # False (the benchmark): an episode runs to t_end, the robot acting after it reached, so
    # CR_full sees what happens once it parks at the human's destination; success, SPL and AS
    # keep their first-reach definitions. True: the episode ends at the first reach (the
    # imitation and PPO training rollouts, whose data and rewards stop there).
    end_at_reach: bool = False
