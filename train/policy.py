"""`conav train policy`'s stage: the CoNav LSTM policy imitates the expert (BC, then DAgger rounds).

`train_policy` takes the train env and the validation env (`train_policy_from_data` builds them
from a dataset directory: `imitation_envs`). Round 0 records the expert on the train split; each
DAgger round rolls out the current policy (the expert mixed in at `ImitationConfig.dagger_beta`),
the expert labels the states it visits, and the aggregated windows (RUN/data/round_R.npz) train
it further. Every round trains on train.loop in RUN/round_R/ (its own log.jsonl and
checkpoints: it resumes exactly), with a fresh Adam and its own warm-up + cosine schedule,
warm-started from the previous round's weights; validation runs the policy in the simulator on
the minival split (hyper-parameters are chosen there, never on the reported val split).
RUN/log.jsonl holds the expert's validation metrics (the ceiling) and the recordings;
RUN/ckpt_<step>.npz the policy at the end of each round (read by envs.agents.policy and
train.ppo's init_from). The expert's ceiling and round-0 recording depend on neither the seed
nor the weights: runs that agree on what they do depend on share them through the dataset's
`expert_cache/` (`expert_cache_entries`; Table 3's rows and seeds and a DAgger run continuing its
BC run record once: `round0_configs`). With a device mesh (conav_jax.parallel) every update's windows and
every simulator batch are split over the devices, parameters replicated. The same rounds train
the goal-navigation baselines (train/goalnav.py): an `ImitationTask` names their teacher, their
goal sensor and their run's kind in place of the CoNav expert.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, NamedTuple

import jax
import numpy as np

from conav_jax import runs
from conav_jax.checkpoints import (checkpoint_path, latest_checkpoint, load_checkpoint, read_checkpoint_meta,
                                  save_checkpoint)
from conav_jax.data.arrayio import save_json, sha256_file
from conav_jax.data.episodes import read_manifest
from conav_jax.models import policy
from conav_jax.models.policy import config_dict, encoder_name
from conav_jax.provenance import PROVENANCE_KEY, provenance
from conav_jax.nav.expert import ExpertConfig
from conav_jax.parallel import check_divisible
from conav_jax.runs import append_log
from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.config import materials_of_run
from conav_jax.envs.agents.base import NO_INTENTIONS
from conav_jax.envs.agents.policy import intention_source, load_predictors, needed_predictors
from conav_jax.envs.metrics import summarize
from conav_jax.envs.rollout import jit_with_bank
from conav_jax.train import imitation as im
from conav_jax.train import loop
from conav_jax.train.env_checks import check_ends_at_reach, check_same_data, check_sensor, check_split
from conav_jax.train.loop import TrainConfig

KIND = runs.POLICY
# Each imitation round's schedule unless a run gives its own (`conav train policy|objectnav|imagenav`'s
# defaults): BC's updates, windows per update, validations on minival.
POLICY_TRAIN = TrainConfig(steps=2000, batch=16, lr=3e-4, warmup_steps=100, val_every=1000, ckpt_every=500)
# ImitationConfig fields a resumed run may change: more DAgger rounds continue a finished run;
# batching and the validation subset do not change the weights.
RESUME_FREE = ("dagger_rounds", "rollout_batch", "val_batch", "val_episodes")
# Device memory one recording call's records may take (RECORD_BUDGET_BYTES on an accelerator;
# on the CPU they share the host's memory with every recorded episode, so less) and the most
# lanes a call runs: a call steps its lanes together, so a few large calls beat many small ones.
RECORD_BUDGET_BYTES = 16 * 2**30
RECORD_BUDGET_BYTES_CPU = 2 * 2**30
MAX_ROLLOUT_LANES = 1024
# Recorded in the run's config, yet a resumed run may change them: the length of DAgger rounds
# to come (a round already begun takes it as its new length; its schedule stretches) and the
# expert's share in the rounds not yet recorded (a BC run continues with DAgger of either kind).
RESUME_CHANGEABLE = ("imitation.dagger_steps", "imitation.dagger_beta", "imitation.dagger_episodes")
# Where a run's predictor runs lay (its config names them: the CoNav agent and train.ppo find them
# there). A run resumed in another directory (a pack unpacked elsewhere) finds them elsewhere:
# their content must match ("predictor_digests"), not their paths.
PREDICTOR_PATHS = ("intention_run", "trajectory_run")
# ImitationConfig fields added after runs were written: a run's config stores them only where set.
LATER_IMITATION_FIELDS = ("dagger_episodes",)
TRAIN_INTENTIONS = ("ground_truth", "predicted")
# The dataset's subdirectory where runs share the expert's ceiling and round-0 recordings, and
# the layout of its entries (a change to what a recording holds bumps it: older entries unread).
EXPERT_CACHE_DIR = "expert_cache"
EXPERT_CACHE_VERSION = 2  # 2: one round-0 entry for every ablation (`round0_configs`)
# Each round draws its own minibatches: round r trains with TrainConfig.seed + ROUND_SEED_STRIDE * r.
ROUND_SEED_STRIDE = 7919


@dataclass(frozen=True)
class ImitationConfig:
    """Which data the policy learns from and where it is validated (TrainConfig: each round's
    updates; the network, its resolution and ablation: conav_jax.models.policy.PolicyConfig)."""

    episodes: int | None = None  # train-split episodes recorded (None: all)
    val_episodes: int | None = None  # validation episodes (None: all of the split)
    val_split: str = "minival"  # validated on while training; the reported val split stays unseen
    dagger_rounds: int = 0  # rounds after behaviour cloning
    dagger_steps: int | None = None  # updates per DAgger round (None: TrainConfig.steps)
    # DAgger round r >= 1 records a mixture: at each step the expert acts with probability
    # dagger_beta ** r, else the policy (Ross et al. 2011's beta_i = p ** (i - 1), round 0 being
    # the expert's); 0: the policy alone.
    dagger_beta: float = 0.0
    # Train episodes each DAgger round records: a different random subset of `episodes` each
    # round (None: all of them). The policy's own episodes run about three times the expert's,
    # and every recorded window stays on the GPU while the run trains (12 MB each at 112x448).
    dagger_episodes: int | None = None
    seq_len: int = 32  # steps per training window in the loss (truncated BPTT)
    burn_in: int = 16  # steps before each window that only warm up the LSTM
    # Episodes per recording call (None: as many as RECORD_BUDGET_BYTES of records hold, see
    # `recording_lanes`) and per validation call (validation keeps no observations).
    rollout_batch: int | None = None
    val_batch: int = MAX_ROLLOUT_LANES
    # Intention inputs in the training data: "ground_truth" (the paper, sec. 4.2) or "predicted"
    # (the predictor runs' outputs, recorded along every rollout: what the policy reads at
    # evaluation, so it learns how far to trust them).
    train_intentions: str = "ground_truth"

    def __post_init__(self):
        if self.train_intentions not in TRAIN_INTENTIONS:
            raise ValueError(f"unknown train_intentions {self.train_intentions!r}; expected one of {TRAIN_INTENTIONS}")
        if self.dagger_rounds < 0 or self.seq_len < 1 or self.burn_in < 0 or self.val_batch < 1:
            raise ValueError("need dagger_rounds >= 0, seq_len >= 1, burn_in >= 0, val_batch >= 1")
        if not 0.0 <= self.dagger_beta <= 1.0:
            raise ValueError(f"ImitationConfig.dagger_beta is a probability in [0, 1], got {self.dagger_beta}")
        for name in ("episodes", "val_episodes", "dagger_steps", "dagger_episodes", "rollout_batch"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ValueError(f"ImitationConfig.{name} must be >= 1 (or None), got {getattr(self, name)}")


def round_episodes(train_episodes: np.ndarray, r: int, imitation: ImitationConfig, seed: int) -> np.ndarray:
    """The train episodes round `r` records, in order: every one in round 0 and, without
    `imitation.dagger_episodes`, in every round; else a DAgger round's own random subset of that
    many, drawn from (seed, round) alone (a resumed run records the same)."""
    n = imitation.dagger_episodes
    if r == 0 or n is None or n >= len(train_episodes):
        return train_episodes
    return np.sort(np.random.default_rng([seed, r]).choice(train_episodes, n, replace=False))


def imitation_record(imitation: ImitationConfig) -> dict:
    """What a run's config stores of `imitation`: what its training depends on (not RESUME_FREE's
    fields), LATER_IMITATION_FIELDS only where set, so runs written before them still resume."""
    return {k: v for k, v in dataclasses.asdict(imitation).items()
            if k not in RESUME_FREE and not (k in LATER_IMITATION_FIELDS and v is None)}


def round_actor(r: int, imitation: ImitationConfig, teacher_name: str) -> tuple[str, float]:
    """Who acts while round `r` is recorded, and the probability the teacher acts at a step:
    round 0 the teacher (behaviour cloning); DAgger round r the policy, with the teacher mixed in
    at `imitation.dagger_beta ** r`."""
    if r == 0:
        return teacher_name, 1.0
    beta = imitation.dagger_beta ** r
    return ("policy" if beta == 0.0 else f"policy, {teacher_name} at beta {beta:g}"), beta


def recording_lanes(chunk_steps: int, seq_len: int, burn_in: int, resolution: tuple[int, int], goal_image: bool = False,
                    budget_bytes: int | None = None) -> int:
    """Episodes one recording call runs (train.imitation.record_windows): what a lane holds on
    the device at once, a chunk of `chunk_steps` records, the burn-in kept for the next chunk,
    the chunk's windows and the copy of those kept (each step the compact panorama, and a goal
    image where the policy reads one), within `budget_bytes` (default: RECORD_BUDGET_BYTES, on
    the CPU RECORD_BUDGET_BYTES_CPU), at least 1, at most MAX_ROLLOUT_LANES."""
    h, w = resolution
    step_bytes = h * w * (im.PANORAMA_BYTES_PER_PIXEL + (im.GOAL_IMAGE_BYTES_PER_PIXEL if goal_image else 0))
    window_steps = chunk_steps // seq_len * (burn_in + seq_len)
    return lanes_within((chunk_steps + burn_in + 2 * window_steps) * step_bytes, budget_bytes)


def lanes_within(lane_bytes: int, budget_bytes: int | None = None) -> int:
    """Lanes of `lane_bytes` each that `budget_bytes` (default: RECORD_BUDGET_BYTES, on the CPU
    RECORD_BUDGET_BYTES_CPU) holds, at least 1, at most MAX_ROLLOUT_LANES."""
    if budget_bytes is None:
        budget_bytes = RECORD_BUDGET_BYTES_CPU if jax.default_backend() == "cpu" else RECORD_BUDGET_BYTES
    return int(np.clip(budget_bytes // lane_bytes, 1, MAX_ROLLOUT_LANES))


class ImitationTask(NamedTuple):
    """What a run imitates in place of the CoNav expert: the goal-navigation baselines' planners."""

    kind: str  # the run's conav_jax.runs kind
    teacher: Callable[[Any], Any]  # env -> the teacher Agent in that env (train and validation envs)
    goal_obs: Callable[[Any], Callable] | None  # env -> `sensor(state) -> dict` the policy also reads; None: none
    config: dict  # what the run records about its teacher and goal (JSON)


