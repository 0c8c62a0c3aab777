"""`conav reproduce`'s plan: the paper's Tables 2 and 3 as resumable stages of declared steps.

config -> `plan_stages` (each stage: its steps, each a Python call declared as data: the library
function of its kind and its configs, the directories it reads and writes under OUT, the
training seed it belongs to (eval.cli.reproduce_steps); and the files that show the stage is done)
-> one dependency graph (eval.cli.reproduce_progress `prerequisites`, from the declared reads and
writes) orders them, for the command line's runner in this process and for `run_parallel`'s
processes alike; progress.json records each step by its identity, its kind and the directory it
writes, so a stage cut short resumes (every training run resumes exactly from its checkpoints)
-> results and tables (eval.cli.reproduce_tables); several steps at once and the pack that carries a
run to another machine (eval.cli.reproduce_run). Planning imports the configs, not the training
code. The CoNav rows are trained offline (train.policy, recorded windows) or live (train.live,
with the ground-truth rows; `ReproduceConfig.trainer`), and evaluated on val or, to choose
budgets, on minival (`ReproduceConfig.eval_split`).
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from pathlib import Path

from conav_jax.eval.cli.reproduce_steps import Call, Stage, Step
from conav_jax.models.policy import DEFAULT_ENCODER, ENCODERS

STAGES = ("generate", "predictors", "baselines", "bc", "dagger", "eval", "tables", "pack")
ABLATIONS = ("none", "activity", "object", "activity_object", "all")  # the paper's Table 3 rows 1-5
# The ground-truth bound: Table 3 rows trained and evaluated reading the env's true intentions
# (privileged), by row name -> the ablation whose inputs they read. Trained by the live trainer.
GROUND_TRUTH_ROWS = {"gt_object": "object", "gt_all": "all"}
# How the CoNav policy is trained: "offline", from recorded windows of a subset of the train
# episodes (train.policy: BC, then DAgger rounds), or "live", from the live simulator over the
# whole train split (train.live: BC is beta = 1, DAgger a decaying beta).
TRAINERS = ("offline", "live")
EVAL_SPLITS = ("val", "minival")  # the reported split, and the one choices are made on
# ReproduceConfig fields that override the preset's budget (Budget fields of the same name): the
# intention predictor's schedule and the live trainer's.
INTENTION_OVERRIDES = ("intention_steps", "intention_batch", "intention_lr")
LIVE_OVERRIDES = ("live_lanes", "live_window_steps", "live_iterations", "live_lr")
BUDGET_OVERRIDES = INTENTION_OVERRIDES + LIVE_OVERRIDES
# Panoramas of at least this many pixels train the CoNav policy with remat: recomputing the CNN
# in the backward pass instead of keeping every window step's activations makes their update
# faster, not slower (BENCHMARKS.md, "Training updates"); smaller panoramas keep the plain
# update (their runs' configs as made).
REMAT_FROM_PIXELS = 112 * 448
# At such panoramas each DAgger round records this many of the train episodes (ImitationConfig's
# dagger_episodes),
# a subset of its own: the policy's episodes run about 480 steps (its AS on val) where the
# expert's run 152, some 17 windows of 12 MB each, so 64 hold about 13 GB a round beside BC's
# 24 GB on the GPU (the host holds them twice while they are joined); all 400 would be about
# 70 GB a round (estimates from the window size). With the expert mixed in (`dagger_beta` 0.5)
# episodes end sooner and a round records far fewer windows (results/bench/README.md), so
# `dagger_episodes` may ask for more.
LARGE_PANORAMA_DAGGER_EPISODES = 64

@dataclass(frozen=True)
class Budget:
    """Training budgets of one preset (updates, batches, rounds), chosen on minival."""

    intention_steps: int = 6000
    # The intention predictor's samples per update and peak learning rate (None:
    # train.intention.INTENTION_TRAIN's, the published runs').
    intention_batch: int | None = None
    intention_lr: float | None = None
    trajectory_steps: int = 3000
    policy_steps: int = 2000  # BC updates
    policy_batch: int = 256  # windows per update
    # Train episodes each imitation round records: their windows live on the GPU (about 125 kB a
    # step at 112x448 in uint8 RGB + float16 depth), so the paper preset records a subset.
    policy_episodes: int | None = None
    dagger_rounds: int = 2
    dagger_steps: int = 4000
    baseline_steps: int = 2000  # object-goal and image-goal BC updates
    baseline_dagger_rounds: int = 1
    # Train episodes each of their rounds records (None: all). A DAgger round's policy rarely
    # reaches its goal, so its episodes run to the end: about 18 windows each, 1 MB a window
    # at 32x128 (the paper preset's 1,000 episodes: some 18 GB a round on the device).
    baseline_episodes: int | None = None
    # Updates between validations on minival while training (None: train.policy.POLICY_TRAIN's);
    # the paper preset's minival is 1,000 episodes, so it validates less often.
    val_every: int | None = None
    eval_batch: int = 2048  # evaluation lanes
    # The CoNav policy's CNN dtype (PolicyConfig.conv_dtype): bfloat16 halves the CNN's memory
    # traffic and runs it on tensor cores, which speeds up the large panoramas' update
    # (BENCHMARKS.md, "Training updates"); float32 keeps the small runs' configs.
    policy_conv_dtype: str = "float32"
    # The live trainer (train.live.LiveConfig): lanes, window steps and updates of every CoNav run,
    # its peak learning rate and warm-up; its DAgger row's beta falls linearly from 1 to the
    # run's `dagger_beta` over the first `live_dagger_decay` of the updates.
    live_lanes: int = 256
    live_window_steps: int = 16
    live_iterations: int = 2000
    live_lr: float = 1e-3
    live_warmup_iterations: int = 100
    live_dagger_decay: float = 0.5


BUDGETS = {
    # Tiny: a smoke test of the pipeline on CPU; 100 updates is the least the default 100-step
    # learning-rate warm-up allows.
    "tiny": Budget(intention_steps=100, trajectory_steps=100, policy_steps=100, policy_batch=8, dagger_rounds=1,
                   dagger_steps=50, baseline_steps=100, baseline_dagger_rounds=0, eval_batch=64,
                   live_lanes=8, live_window_steps=8, live_iterations=4, live_warmup_iterations=0),
    "small": Budget(policy_episodes=500, eval_batch=512, live_lanes=1024, live_iterations=600,
                    live_warmup_iterations=30),
    # Live: 2,048 lanes of 16 steps, 500 updates (16.4M env timesteps), chosen on minival over
    # 8,192 x 4 at 16.4M and at 50M timesteps (results/paper_112x448_live_budget/README.md).
    "paper": Budget(policy_episodes=400, policy_conv_dtype="bfloat16", baseline_episodes=1000, val_every=1000,
                    live_lanes=2048, live_window_steps=16, live_iterations=500, live_warmup_iterations=50),
}


@dataclass(frozen=True)
class ReproduceConfig:
    """One `conav reproduce` run."""

    out: Path  # data, runs, evaluations, results and tables
    preset: str = "paper"  # the dataset preset and its training budgets (BUDGETS)
    seeds: int = 3  # training seeds of every learned CoNav row
    # Training seeds of each learned baseline (the object-goal and image-goal agents). Seed 0's
    # runs and evaluations keep the unseeded names (`baseline_name`) of OUT directories made with
    # one seed, so those continue as they are.
    baseline_seeds: int = 3
    resolution: tuple[int, int] = (112, 448)  # the panorama every agent reads (the paper's)
    data_seed: int = 0
    workers: int = 2  # dataset generation processes
    # The expert's share in the DAgger rounds (ImitationConfig.dagger_beta: it acts at a step of
    # round r with probability dagger_beta**r); 0: the policy alone (runs/dagger_s*). Any other
    # value trains and evaluates runs of its own name beside them (runs/dagger_betaP_s*), and the
    # tables show every DAgger variant evaluated.
    dagger_beta: float = 0.0
    # DAgger rounds after BC (ImitationConfig.dagger_rounds); None: the preset's budget. Other
    # counts, like other shares, train and evaluate runs of their own name.
    dagger_rounds: int | None = None
    # Train episodes each DAgger round records (ImitationConfig.dagger_episodes); None: the
    # resolution's default (LARGE_PANORAMA_DAGGER_EPISODES at >= 112x448, else all the policy's).
    # Another count, like other shares and rounds, trains and evaluates runs of its own name.
    dagger_episodes: int | None = None
    # The CoNav policy's panorama encoder (models.policy.ENCODERS) in every BC and DAgger run:
    # the default's configs are those of the runs in results/; patch trains faster at large
    # panoramas (BENCHMARKS.md). One OUT directory holds one encoder, as it holds one resolution.
    encoder: str = DEFAULT_ENCODER
    # The intention predictor's training and inference options (off: the configs of the runs in
    # results/). Frames mirrored half the time (IntentionDataConfig.mirror):
    mirror: bool = False
    # The intention predictor trains on frames whose colours are redrawn for every sample and
    # update (IntentionDataConfig.recolour).
    recolour: bool = False
    # The intention predictor weighs activities by whether the robot's panoramas have shown their
    # object (PerceiverConfig.seen_objects: oracle segmentation, listed as privileged).
    seen_objects: bool = False
    # How the CoNav rows are trained (TRAINERS): "offline" (train.policy: recorded windows of a
    # subset of the train episodes, BC then DAgger rounds) or "live" (train.live: the live
    # simulator over every train episode; adds the ground-truth rows, GROUND_TRUTH_ROWS, to Table
    # 3, and its DAgger row starts from scratch, beta falling from 1 to dagger_beta). One OUT
    # directory holds one trainer.
    trainer: str = "offline"
    # The Table 3 rows to train and evaluate (empty: every one the trainer has, `all_rows`); the
    # tables list the others as not run. DAgger's runs are the dagger stage's, whatever the rows.
    rows: tuple[str, ...] = ()
    # The learned baselines to train and evaluate, by run kind (objectnav, imagenav; empty: both);
    # the tables list the others as not run.
    baselines: tuple[str, ...] = ()
    # The intention predictor's schedule and the live trainer's budget where they are not the
    # preset's (None: Budget.intention_*, Budget.live_*): one OUT directory holds one budget, so
    # budgets compared on minival are OUT directories of their own.
    intention_steps: int | None = None  # the intention predictor's updates
    intention_batch: int | None = None  # the intention predictor's samples per update
    intention_lr: float | None = None  # the intention predictor's peak learning rate
    live_lanes: int | None = None  # the live trainer's lanes
    live_window_steps: int | None = None  # the live trainer's control steps per window
    live_iterations: int | None = None  # the live trainer's updates
    live_lr: float | None = None  # the live trainer's peak learning rate
    # The split every evaluation runs on: "val", the reported numbers, or "minival", where
    # budgets and variants are chosen (its evaluations, results and tables are files of their
    # own: `eval_dir`, `results_file`, `tables_file`; the runs are shared).
    eval_split: str = "val"

    def __post_init__(self):
        for name in BUDGET_OVERRIDES:
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise ValueError(f"ReproduceConfig.{name} must be positive, got {value}")
        if self.eval_split not in EVAL_SPLITS:
            raise ValueError(f"ReproduceConfig.eval_split must be one of {', '.join(EVAL_SPLITS)}, got {self.eval_split!r}")
        if self.trainer not in TRAINERS:
            raise ValueError(f"unknown ReproduceConfig.trainer {self.trainer!r}; choose from {', '.join(TRAINERS)}")
        unknown = [r for r in self.rows if r not in self.all_rows]
        if unknown or len(set(self.rows)) != len(self.rows):
            raise ValueError(f"ReproduceConfig.rows {','.join(self.rows)}: each once, from {', '.join(self.all_rows)} "
                             f"(the {self.trainer} trainer's Table 3 rows; DAgger's runs are not a row: the dagger "
                             "stage trains them whatever the rows)")
        unknown = [k for k in self.baselines if k not in BASELINE_KINDS]
        if unknown or len(set(self.baselines)) != len(self.baselines):
            raise ValueError(f"ReproduceConfig.baselines {','.join(self.baselines)}: each once, from "
                             f"{', '.join(BASELINE_KINDS)}")
        if self.preset not in BUDGETS:
            raise ValueError(f"unknown preset {self.preset!r}; choose from {', '.join(BUDGETS)}")
        if self.seeds < 1:
            raise ValueError(f"ReproduceConfig.seeds must be at least 1, got {self.seeds}")
        if self.baseline_seeds < 1:
            raise ValueError(f"ReproduceConfig.baseline_seeds must be at least 1, got {self.baseline_seeds}")
        if not 0.0 <= self.dagger_beta <= 1.0:
            raise ValueError(f"ReproduceConfig.dagger_beta is a probability in [0, 1], got {self.dagger_beta}")
        if self.dagger_rounds is not None and self.dagger_rounds < 1:
            raise ValueError(f"ReproduceConfig.dagger_rounds must be at least 1, got {self.dagger_rounds}")
        if self.dagger_episodes is not None and self.dagger_episodes < 1:
            raise ValueError(f"ReproduceConfig.dagger_episodes must be at least 1, got {self.dagger_episodes}")
        if self.encoder not in ENCODERS:
            raise ValueError(f"unknown ReproduceConfig.encoder {self.encoder!r}; choose from {', '.join(sorted(ENCODERS))}")

    @property
    def budget(self) -> Budget:
        """The preset's budget with this run's overrides (BUDGET_OVERRIDES)."""
        given = {k: getattr(self, k) for k in BUDGET_OVERRIDES if getattr(self, k) is not None}
        return dataclasses.replace(BUDGETS[self.preset], **given)

    @property
    def rounds(self) -> int:
        """The DAgger rounds this run trains."""
        return self.budget.dagger_rounds if self.dagger_rounds is None else self.dagger_rounds

    @property
    def large(self) -> bool:
        """Panoramas that train the policy with remat and record DAgger rounds on a subset."""
        return self.resolution[0] * self.resolution[1] >= REMAT_FROM_PIXELS

    @property
    def default_dagger_episodes(self) -> int | None:
        """The train episodes a DAgger round records unless `dagger_episodes` says (None: all)."""
        return LARGE_PANORAMA_DAGGER_EPISODES if self.large else None

    @property
    def round_episodes(self) -> int | None:
        """The train episodes each of this run's DAgger rounds records (None: all the policy's)."""
        return self.default_dagger_episodes if self.dagger_episodes is None else self.dagger_episodes

    @property
    def eval_dir(self) -> str:
        """OUT's directory of this run's evaluations: "eval" on val, "eval_minival" on minival."""
        return "eval" if self.eval_split == "val" else f"eval_{self.eval_split}"

    @property
    def results_file(self) -> str:
        return "results.json" if self.eval_split == "val" else f"results_{self.eval_split}.json"

    @property
    def tables_file(self) -> str:
        return "tables.md" if self.eval_split == "val" else f"tables_{self.eval_split}.md"

    @property
    def all_rows(self) -> tuple[str, ...]:
        """The trainer's Table 3 rows: the five ablations, and with the live trainer the
        ground-truth rows."""
        return ABLATIONS + (tuple(GROUND_TRUTH_ROWS) if self.trainer == "live" else ())

    @property
    def table3_rows(self) -> tuple[str, ...]:
        """The Table 3 rows this run trains (`rows`, in `all_rows` order; empty: all)."""
        return tuple(r for r in self.all_rows if not self.rows or r in self.rows)

    @property
    def dagger(self) -> str:
        """This run's DAgger row (`dagger_row`): the budget's round count and the resolution's
        episode count name neither; the live trainer's is `live_dagger_row`."""
        if self.trainer == "live":
            return live_dagger_row(self.dagger_beta)
        return dagger_row(self.dagger_beta, None if self.rounds == self.budget.dagger_rounds else self.rounds,
                          None if self.round_episodes == self.default_dagger_episodes else self.round_episodes)


