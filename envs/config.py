"""Simulator configuration: physics, sensors and the RL reward, with documented defaults.

Task numbers (radius, speeds, success radius, control step) come from conav_jax.config.TaskConfig
of the dataset being simulated; nothing here repeats them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

SENSOR_KINDS = ("auto", "fast", "pallas", "reference")
PHYSICS_IMPLS = ("auto", "jax", "warp")
MATERIALS = ("instance", "flat")


def resolve_sensor_kind(kind: str) -> str:
    """The caster `kind` names; "auto" is "pallas" on a GPU (one Triton kernel; the fastest
    caster there, BENCHMARKS.md) and "fast" elsewhere: Triton needs a GPU. On a mesh of GPUs the
    kernel runs per device (conav_jax.parallel.lanes_on_devices)."""
    if kind != "auto":
        return kind
    import jax

    return "pallas" if jax.default_backend() == "gpu" else "fast"


def resolve_physics_impl(impl: str) -> str:
    """The MJX implementation `impl` names; "auto" is "warp" (MuJoCo Warp through JAX's FFI) when
    warp-lang imports and the default JAX device is a single visible CUDA GPU, else "jax". XLA's
    partitioner cannot split the FFI call over a device mesh: it gathers the whole batch onto
    every device around it (363 all-gathers in one env step on two devices), so each device
    would step every world. An explicit "warp" runs anyway, and on the CPU too (Warp compiles
    its kernels for it; the tests run it there)."""
    if impl not in PHYSICS_IMPLS:
        raise ValueError(f"physics impl must be one of {PHYSICS_IMPLS}, got {impl!r}")
    if impl == "jax":
        return impl
    has_warp = _warp_imports()
    if impl == "warp":
        if not has_warp:
            raise ImportError('physics impl "warp" needs warp-lang: pip install -e ".[warp]"')
        return impl
    return "warp" if has_warp and _single_cuda_device() else "jax"


def _warp_imports() -> bool:
    try:
        import warp  # noqa: F401
    except (ImportError, RuntimeError):  # RuntimeError: a warp-lang that cannot initialise
        return False
    return True


def _single_cuda_device() -> bool:
    import jax

    if jax.default_backend() != "gpu" or jax.device_count() != 1:
        return False
    try:
        return jax.devices()[0] in jax.devices("cuda")
    except RuntimeError:  # a GPU backend other than CUDA (ROCm): MuJoCo Warp does not run there
        return False


@dataclass(frozen=True)
class SensorConfig:
    """Panoramic RGB-D camera at the robot's camera height.

    Equirectangular: column j looks at azimuth yaw + pi - 2 pi (j + 0.5) / W (the image centre
    faces forward, the robot's left is on the image's left); rows span a vertical field of view
    of 2 pi H / W (square pixels; 90 degrees at 112x448), row 0 at the top.
    """

    resolution: tuple[int, int] = (112, 448)  # (H, W) pixels: the paper's panorama
    max_depth_m: float = 10.0  # farther hits and no hit read as max_depth and sky colour
    # "fast": our column caster, one fused min over all geoms (nothing of size geoms x H x W
    # reaches memory); "pallas": the same math as a Pallas (Triton) GPU kernel; "reference":
    # mujoco.mjx.ray per pixel; "auto": pallas on a GPU, else fast (resolve_sensor_kind).
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
    # With the Pallas caster, colour "instance" materials in a Pallas kernel as well
    # (envs.panorama_pallas.pallas_shade) rather than in XLA (same colours within float error).
    pallas_shade: bool = True
    # What RGB shows. "instance": every object instance, the walls and the floor in their own
    # material (conav_jax.data.materials: a colour from a palette shared by all categories and a
    # procedural pattern), the humanoid in per-episode clothing, all Lambertian-shaded
    # (envs.panorama.shade), so colour does not give away an object's category. "flat": each geom
    # in its category's flat colour, unshaded (RGB is then a segmentation map; the images of
    # runs trained before materials existed).
    materials: str = "instance"
    # Shading: direction towards the light (world frame, normalised when used) and the share of
    # a surface's colour it shows unlit.
    light_direction: tuple[float, float, float] = (0.35, 0.55, 0.76)
    ambient: float = 0.45

    def __post_init__(self):
        if not isinstance(self.resolution, (tuple, list)) or len(self.resolution) != 2:
            raise ValueError(f"sensor resolution is (height, width) in pixels, got {self.resolution!r}")
        # A hashable (H, W) of ints, however given (a list read from JSON, numpy ints).
        object.__setattr__(self, "resolution", (int(self.resolution[0]), int(self.resolution[1])))
        if self.materials not in MATERIALS:
            raise ValueError(f"sensor materials must be one of {MATERIALS}, got {self.materials!r}")
        if not 0.0 <= self.ambient <= 1.0:
            raise ValueError(f"sensor ambient must be in [0, 1], got {self.ambient}")
        if self.kind not in SENSOR_KINDS:
            raise ValueError(f"sensor kind must be one of {SENSOR_KINDS}, got {self.kind!r}")
        if self.fast_min not in ("reduce", "unroll"):
            raise ValueError(f"fast_min must be 'reduce' or 'unroll', got {self.fast_min!r}")
        if self.pallas_block_w < 1 or self.pallas_block_w & (self.pallas_block_w - 1):
            raise ValueError(f"pallas_block_w must be a power of two, got {self.pallas_block_w}")
        if self.height < 4 or self.width < 8 or self.width % 8:
            raise ValueError(f"panorama must be at least 4x8 with width a multiple of 8, got {self.height}x{self.width}")

    @property
    def height(self) -> int:
        """Panorama rows (pixels): resolution[0]."""
        return self.resolution[0]

    @property
    def width(self) -> int:
        """Panorama columns (pixels): resolution[1]."""
        return self.resolution[1]


def materials_of_run(config: dict) -> str:
    """The SensorConfig.materials a run's checkpoint config records (key "materials", or in
    its "data" for intention runs); "flat" for runs written before materials existed."""
    return config.get("materials", config.get("data", {}).get("materials", "flat"))


def run_materials(run_dir) -> str:
    """The SensorConfig.materials the images of the run in `run_dir` were rendered with: what
    an env that the run's agent or predictor acts in must render. FileNotFoundError for a
    directory without a checkpoint."""
    from conav_jax.checkpoints import latest_checkpoint, read_checkpoint_meta

    found = latest_checkpoint(run_dir)
    if found is None:
        raise FileNotFoundError(f"no checkpoint in run {run_dir}")
    return materials_of_run(read_checkpoint_meta(found)["config"])


def check_materials(trained: str, sensor: SensorConfig, source_name: str) -> None:
    """ValueError, naming both, unless `sensor` renders the materials `source_name` was trained on."""
    if trained != sensor.materials:
        raise ValueError(f"{source_name} was trained on materials={trained!r} images but the env renders "
                         f"materials={sensor.materials!r}; build the env with SensorConfig(materials={trained!r})")


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
    # 2/4 within 1.4 mm; with friction even 4/8 was 2.8 mm off. Fewer rows and iterations make
    # the step cheaper: `conav bench sim --physics contact_condim=3 solver_iterations=4
    # ls_iterations=8` times the frictional alternative (measured: results/bench/README.md).
    contact_condim: int = 1
    # Constraint solver budget per substep (MJX defaults to 100 / 50; three dofs need few).
    solver_iterations: int = 3
    ls_iterations: int = 4
    # Substeps unrolled per iteration of the substep scan (1: a rolled loop). Unrolling lets XLA
    # fuse across substeps, but where timed it ran no faster and compiled much longer;
    # `conav bench sim --physics substep_unroll=N` times it (results/bench/README.md).
    substep_unroll: int = 1
    # MJX implementation: "jax" (XLA), "warp" (MuJoCo Warp kernels through JAX's FFI; needs
    # warp-lang, `pip install -e ".[warp]"`), or "auto": warp where warp-lang imports and the
    # default device is a single CUDA GPU, else jax (resolve_physics_impl). Same model, servos and solver
    # budget: random drives on the tiny val episodes agree to 1 um and count the same contacts
    # (tests/test_warp_physics.py). They part where MJX's JAX collision functions differ from
    # MuJoCo's, which Warp follows: JAX finds no contact between the robot and a box's vertical
    # edge (a robot rounding a corner cuts into it, 17 mm seen) and one, not two, between
    # parallel capsules (the robot and a standing human's legs: mm-scale differences in how
    # fast they separate).
    impl: str = "auto"
    # impl="warp": MuJoCo Warp keeps ONE contact buffer for all the worlds (envs) a step serves,
    # naconmax = warp_max_worlds x the robot's worst case per world (2 contacts per robot-box slot
    # and per robot-capsule pair: 38 with 8 slots and 11 capsules; envs.mjcf.warp_data_sizes), about
    # 200 bytes per contact with its scratch (250 MB at the default). A batch up to
    # warp_max_worlds never loses a contact. A larger one loses some only when, at a substep, its
    # contacts outnumber naconmax: MuJoCo Warp then drops the ones past it (a robot may pass into
    # a wall), prints "narrowphase overflow" (or "broadphase overflow") on every such substep, and
    # flags every world of the batch, whose episodes' metrics["physics_overflow"] read 1.
    # Constraint rows (njmax) are per world, sized for the same worst case: they cannot overflow.
    warp_max_worlds: int = 32768

    def __post_init__(self):
        for name in ("timestep_s", "robot_mass_kg", "kv_linear", "kv_angular", "force_limit_n", "torque_limit_nm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"physics {name} must be positive, got {getattr(self, name)}")
        if self.contact_condim not in (1, 3):
            raise ValueError(f"physics contact_condim must be 1 or 3, got {self.contact_condim}")
        for name in ("collision_slots", "solver_iterations", "ls_iterations", "substep_unroll", "warp_max_worlds"):
            if getattr(self, name) < 1:
                raise ValueError(f"physics {name} must be at least 1, got {getattr(self, name)}")
        if self.impl not in PHYSICS_IMPLS:
            raise ValueError(f"physics impl must be one of {PHYSICS_IMPLS}, got {self.impl!r}")


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
    # Ground-truth intention observations (activity/object one-hots, future trajectory) in what
    # brax's reset/step observe, as the paper feeds them during training. An agent in a rollout
    # gets them only by declaring them (envs.observations), whatever this says.
    intention_obs: bool = True
    # False (the benchmark): an episode runs to t_end, the robot acting after it reached, so
    # CR_full sees what happens once it parks at the human's destination; success, SPL and AS
    # keep their first-reach definitions. True: the episode ends at the first reach (the
    # imitation and PPO training rollouts, whose data and rewards stop there).
    end_at_reach: bool = False


def env_settings(config: EnvConfig) -> dict:
    """What an env's config changes about a figure, for a provenance block (conav_jax.provenance):
    physics implementation, caster kind, materials and resolution [H, W], "auto" resolved here."""
    return {"physics": resolve_physics_impl(config.physics.impl), "caster": resolve_sensor_kind(config.sensor.kind),
            "materials": config.sensor.materials, "resolution": list(config.sensor.resolution)}