class PolicyResult(NamedTuple):
    params: dict
    val: dict  # the final policy's validation metrics (envs.metrics.summarize)
    expert_val: dict  # the expert's, same episodes
    run_dir: Path


def records_predictions(imitation: ImitationConfig, model, intention=None, trajectory=None) -> bool:
    """Whether a run's recordings hold the predictors' outputs in place of the ground-truth
    intention inputs: `ImitationConfig.train_intentions` "predicted" with predictors given, for
    a policy that reads some intention input (one that reads none, Table 3's first row, records
    the same either way and needs no predictor)."""
    return (imitation.train_intentions == "predicted" and (intention is not None or trajectory is not None)
            and intention_source(model, intention, trajectory) != NO_INTENTIONS)


def round0_configs(model, imitation: ImitationConfig, intention=None, trajectory=None, shared: bool = False):
    """(the policy config round 0's recorder runs, the config naming its shared recording). The
    expert alone acts in round 0, so the policy's config only decides which inputs the records
    hold as predicted; every other input holds the ground truth, whatever the policy reads. A
    shared recording of predictions holds every one the given predictors make; each run reads
    its own inputs from it and never the others, so Table 3's five rows share one recording
    instead of making five, each large on disk and long to make at large panoramas
    (results/bench/README.md). Unshared: `model` twice."""
    if not shared:
        return model, model
    if imitation.train_intentions == "predicted":
        recorder = dataclasses.replace(model, use_activity=intention is not None, use_object=intention is not None,
                                       use_trajectory=trajectory is not None)
        return recorder, recorder
    # Ground truth: the records hold every input whichever the policy reads (compact_obs).
    return model, dataclasses.replace(model, use_activity=True, use_object=True, use_trajectory=True)