def dagger_row(beta: float, rounds: int | None = None, episodes: int | None = None) -> str:
    """The DAgger row's name for the expert's share `beta` ("dagger" for the policy alone), a
    round count other than the preset's (`rounds`; None: the preset's) and train episodes a round
    other than the resolution's default (`episodes`; None: the default): its runs are
    runs/NAME_s{seed}, their evaluations eval/conav_NAME_s{seed}."""
    return (("dagger" if beta == 0.0 else f"dagger_beta{beta:g}") + ("" if rounds is None else f"_rounds{rounds}")
            + ("" if episodes is None else f"_episodes{episodes}"))


def live_dagger_row(beta_end: float) -> str:
    """The live trainer's DAgger row: beta falls from 1 to `beta_end` (Budget.live_dagger_decay)."""
    return f"dagger_live_beta{beta_end:g}"


def live_dagger_variant(row: str) -> float | None:
    """The final beta of a DAgger row named by `live_dagger_row`; None for any other name."""
    m = re.fullmatch(r"dagger_live_beta([0-9.e+-]+)", row)
    try:
        return None if m is None else float(m.group(1))
    except ValueError:
        return None


def dagger_variant(row: str) -> tuple[float, int | None, int | None] | None:
    """(the expert's share, the round count or None, the episodes a round or None) of a DAgger
    row named by `dagger_row`; None for any other name."""
    m = _DAGGER_ROW.fullmatch(row)
    try:
        return None if m is None else (float(m.group(1) or 0.0), *(None if g is None else int(g) for g in m.groups()[1:]))
    except ValueError:  # not a number after "_beta"
        return None