def expert_label_statistics(data_dir: str | Path, policy_run: str | Path, episodes: int = 96,
                            intention_run=None, trajectory_run=None, batch: int | None = None,
                            seed: int = 0) -> dict:
    """The CoNav expert's labels on its own states (behaviour cloning's data, beta = 1) and on
    the states of a `conav train policy` run acting (what a DAgger round adds, beta = 0), over
    the first `episodes` train episodes of `data_dir` at the run's panorama, the rollouts
    recording as the run's rounds do (its expert config; predicted intentions where it trained
    on them, from `intention_run`/`trajectory_run` or the runs it names) ->
    {"expert": ..., "policy": ...} of imitation.label_statistics, plus whether the data are
    those the run was trained on."""
    from conav_jax.envs.agents.policy import load_policy_run
    from conav_jax.envs.rollout import map_episodes

    if episodes < 1 or (batch is not None and batch < 1):
        raise ValueError(f"episodes and batch must be at least 1, got {episodes} and {batch}")
    params, model, config = load_policy_run(policy_run)  # ValueError for a run of another kind
    content_hash = read_manifest(data_dir)["content_hash"]
    imitation = ImitationConfig(train_intentions=config["imitation"]["train_intentions"])
    intention_run = intention_run or config.get("intention_run")
    trajectory_run = trajectory_run or config.get("trajectory_run")
    intention, trajectory = load_predictors(intention_run, trajectory_run)
    predicted = records_predictions(imitation, model, intention, trajectory)
    if imitation.train_intentions == "predicted" and needed_predictors(model) and not predicted:
        raise ValueError(f"{policy_run} trained on predicted intentions: pass its intention_run and trajectory_run")
    expert = ExpertConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in config["expert"].items()})
    h, w = model.resolution
    sensor = SensorConfig(resolution=(h, w), materials=materials_of_run(config))
    env = ConavEnv(data_dir, "train", EnvConfig(sensor=sensor, end_at_reach=True),
                   max_episodes=episodes)
    rollout = jit_with_bank(env, im.make_rollout_fn(
        env, model, expert, record=True, record_predicted=predicted,
        **({"intention": intention, "trajectory": trajectory} if predicted else {})))
    batch = batch or lanes_within(env.bank.max_steps * h * w * im.PANORAMA_BYTES_PER_PIXEL)  # whole episodes' records
    ids = np.arange(env.num_episodes, dtype=np.int32)
    out = {"data_is_the_runs": content_hash == config.get("data_hash"), "episodes": int(env.num_episodes)}
    for who, beta in (("expert", 1.0), ("policy", 0.0)):
        m, recs = map_episodes(lambda k, idx: rollout(params, k, idx, beta), ids, batch, jax.random.PRNGKey(seed),
                               host_fn=lambda o: (o[0], o[1]._replace(obs={})))  # the labels, not the panoramas
        out[who] = im.label_statistics(recs, m)
    return out