# The shares `:g` writes, then the round and episode counts.
_DAGGER_ROW = re.compile(r"dagger(?:_beta([0-9.e+-]+))?(?:_rounds([0-9]+))?(?:_episodes([0-9]+))?")


def baseline_name(name: str, seed: int) -> str:
    """A learned baseline's run (runs/NAME) or evaluation (eval/NAME) for training seed `seed`:
    NAME for seed 0, as OUT directories with one seed name it, else NAME_s{seed}."""
    return name if seed == 0 else f"{name}_s{seed}"


# The learned baselines' evaluations (Table 2's rows) and the run each reads, with the predictor
# the predicted-goal agent adds.
LEARNED_BASELINES = {"objectgoal-oracle": "objectnav", "objectgoal-predicted": "objectnav", "imagegoal": "imagenav"}
BASELINE_KINDS = ("objectnav", "imagenav")


def resolution_name(cfg: ReproduceConfig) -> str:
    """The run's panorama as the command line writes it: "112x448"."""
    return "x".join(map(str, cfg.resolution))


def plan_stages(cfg: ReproduceConfig) -> list[Stage]:
    """Every stage of the pipeline for `cfg`, in order."""
    from conav_jax.data.presets import preset
    from conav_jax.envs.human_crop import default_crop_hw
    from conav_jax.models.perceiver import PerceiverConfig
    from conav_jax.models.trajectory import TrajectoryConfig
    from conav_jax.train.goalnav import imagenav_model, objectnav_model
    from conav_jax.train.intention import INTENTION_TRAIN, IntentionDataConfig
    from conav_jax.train.policy import POLICY_TRAIN, ImitationConfig
    from conav_jax.train.trajectory import TRAJECTORY_TRAIN

    b, out, res = cfg.budget, Path(cfg.out), tuple(cfg.resolution)
    data, runs, evals = out / "data", out / "runs", out / cfg.eval_dir
    intention, trajectory = runs / "intention", runs / "trajectory"

    def step(kind: str, writes: Path, reads: tuple[Path, ...] = (data,), seed: int | None = None, **kwargs) -> Step:
        return Step(Call(kind, kwargs), str(writes.relative_to(out)), tuple(str(r.relative_to(out)) for r in reads), seed)

    # The imitation runs' rounds: the preset's validation cadence where it has one.
    rounds = dataclasses.replace(POLICY_TRAIN, **({"val_every": b.val_every} if b.val_every else {}))
    schedule = {k: v for k, v in (("batch", b.intention_batch), ("lr", b.intention_lr)) if v is not None}
    stages = [
        Stage("generate", (step("generate", data, reads=(), cfg=preset(cfg.preset, cfg.data_seed), out_dir=str(data),
                                workers=cfg.workers),), (data / "manifest.json",)),
        Stage("predictors", (
            step("train intention", intention, data_dir=str(data), run_dir=str(intention),
                 cfg=dataclasses.replace(INTENTION_TRAIN, steps=b.intention_steps, **schedule),
                 # crops of the panorama the agents render (envs.human_crop)
                 model=PerceiverConfig(image_hw=default_crop_hw(res), seen_objects=cfg.seen_objects),
                 data=IntentionDataConfig(resolution=res, mirror=cfg.mirror, recolour=cfg.recolour),
                 progress=False),
            step("train trajectory", trajectory, data_dir=str(data), run_dir=str(trajectory),
                 cfg=dataclasses.replace(TRAJECTORY_TRAIN, steps=b.trajectory_steps), model=TrajectoryConfig(),
                 progress=False),
        ), (intention / "ckpt_{:08d}.npz".format(b.intention_steps),
            trajectory / "ckpt_{:08d}.npz".format(b.trajectory_steps))),
    ]
    # The learned baselines share the policy's encoder. At large panoramas they also record as
    # many train episodes as the policy (the preset's 1,000 would be some 50 GB of BC windows on
    # the GPU, an estimate), with its dtype, remat and the default DAgger subsets (reproduce's
    # `dagger_episodes` changes the CoNav DAgger rows' alone); smaller panoramas keep the
    # configs their runs were made with.
    net = _network(cfg, b.policy_conv_dtype if cfg.large else "float32")
    imitation = ImitationConfig(dagger_rounds=b.baseline_dagger_rounds, dagger_episodes=cfg.default_dagger_episodes,
                                episodes=b.policy_episodes if cfg.large and b.policy_episodes else b.baseline_episodes)
    kinds = tuple((kind, model) for kind, model in (("objectnav", objectnav_model(res, base=net)),
                                                     ("imagenav", imagenav_model(res, net)))
                  if not cfg.baselines or kind in cfg.baselines)
    baseline_runs = [(s, kind, runs / baseline_name(kind, s)) for s in range(cfg.baseline_seeds) for kind, _ in kinds]

    def baseline(s: int, kind: str, run: Path) -> Step:
        if cfg.trainer == "live" and kind == "objectnav":
            # The object-goal agent trains live as the CoNav rows do, at their budget and seed.
            model = objectnav_model(res, base=_live_network(cfg))
            return step("train objectnav live", run, seed=s, data_dir=str(data), out_dir=str(run), model=model,
                        live=dataclasses.replace(_live_config(cfg), seed=s), progress=False)
        return step(f"train {kind}", run, seed=s, data_dir=str(data), run_dir=str(run),
                    cfg=dataclasses.replace(rounds, steps=b.baseline_steps, seed=s), model=dict(kinds)[kind],
                    imitation=imitation, remat=cfg.large, progress=False)

    stages.append(Stage("baselines", tuple(baseline(*r) for r in baseline_runs),
                        tuple(run / "log.jsonl" for _, _, run in baseline_runs)))
    predictors = (data, intention, trajectory)

    def evaluation(agents: str, target: Path, run: Path | None = None, seed: int | None = None,
                   reads: tuple[Path, ...] = (), ground_truth: bool = False) -> Step:
        intentions = {"ground_truth": True} if ground_truth else {"intention_run": str(intention)} if intention in reads else {}
        return step("eval", target, (data, *((run,) if run is not None else ()), *reads), seed, data=str(data),
                    split=cfg.eval_split, agents=tuple(agents.split(",")), out=str(target),
                    checkpoint=None if run is None else str(run), intention_kwargs=intentions, batch=b.eval_batch,
                    resolution=res, progress=True)

    if cfg.trainer == "live":
        stages += _live_stages(cfg, step, evaluation, predictors)
    else:
        stages += _offline_stages(cfg, step, evaluation, dataclasses.replace(rounds, steps=b.policy_steps,
                                                                              batch=b.policy_batch), predictors)
    baseline_evals = [(baseline_name(agent, s), agent, runs / baseline_name(kind, s), s)
                      for s in range(cfg.baseline_seeds) for agent, kind in LEARNED_BASELINES.items()
                      if kind in dict(kinds)]
    evals_ = [evaluation("random,follower,pioneer,pioneer-drive,objectgoal-planner,expert", evals / "scripted")] + [
        evaluation(agent, evals / target, run, s, reads=(intention,) if agent == "objectgoal-predicted" else ())
        for target, agent, run, s in baseline_evals]
    name = cfg.dagger
    dagger_eval = CONAV_EVAL.format(row=name, seed="{}")
    evals_ += [evaluation("conav", evals / dagger_eval.format(s), runs / f"{name}_s{s}", s) for s in range(cfg.seeds)]
    names = ["scripted"] + [target for target, *_ in baseline_evals] + [dagger_eval.format(s) for s in range(cfg.seeds)]
    stages.append(Stage("eval", tuple(evals_), tuple(evals / n / "metrics.json" for n in names)))
    stages.append(Stage("tables", (), (out / cfg.results_file, out / cfg.tables_file)))
    stages.append(Stage("pack", (), (out / "pack.tar",)))
    return stages