def run_config(model, imitation: ImitationConfig, expert, content_hash: str | None, intention_run,
               trajectory_run) -> dict:
    """The checkpoint's config: "kind", the PolicyConfig as "model" (what train.ppo's
    init_from and envs.agents.policy rebuild the network from: its resolution, ablation and
    saliency switch), the data and the predictor runs validation used."""
    return {
        "kind": KIND,
        "model": config_dict(model),
        "materials": SensorConfig.materials,  # what the training env renders (train_policy)
        "imitation": imitation_record(imitation),
        "expert": dataclasses.asdict(expert),
        "data_hash": content_hash,
        "intention_run": None if intention_run is None else str(intention_run),
        "trajectory_run": None if trajectory_run is None else str(trajectory_run),
        "predictor_digests": {"intention": predictor_digest(intention_run),
                              "trajectory": predictor_digest(trajectory_run)},
        PROVENANCE_KEY: provenance(materials=SensorConfig.materials, resolution=list(model.resolution),
                                   encoder=encoder_name(model), conv_dtype=model.conv_dtype),
    }


def predictor_resume_ignore(found: Path | None) -> tuple[str, ...]:
    """The config keys a resumed checkpoint `found` may differ in as to its predictors: their
    paths where it records their digests (checked instead); a checkpoint saved before runs
    recorded them is checked by the paths, as it was made."""
    if found is None:
        return ()
    return PREDICTOR_PATHS if "predictor_digests" in read_checkpoint_meta(found)["config"] else ("predictor_digests",)


def task_run_config(task: ImitationTask, model, imitation: ImitationConfig, content_hash: str | None) -> dict:
    """The checkpoint's config of a run imitating `task`'s teacher: its kind, the PolicyConfig as
    "model" (what envs.agents.goalnav rebuilds the network from), the data and the teacher."""
    return {
        "kind": task.kind,
        "model": config_dict(model),
        "materials": SensorConfig.materials,
        "imitation": imitation_record(imitation),
        "teacher": task.config,
        "data_hash": content_hash,
        PROVENANCE_KEY: provenance(materials=SensorConfig.materials, resolution=list(model.resolution),
                                   encoder=encoder_name(model), conv_dtype=model.conv_dtype),
    }


def expert_cache_key(fields: dict) -> str:
    """A cache entry's name: the digest of everything its content depends on (canonical JSON)."""
    fields = {"version": EXPERT_CACHE_VERSION, **fields}
    return hashlib.sha256(json.dumps(fields, sort_keys=True, default=str).encode()).hexdigest()[:20]


def expert_cache_entries(cache: Path, content_hash: str, model, imitation: ImitationConfig, expert, predicted: bool,
                         intention_run, trajectory_run, record_batch: int, devices: int) -> tuple[Path, Path]:
    """The CoNav expert's (ceiling .json, round-0 .npz) entries in `cache`, each named by what its
    content depends on: the data, the expert, the panorama size and the batching (floating-point
    reductions follow a batch's shape); for the ceiling its split and episodes; for round 0 the
    train episodes, the policy's config (the inputs it records), the windowing and, when it
    records the predictors' outputs, their checkpoints. Not the seed nor the weights: the expert
    ignores the rollout key (reset too: the episode fixes it) and, acting alone, the policy."""
    same = {"data_hash": content_hash, "expert": dataclasses.asdict(expert), "resolution": list(model.resolution),
            "devices": devices}
    ceiling = expert_cache_key({**same, "split": imitation.val_split, "episodes": imitation.val_episodes,
                                "batch": imitation.val_batch})
    round0 = expert_cache_key({
        **same, "split": "train", "episodes": imitation.episodes, "batch": record_batch, "model": config_dict(model),
        "seq_len": imitation.seq_len, "burn_in": imitation.burn_in, "predicted": predicted,
        "predictors": [predictor_digest(intention_run), predictor_digest(trajectory_run)] if predicted else None})
    return cache / f"ceiling_{ceiling}.json", cache / f"round0_{round0}.npz"