def _network(cfg: ReproduceConfig, conv_dtype: str, visual_norm: bool | None = None):
    """The CoNav policy's network at the run's panorama: `cfg.encoder`, convolutions in
    `conv_dtype`, `visual_norm` (None: PolicyConfig's)."""
    from conav_jax.models.policy import PolicyConfig, encoder_config

    norm = PolicyConfig.visual_norm if visual_norm is None else visual_norm
    return encoder_config(PolicyConfig(resolution=tuple(cfg.resolution), conv_dtype=conv_dtype, visual_norm=norm),
                          cfg.encoder)


def _offline_stages(cfg: ReproduceConfig, step, evaluation, schedule, predictors) -> list[Stage]:
    """The bc and dagger stages of the offline trainer (train.policy); `schedule`: BC's
    TrainConfig, `predictors`: the data and predictor runs."""
    from conav_jax.models.policy import ablation_config
    from conav_jax.train.policy import ImitationConfig

    b, runs, evals = cfg.budget, Path(cfg.out) / "runs", Path(cfg.out) / cfg.eval_dir
    data, intention, trajectory = predictors
    net = _network(cfg, b.policy_conv_dtype)
    imitation = ImitationConfig(train_intentions="predicted", episodes=b.policy_episodes)
    policy = dict(data_dir=str(data), intention_run=str(intention), trajectory_run=str(trajectory), remat=cfg.large,
                  progress=False)
    # Each BC run, then its evaluation on val: an evaluated run needs no checkpoint to travel in a
    # pack (at 112x448 a policy's is 15 MB, the pack's limit four of them) but the one DAgger continues.
    bc = []
    for s in range(cfg.seeds):
        for a in cfg.table3_rows:
            run = runs / f"bc_{a}_s{s}"
            bc.append(step("train policy", run, predictors, s, **policy, run_dir=str(run),
                           cfg=dataclasses.replace(schedule, seed=s), model=ablation_config(net, a), imitation=imitation))
            bc.append(evaluation("conav", evals / BC_ROW_EVAL.format(row=a, seed=s), run, s))
    dagger, name = [], cfg.dagger
    rounds = dataclasses.replace(imitation, dagger_rounds=cfg.rounds, dagger_steps=b.dagger_steps,
                                 dagger_beta=cfg.dagger_beta, dagger_episodes=cfg.round_episodes)
    for s in range(cfg.seeds):  # DAgger continues a copy of the seed's BC run (all inputs)
        run, start = runs / f"{name}_s{s}", runs / f"bc_all_s{s}"
        dagger.append(step("copy", run, (start,), s, source=str(start), target=str(run)))
        dagger.append(step("train policy", run, predictors, s, **policy, run_dir=str(run),
                           cfg=dataclasses.replace(schedule, seed=s), model=ablation_config(net, "all"),
                           imitation=rounds))
    return [Stage("bc", tuple(bc), tuple(evals / BC_ROW_EVAL.format(row=a, seed=s) / "metrics.json"
                                         for s in range(cfg.seeds) for a in cfg.table3_rows)),
            Stage("dagger", tuple(dagger), tuple(runs / f"{name}_s{s}" / "log.jsonl" for s in range(cfg.seeds)))]