def predictor_digest(run) -> str | None:
    """The sha256 of a predictor run's latest checkpoint (None without a run): what a recording
    of its outputs depends on, wherever the run lies."""
    if run is None:
        return None
    found = latest_checkpoint(run)
    if found is None:
        raise FileNotFoundError(f"no checkpoint in predictor run {run}")
    return sha256_file(found)


def read_shared(path: Path):
    """An expert cache entry: a .json's content or a .npz's windows. ValueError naming the entry
    and the way out when it is missing or unreadable (entries are written atomically: only a
    change by hand breaks one)."""
    try:
        return json.loads(path.read_text()) if path.suffix == ".json" else im.load_sequences(path)
    except Exception as e:  # a truncated .npz raises zipfile's, numpy's or OSError, a bad .json its own
        raise ValueError(f"the expert cache entry {path} is unreadable ({type(e).__name__}: {e}); delete "
                         f"{path.parent} or train without sharing (share_expert=False)") from e


def _link_or_copy(src: Path, dst: Path) -> None:
    """`dst` as a hard link to `src` (no second copy of a recording on disk), else a copy;
    atomically either way, also with runs on the same data writing at once (a temp name each)."""
    if dst.exists() and os.path.samefile(src, dst):
        return
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.{time.monotonic_ns()}.tmp")
    try:
        os.link(src, tmp)
    except OSError:  # another filesystem, or one without hard links
        shutil.copyfile(src, tmp)
    os.replace(tmp, dst)
    tmp.unlink(missing_ok=True)  # renaming one link of a file onto another leaves both