def _live_network(cfg: ReproduceConfig):
    """The network live runs train (the CoNav rows' before their ablation, the object-goal
    baseline's before its inputs): the preset's dtype, train.live's visual norm."""
    from conav_jax.train.live import DEFAULT_POLICY

    return _network(cfg, cfg.budget.policy_conv_dtype, visual_norm=DEFAULT_POLICY.visual_norm)


def _live_config(cfg: ReproduceConfig):
    """The preset's live budget (seed 0)."""
    from conav_jax.train.live import LiveConfig

    b = cfg.budget
    # No remat: the live window holds the panoramas as the CNN reads them, so the update widens
    # nothing, its activations fit, and recomputing the CNN only costs time (BENCHMARKS.md).
    return LiveConfig(lanes=b.live_lanes, window_steps=b.live_window_steps, iterations=b.live_iterations, lr=b.live_lr,
                      warmup_iterations=b.live_warmup_iterations, remat=False)


def _live_stages(cfg: ReproduceConfig, step, evaluation, predictors: tuple[Path, Path, Path]) -> list[Stage]:
    """The bc and dagger stages of the live trainer (train.live): every Table 3 row, the
    ground-truth rows among them, then its evaluation (on `cfg.eval_split`), seed by seed; the
    DAgger row trains from scratch beside them (seed s of every row shares its episode order and
    initial weights: train.live). `predictors`: the data and predictor runs."""
    from conav_jax.envs.agents.policy import needed_predictors
    from conav_jax.models.policy import ablation_config

    b = cfg.budget
    data, intention, trajectory = predictors
    runs, evals = Path(cfg.out) / "runs", Path(cfg.out) / cfg.eval_dir
    net, live = _live_network(cfg), _live_config(cfg)
    predicted = {"intention_run": str(intention), "trajectory_run": str(trajectory)}
    bc, outputs = [], []
    for s in range(cfg.seeds):
        for row in cfg.table3_rows:
            gt = row in GROUND_TRUTH_ROWS
            config = ablation_config(net, GROUND_TRUTH_ROWS.get(row, row))
            # A row that reads no intention (none) neither reads nor waits for the predictors.
            reads_predictors = not gt and bool(needed_predictors(config))
            run, target = runs / f"bc_{row}_s{s}", evals / BC_ROW_EVAL.format(row=row, seed=s)
            bc.append(step("train live", run, predictors if reads_predictors else (data,), s, data_dir=str(data),
                           out_dir=str(run), policy_config=config, live=dataclasses.replace(live, seed=s),
                           **(predicted if reads_predictors else {}), progress=False))
            bc.append(evaluation("conav", target, run, s, ground_truth=gt))
            outputs.append(target / "metrics.json")
    name, dagger = cfg.dagger, []
    decay = max(1, round(b.live_dagger_decay * b.live_iterations))
    for s in range(cfg.seeds):
        run = runs / f"{name}_s{s}"
        dagger.append(step("train live", run, predictors, s, data_dir=str(data), out_dir=str(run),
                           policy_config=ablation_config(net, "all"), **predicted, progress=False,
                           live=dataclasses.replace(live, seed=s, beta_start=1.0, beta_end=cfg.dagger_beta,
                                                    beta_decay_iterations=decay)))
    return [Stage("bc", tuple(bc), tuple(outputs)),
            Stage("dagger", tuple(dagger), tuple(runs / f"{name}_s{s}" / "log.jsonl" for s in range(cfg.seeds)))]


# A seed's evaluations under OUT/eval: each BC run (Table 3's rows), a DAgger row's run. Runs made
# before the BC runs were evaluated one by one hold a seed's five in one evaluation, its ablations.
CONAV_EVAL = "conav_{row}_s{seed}"
BC_ROW_EVAL = CONAV_EVAL.format(row="bc_{row}", seed="{seed}")
BC_EVAL, DAGGER_EVAL = (CONAV_EVAL.format(row=row, seed="{}") for row in ("bc", "dagger"))