@contextlib.contextmanager
def entry_lock(entry: Path | None, log: Callable[[str], None] = print):
    """Hold `entry`'s lock file (ENTRY.lock) while the entry is read or recorded: runs started
    together on one dataset (`conav reproduce --gpus`) record a shared entry once, the others
    waiting for it and then reading it. None: no lock (the run shares nothing)."""
    if entry is None:
        yield
        return
    entry.parent.mkdir(parents=True, exist_ok=True)
    with open(entry.with_name(entry.name + ".lock"), "a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log(f"waiting for another run recording {entry}")
            fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def check_recordable(r: int, begun: bool, path: Path, run_dir: Path) -> None:
    """Round `r`'s data file `path` is missing: fine before the round has begun, and for round 0
    at any time (the expert acts alone there, so its data depend on neither the weights nor the
    seed: a run copied without its data resumes). A later round's data came from a policy that no longer exists:
    FileNotFoundError."""
    if not begun or r == 0:
        return
    raise FileNotFoundError(f"cannot resume {run_dir}: {path}, the data of round {r}, is missing "
                            "(recorded by the policy of that time; start a new run)")


def rates_line(m: dict) -> str:
    """One line of a rollout's summary metrics, as the training logs print them."""
    return f"FASR {m['FASR']:.1f}  RASR {m['RASR']:.1f}  CR {m['CR']:.1f}  AS {m['AS']:.0f}"


def imitation_envs(data_dir: str | Path, model, imitation: ImitationConfig) -> tuple[ConavEnv, ConavEnv]:
    """The (train, validation) envs `train_policy` takes, from the dataset `data_dir`: its train
    split's first `imitation.episodes` and `imitation.val_split`'s first
    `imitation.val_episodes`, rendering the policy's resolution, each episode ending at the first
    reach (the expert's demonstrations end there)."""
    h, w = model.resolution
    env_cfg = EnvConfig(sensor=SensorConfig(resolution=(h, w)), end_at_reach=True)
    return (ConavEnv(data_dir, "train", env_cfg, max_episodes=imitation.episodes),
            ConavEnv(data_dir, imitation.val_split, env_cfg, max_episodes=imitation.val_episodes))


def check_run_args(cfg: TrainConfig, model, imitation: ImitationConfig, expert=None, intention_run=None,
                   trajectory_run=None, mesh=None, task: ImitationTask | None = None) -> None:
    """ValueError for what `train_policy` refuses whatever its envs: a task's run given an expert,
    predictor runs or predicted intentions; a batch the mesh does not divide; predicted training
    intentions without a predictor run for each input the ablation keeps."""
    if task is not None and (expert is not None or intention_run is not None or trajectory_run is not None
                             or imitation.train_intentions != "ground_truth"):
        raise ValueError(f"a {task.kind} run imitates its own teacher on its goal: no expert config, predictor runs "
                         "or predicted training intentions")
    if mesh is not None:
        check_divisible(cfg.batch, mesh, "TrainConfig.batch")
    if imitation.train_intentions == "predicted":
        given = {"intention": intention_run, "trajectory": trajectory_run}
        missing = [f"{k}_run" for k in needed_predictors(model) if given[k] is None]
        if missing:
            raise ValueError("training on predicted intentions (ImitationConfig.train_intentions) needs the predictor "
                             f"runs {', '.join(missing)}")


def check_imitation_envs(train_env: ConavEnv, val_env: ConavEnv, model, imitation: ImitationConfig) -> None:
    """ValueError, naming the config field, unless `train_env` holds the train split and `val_env`
    `imitation.val_split`, both of one dataset, with the episodes `imitation` names
    (`imitation_envs`), rendering the policy's resolution and the materials a run records
    (SensorConfig's default), each episode ending at the first reach."""
    check_split(train_env.split, "train", "train_env")
    check_split(val_env.split, imitation.val_split, "val_env", "ImitationConfig.val_split")
    check_same_data(train_env.split, val_env.split)
    for role, env, field, wanted in (("train_env", train_env, "episodes", imitation.episodes),
                                     ("val_env", val_env, "val_episodes", imitation.val_episodes)):
        check_sensor(env, role, model.resolution, "PolicyConfig.resolution", SensorConfig.materials,
                     "SensorConfig.materials (an imitation run records its default)")
        check_ends_at_reach(env, role, "the expert's demonstrations end there")
        check_episodes(env, wanted, f"ImitationConfig.{field}", role)


def check_episodes(env: ConavEnv, wanted: int | None, field: str, role: str) -> None:
    """ValueError unless `env` holds `wanted` episodes of its split (None: every one; all of them
    where the split has fewer), as ConavEnv's `max_episodes` loads them: a run records `wanted`,
    and the expert's shared recordings are named by it. A split made by hand counts as whole."""
    listed = env.split.manifest.get("splits", {}).get(env.split.name, {}).get("episodes", env.num_episodes)
    expected = listed if wanted is None else min(wanted, listed)
    if env.num_episodes != expected:
        raise ValueError(f"{field} is {wanted} but {role} holds {env.num_episodes} of the {listed} episodes of its "
                         f"split; build it with ConavEnv(..., max_episodes={wanted})")


def train_policy(
    train_env: ConavEnv,
    val_env: ConavEnv,
    run_dir: str | Path,
    cfg: TrainConfig,
    model,
    imitation: ImitationConfig = ImitationConfig(),
    expert=None,
    intention_run: str | Path | None = None,
    trajectory_run: str | Path | None = None,
    progress: bool = True,
    compiler_options: dict | None = None,
    log=print,
    mesh=None,
    remat: bool = False,
    scan_updates: bool | None = None,
    task: ImitationTask | None = None,
    share_expert: bool = True,
) -> PolicyResult:
    """Imitation-train the policy `model` (a conav_jax.models.policy.PolicyConfig: network,
    resolution, ablation) on `train_env` into `run_dir`, validating on `val_env`, resuming a run
    of the same config (ValueError naming the first difference otherwise). The envs are those
    `imitation_envs` builds: the train split and `imitation.val_split` of one dataset, whose
    content hash the run records (None for splits made by hand), with the episodes `imitation`
    names, rendering the policy's resolution, episodes ending at the first reach
    (`check_imitation_envs`: ValueError naming the config field an env does not match).

    Round 0 (behaviour cloning) makes `cfg.steps` updates, each DAgger round
    `imitation.dagger_steps`, each on train.loop in `run_dir/round_R` with a fresh Adam and its
    own warm-up + cosine schedule, warm-started from the previous round's weights; batches are
    `cfg.batch` windows drawn from (seed, round, update) alone, so a resumed run repeats an
    uninterrupted one. With `intention_run` / `trajectory_run`, validation feeds the policy the
    predictors' outputs (all of the inputs it reads, never a mix with ground truth); training
    uses ground truth (paper sec. 4.2) unless `imitation.train_intentions == "predicted"`, which
    records the predictors' outputs instead (ValueError unless a run is given for each input the
    ablation keeps). With a `mesh` (conav_jax.parallel.make_mesh) updates and rollouts run
    data-parallel over its devices. `remat` rematerialises the CNN per window step (less
    memory, same result up to float rounding). `scan_updates` (default: on a GPU or TPU, not on
    the CPU) as train.loop.train. With a `task` the policy imitates its teacher instead of the
    CoNav expert and also reads its goal sensor's observations; the run is of its kind (no
    `expert`, no predictor runs: a task's policy trains and validates on its goal itself).
    With `share_expert` the CoNav expert's ceiling and round-0 recording are read from
    EXPERT_CACHE_DIR of the dataset the train env was loaded from when an earlier run made them,
    else written there (same bytes as recording them: see `expert_cache_key`); a task's teacher
    and splits made by hand are not shared. Nothing is written before the arguments and the
    envs have been checked."""
    check_run_args(cfg, model, imitation, expert, intention_run, trajectory_run, mesh, task)
    check_imitation_envs(train_env, val_env, model, imitation)
    content_hash = train_env.split.content_hash
    expert = expert or ExpertConfig()
    if scan_updates is None:
        scan_updates = jax.default_backend() != "cpu"

    run_dir = Path(run_dir)
    config = (run_config(model, imitation, expert, content_hash, intention_run, trajectory_run) if task is None
              else task_run_config(task, model, imitation, content_hash))
    round_steps = [cfg.steps] + [imitation.dagger_steps or cfg.steps] * imitation.dagger_rounds
    round_end = np.cumsum(round_steps)  # global update count at each round's end

    # Rounds already trained: the latest top-level checkpoint (one per finished round).
    params = policy.init(jax.random.PRNGKey(cfg.seed), model)
    done, expert_val, val = -1, {}, {}
    found = latest_checkpoint(run_dir)
    if found is not None:
        try:
            ckpt = load_checkpoint(found, config=config, params_like=params,
                                   ignore=RESUME_CHANGEABLE + predictor_resume_ignore(found), upgrade=runs.upgrade_config)
        except ValueError as e:
            raise ValueError(f"cannot resume {run_dir}: {e}") from None
        params, done = ckpt.params, int(ckpt.extra["round"])
        expert_val, val = ckpt.extra["expert_val"], ckpt.extra["val"]
        log(f"resuming {run_dir} after round {done}")
    (run_dir / "data").mkdir(parents=True, exist_ok=True)
    log_path = run_dir / runs.LOG_FILE

    h, w = model.resolution
    intention, trajectory = load_predictors(intention_run, trajectory_run)
    # The rollouts take each split's episode bank as an argument: no episode data in the programs.
    jit = lambda env, f: jit_with_bank(env, f, mesh=mesh, compiler_options=compiler_options)  # noqa: E731

    def task_kwargs(env) -> dict:  # a task's teacher and goal sensor in `env`
        if task is None:
            return {}
        return {"teacher": task.teacher(env), "goal_obs": None if task.goal_obs is None else task.goal_obs(env)}

    train_task = task_kwargs(train_env)
    teacher_name = "expert" if task is None else train_task["teacher"].name
    share = share_expert and task is None and train_env.split.data_dir is not None
    round0_model, round0_key_model = round0_configs(model, imitation, intention, trajectory, share)
    recorder_models = (round0_model, model)
    recorders = {}

    def round_recorder(r: int):
        """(recorder, its jitted start, its jitted advance) of round `r`, built on first use."""
        m = recorder_models[min(r, 1)]
        if m not in recorders:
            rec_predicted = records_predictions(imitation, m, intention, trajectory)
            rec = im.make_recorder(train_env, m, expert, seq_len=imitation.seq_len, burn_in=imitation.burn_in,
                                   record_predicted=rec_predicted, **train_task,
                                   **({"intention": intention, "trajectory": trajectory} if rec_predicted else {}))
            recorders[m] = rec, jit(train_env, rec.start), jit(train_env, rec.advance)
        return recorders[m]

    recorder = round_recorder(0)[0]
    validate = jit(val_env, im.make_rollout_fn(val_env, model, expert, record=False, intention=intention, trajectory=trajectory,
                                      **task_kwargs(val_env)))
    # Where validation's intention inputs come from, logged with each validation (ground truth
    # when no predictor run is given: a training-time check, not a benchmark result).
    val_source = intention_source(model, intention, trajectory)
    train_eps, val_eps = np.arange(train_env.num_episodes), np.arange(val_env.num_episodes)
    record_batch = imitation.rollout_batch or recording_lanes(
        recorder.chunk_steps, imitation.seq_len, imitation.burn_in, (h, w),
        goal_image=task is not None and task.goal_obs is not None)
    val_key = jax.random.PRNGKey(cfg.seed + 1)
    cache = Path(train_env.split.data_dir) / EXPERT_CACHE_DIR if share else None
    if cache is not None:
        ceiling_entry, round0_entry = expert_cache_entries(
            cache, content_hash, round0_key_model, imitation, expert,
            records_predictions(imitation, round0_key_model, intention, trajectory), intention_run, trajectory_run,
            record_batch, 1 if mesh is None else mesh.size)

    def val_metrics(p, beta: float) -> dict:
        m, _ = im.run_batched(validate, p, val_key, val_eps, beta, imitation.val_batch, mesh=mesh)
        return {**summarize(m), "intention_source": val_source}

    def policy_val(p) -> dict:
        return {k: v for k, v in val_metrics(p, 0.0).items() if k != "intention_source"}

    if not expert_val:
        t0, shared = time.perf_counter(), ""
        with entry_lock(ceiling_entry if cache is not None else None, log):
            if cache is not None and ceiling_entry.is_file():
                expert_val, shared = read_shared(ceiling_entry), f", shared: {ceiling_entry}"
            else:
                expert_val = {k: v for k, v in val_metrics(params, 1.0).items() if k != "intention_source"}
                if cache is not None:
                    save_json(ceiling_entry, expert_val)
        append_log(log_path, {"split": imitation.val_split, "agent": teacher_name, "episodes": len(val_eps), **expert_val})
        log(f"{teacher_name} (the ceiling) on {imitation.val_split}, {len(val_eps)} episodes: {rates_line(expert_val)}  "
            f"[{time.perf_counter() - t0:.0f} s{shared}]")

    parts = []
    for r, steps in enumerate(round_steps):
        if done >= len(round_steps) - 1:  # every round trained: no data to record or load
            break
        path = run_dir / "data" / f"round_{r}.npz"
        round_dir = run_dir / f"round_{r}"
        if path.exists():
            parts.append(im.load_sequences(path))
        else:
            check_recordable(r, r <= done or latest_checkpoint(round_dir) is not None, path, run_dir)
            agent, beta = round_actor(r, imitation, teacher_name)
            if r <= done:
                log(f"round {r}: {path} is missing; recording it again (the {teacher_name}'s rollouts: same seed, same data)")
            t0, shared = time.perf_counter(), r == 0 and cache is not None
            with entry_lock(round0_entry if shared else None, log):
                if shared and round0_entry.is_file():  # its log line beside it, written first
                    entry = read_shared(round0_entry.with_suffix(".json"))
                    parts.append(read_shared(round0_entry))
                    _link_or_copy(round0_entry, path)
                    how = f"shared: {round0_entry}"
                else:
                    key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), r)
                    # A shared round 0's recorder may read more inputs than this policy: the expert
                    # acts alone there, yet its program takes parameters of its own config's shapes.
                    rec_params = params if recorder_models[min(r, 1)] == model else policy.init(
                        jax.random.PRNGKey(cfg.seed), recorder_models[0])
                    episodes = round_episodes(train_eps, r, imitation, cfg.seed)
                    m, windows, steps_run = im.record_windows(*round_recorder(r), rec_params, key, episodes, beta,
                                                              record_batch, mesh=mesh)
                    parts.append(windows)
                    im.save_sequences(path, parts[-1])
                    entry = {"step": int(round_end[r] - steps), "round": r, "split": "train", "agent": agent, "beta": beta,
                             "episodes": len(episodes), "windows": len(parts[-1]["label"]), **summarize(m)}
                    if shared:
                        cache.mkdir(exist_ok=True)
                        save_json(round0_entry.with_suffix(".json"), entry)
                        _link_or_copy(path, round0_entry)
                    how = f"recorded, {steps_run} of {round_recorder(r)[0].steps} steps, {min(record_batch, len(episodes))} lanes a call"
            append_log(log_path, entry)
            log(f"round {r}: {entry['episodes']} train episodes, {agent} acting ({rates_line(entry)}): "
                f"{entry['windows']} windows  [{time.perf_counter() - t0:.0f} s, {how}]")
        if r <= done:
            continue
        round_cfg = dataclasses.replace(cfg, steps=steps, warmup_steps=min(cfg.warmup_steps, steps),
                                        seed=cfg.seed + ROUND_SEED_STRIDE * r)
        result = loop.train(
            round_dir, lambda p, b, k: im.bc_loss(p, model, b, remat), params, im.concat_sequences(parts), round_cfg,
            {**config, "round": r}, val_fn=policy_val, progress=progress, compiler_options=compiler_options,
            mesh=mesh, scan_updates=scan_updates, log_extra={"round": r, "intention_source": val_source},
            # A round's length may change while it runs: its schedule stretches.
            resume_ignore=RESUME_CHANGEABLE + (("train.steps",) if r > 0 else ())
            + predictor_resume_ignore(latest_checkpoint(round_dir)), desc=f"round {r}",
        )
        params, val = jax.device_get(result.params), result.val
        save_checkpoint(checkpoint_path(run_dir, int(round_end[r])), params=params, opt_state=None, config=config,
                        step=int(round_end[r]), extra={"round": r, "val": val, "expert_val": expert_val})
        log(f"round {r} done: policy on {imitation.val_split}: {rates_line(val)}")
    if not val:  # resumed after its last round without a validation on record
        val = policy_val(params)
    return PolicyResult(params, val, expert_val, run_dir)


def train_policy_from_data(data_dir: str | Path, run_dir: str | Path, cfg: TrainConfig, model,
                           imitation: ImitationConfig = ImitationConfig(), **kwargs) -> PolicyResult:
    """`train_policy` on the dataset `data_dir`, its envs as `imitation_envs` builds them;
    `kwargs` as train_policy's. The arguments are checked before the dataset is loaded, and the
    dataset before anything is written."""
    check_run_args(cfg, model, imitation, **{k: kwargs.get(k) for k in (
        "expert", "intention_run", "trajectory_run", "mesh", "task")})
    train_env, val_env = imitation_envs(data_dir, model, imitation)
    return train_policy(train_env, val_env, run_dir, cfg, model, imitation, **kwargs)
