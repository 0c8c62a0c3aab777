"""`conav train policy`: the CoNav LSTM policy imitates the expert (BC, then DAgger rounds).

Round 0 records the expert on the train split; each DAgger round rolls out the current policy,
the expert labels the states it visits, and the aggregated windows (RUN/data/round_R.npz)
train it further. Validation runs the policy in the simulator on the val split. RUN/log.jsonl
holds the expert's val metrics (the ceiling), losses, and validations; RUN/ckpt_*.npz the
policy (read by envs.agents.policy.policy_agent and train.ppo's --init-from); runs resume. With a
device mesh (conav_jax.parallel) every update's windows and every simulator batch are split
over the devices, parameters replicated.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

from conav_jax import runs
from conav_jax.runs import append_log, resume
from train.loop import TrainConfig, add_train_args, train_config_from_args

KIND = runs.POLICY
# ImitationConfig fields a resumed run may change: more DAgger rounds continue a finished run;
# batching and the val subset do not change the weights.
RESUME_FREE = ("dagger_rounds", "rollout_batch", "val_episodes")
# Recorded in the run's config, yet a resumed run may change them: the length of DAgger rounds
# to come (a round already begun takes it as its new length; its schedule stretches).
RESUME_CHANGEABLE = ("imitation.dagger_steps",)
# ImitationConfig fields that shape the network: the run's config records them under "model".
MODEL_FIELDS = ("object_saliency",)
TRAIN_INTENTIONS = ("ground_truth", "predicted")


@dataclass(frozen=True)
class ImitationConfig:
    """What the policy sees and which data it learns from (TrainConfig: each round's updates)."""

    ablation: str = "all"  # Table 3 row: none | activity | object | activity_object | all
    resolution: tuple[int, int] = (112, 448)  # panorama (H, W) rendered and fed to the policy
    episodes: int | None = None  # train-split episodes recorded (None: all)
    val_episodes: int | None = None  # val-split episodes validated on (None: all)
    dagger_rounds: int = 0  # rounds after behaviour cloning
    dagger_steps: int | None = None  # updates per DAgger round (None: TrainConfig.steps)
    seq_len: int = 32  # steps per training window in the loss (truncated BPTT)
    burn_in: int = 16  # steps before each window that only warm up the LSTM
    rollout_batch: int = 64  # episodes per simulator call (recording and validation)
    # Intention inputs in the training data: "ground_truth" (the paper, sec. 4.2) or "predicted"
    # (the predictor runs' outputs, recorded along every rollout: what the policy reads at
    # evaluation, so it learns how far to trust them).
    train_intentions: str = "ground_truth"
    # With the object input: read it as a saliency map over the panorama too (PolicyConfig;
    # False gives session 4's policy, which reads the object distribution as a vector only).
    # Recorded in the run's "model" config.
    object_saliency: bool = True

    def __post_init__(self):
        from conav_jax.models.policy import ABLATIONS

        if self.ablation not in ABLATIONS:
            raise ValueError(f"unknown ablation {self.ablation!r}; expected one of {sorted(ABLATIONS)}")
        if self.train_intentions not in TRAIN_INTENTIONS:
            raise ValueError(f"unknown train_intentions {self.train_intentions!r}; expected one of {TRAIN_INTENTIONS}")
        if self.dagger_rounds < 0 or self.seq_len < 1 or self.burn_in < 0 or self.rollout_batch < 1:
            raise ValueError("need dagger_rounds >= 0, seq_len >= 1, burn_in >= 0, rollout_batch >= 1")
        for name in ("episodes", "val_episodes", "dagger_steps"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ValueError(f"ImitationConfig.{name} must be >= 1 (or None), got {getattr(self, name)}")


class PolicyResult(NamedTuple):
    params: dict
    val: dict  # the final policy's val metrics (envs.metrics.summarize)
    expert_val: dict  # the expert's, same episodes
    run_dir: Path


def run_config(model, imitation: ImitationConfig, expert, content_hash: str, intention_run, trajectory_run) -> dict:
    """The checkpoint's config: "kind", the PolicyConfig as "model" (what train.ppo's
    --init-from and envs.agents.policy rebuild the network from), the sensor resolution, the
    data and the predictor runs validation used."""
    return {
        "kind": KIND,
        "model": dataclasses.asdict(model),
        "sensor_hw": list(imitation.resolution),
        "imitation": {k: v for k, v in dataclasses.asdict(imitation).items() if k not in RESUME_FREE + MODEL_FIELDS},
        "expert": dataclasses.asdict(expert),
        "data_hash": content_hash,
        "intention_run": None if intention_run is None else str(intention_run),
        "trajectory_run": None if trajectory_run is None else str(trajectory_run),
    }


def policy_model(imitation: ImitationConfig):
    """The PolicyConfig an imitation run trains: its resolution, ablation and saliency switch."""
    from conav_jax.models.policy import PolicyConfig, ablation_config

    base = PolicyConfig(image_hw=tuple(imitation.resolution), object_saliency=imitation.object_saliency)
    return ablation_config(base, imitation.ablation)


def window_indices(seed: int, step: int, n: int, batch: int):
    """The `batch` window indices of update `step` (with replacement): a function of
    `(seed, step)` alone, so a resumed run draws what an uninterrupted one would."""
    import numpy as np

    return np.random.default_rng([seed, step]).integers(0, n, batch).astype(np.int32)


def check_recordable(r: int, step: int, start: int, path: Path, run_dir: Path) -> None:
    """Round `r`'s data file `path` is missing at update `step` of a run whose round `r` starts at
    update `start`: fine before the round has begun, and for round 0 at any time (the expert acts
    alone there, so its data depend on the seed only: a run copied without its data resumes).
    A later round's data came from a policy that no longer exists: FileNotFoundError."""
    if step <= start or r == 0:
        return
    raise FileNotFoundError(f"cannot resume {run_dir}: {path}, the data of round {r}, is missing "
                            "(recorded by the policy of that time; start a new run)")


def _rates(m: dict) -> str:
    return f"FASR {m['FASR']:.1f}  RASR {m['RASR']:.1f}  CR {m['CR']:.1f}  AS {m['AS']:.0f}"


def make_update(model, cfg: TrainConfig, compiler_options: dict | None = None, mesh=None, remat: bool = False):
    """Jitted `(params, opt_state, data, idx, lr, step, bad_step) -> (params, opt_state, loss,
    grad_norm, bad_step)`: one Adam(W) step on `bc_loss` over the windows `data[idx]`, with
    global-norm clipping. `data` lives on the device and is gathered inside the jit, so an update
    moves only `idx` to the device and nothing back. The first update whose loss or gradient is
    not finite is not applied and its `step` lands in `bad_step` (-1 while all is well); once
    set, no later update is applied either, so the caller checks `bad_step` only when it logs and
    still stops at the last good state. The learning rate is an argument: every round's schedule
    shares one compiled update. With a `mesh` (data, params and opt_state replicated on it) the
    gathered windows are split over its devices and every output is replicated. `remat`: the
    loss rematerialises the CNN per step (bc_loss), same result in less memory."""
    import jax
    import jax.numpy as jnp

    from conav_jax.optim import adam, clip_by_global_norm
    from conav_jax.parallel import constrain_batch, replicated
    from train.imitation import bc_loss

    def update(params, opt_state, data, idx, lr, step, bad_step):
        batch = constrain_batch(jax.tree.map(lambda x: jnp.take(x, idx, axis=0), data), mesh)
        (loss, _), grads = jax.value_and_grad(bc_loss, has_aux=True)(params, model, batch, remat)
        grads, grad_norm = clip_by_global_norm(grads, cfg.grad_clip)
        new_params, new_opt = adam(lr, weight_decay=cfg.weight_decay).update(grads, opt_state, params)
        finite = jnp.isfinite(loss) & jnp.isfinite(grad_norm)
        ok = finite & (bad_step < 0)
        params, opt_state = jax.tree.map(lambda n, o: jnp.where(ok, n, o), (new_params, new_opt), (params, opt_state))
        bad_step = jnp.where(~finite & (bad_step < 0), step, bad_step)
        return params, opt_state, loss, grad_norm, bad_step

    out = None if mesh is None else replicated(mesh)
    return jax.jit(update, compiler_options=compiler_options, out_shardings=out)


def train_policy(
    data_dir: str | Path,
    run_dir: str | Path,
    cfg: TrainConfig,
    imitation: ImitationConfig = ImitationConfig(),
    expert=None,
    intention_run: str | Path | None = None,
    trajectory_run: str | Path | None = None,
    progress: bool = True,
    compiler_options: dict | None = None,
    log=print,
    mesh=None,
    remat: bool = False,
) -> PolicyResult:
    """Imitation-train the policy on `data_dir`'s train split into `run_dir` (resumed from its
    latest checkpoint if it has one of the same config; ValueError naming the first difference
    otherwise).

    Round 0 (behaviour cloning) makes `cfg.steps` updates, each DAgger round
    `imitation.dagger_steps`, each round with a fresh Adam and its own warm-up + cosine
    schedule, warm-started from the previous round's weights. Batches are `cfg.batch` windows
    drawn (with replacement) from `(cfg.seed, update step)` alone, so a resumed run repeats an
    uninterrupted one. With `intention_run` / `trajectory_run`, validation feeds the policy the
    predictors' outputs; training uses ground truth (paper sec. 4.2) unless
    `imitation.train_intentions == "predicted"`, which records the predictors' outputs instead
    (ValueError unless a run is given for each intention input the ablation keeps). With a `mesh`
    (conav_jax.parallel.make_mesh) updates and rollouts run data-parallel over its devices,
    drawing the same windows and episodes (ValueError unless `cfg.batch` divides by the device
    count). `remat` rematerialises the CNN per window step in the update (less memory, same
    result up to float rounding; not part of the run's config, like the mesh).

    A focused loop rather than train.loop: that loop scans its updates inside one jit, and on
    XLA:CPU a conv update inside a while loop runs ~20x slower than the same update jitted
    alone. Here each update is one asynchronous call on device-resident windows; the host
    reads losses back once per log interval, so the GPU is never idle waiting for it."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from tqdm import tqdm

    from conav_jax.checkpoints import checkpoint_path, latest_checkpoint, save_checkpoint
    from conav_jax.episodes import read_manifest
    from conav_jax.expert import ExpertConfig
    from conav_jax.models import policy
    from conav_jax.optim import adam, warmup_cosine
    from conav_jax.parallel import check_divisible, replicate
    from envs import ConavEnv, EnvConfig, SensorConfig
    from envs.agents.policy import intention_source, load_predictors
    from envs.metrics import summarize
    from train import imitation as im
    from train.loop import NonFiniteLoss

    expert = expert or ExpertConfig()
    if mesh is not None:
        check_divisible(cfg.batch, mesh, "TrainConfig.batch")
    if imitation.train_intentions == "predicted":
        needs = policy_model(imitation)
        missing = [flag for flag, use, run in (
            ("--intention", needs.use_activity or needs.use_object, intention_run),
            ("--trajectory", needs.use_trajectory, trajectory_run)) if use and run is None]
        if missing:
            raise ValueError(f"training on predicted intentions (ablation {imitation.ablation!r}) needs the "
                             f"predictor runs {', '.join(missing)}")

    def place(tree):
        """On the device; with a mesh, a copy on each of its devices."""
        return jax.device_put(tree) if mesh is None else replicate(tree, mesh)

    run_dir = Path(run_dir)
    content_hash = read_manifest(data_dir)["content_hash"]  # before any mkdir: a bad --data leaves nothing
    (run_dir / "data").mkdir(parents=True, exist_ok=True)
    log_path = run_dir / runs.LOG_FILE
    model = policy_model(imitation)
    config = {**run_config(model, imitation, expert, content_hash, intention_run, trajectory_run), "train": cfg.optimisation()}
    round_steps = [cfg.steps] + [imitation.dagger_steps or cfg.steps] * imitation.dagger_rounds
    round_end = np.cumsum(round_steps)  # global update count at each round's end

    params = policy.init(jax.random.PRNGKey(cfg.seed), model)
    opt_state = adam(cfg.lr).init(params)
    step, expert_val, val = 0, {}, {}
    ckpt = resume(run_dir, config, params, opt_state, ignore=RESUME_CHANGEABLE)
    if ckpt is not None:
        params, opt_state, step = ckpt.params, ckpt.opt_state, ckpt.step
        expert_val, val = ckpt.extra["expert_val"], ckpt.extra["val"]
        log(f"resuming {run_dir} at update {step}")

    h, w = imitation.resolution
    # Imitation data and validation stop at the first reach (the expert's demonstrations end there).
    env_cfg = EnvConfig(sensor=SensorConfig(height=h, width=w), end_at_reach=True)
    train_env = ConavEnv(data_dir, "train", env_cfg, max_episodes=imitation.episodes)
    val_env = ConavEnv(data_dir, "val", env_cfg, max_episodes=imitation.val_episodes)
    intention, trajectory = load_predictors(intention_run, trajectory_run)
    jit = lambda f: jax.jit(f, compiler_options=compiler_options)  # noqa: E731
    predicted = imitation.train_intentions == "predicted" and (intention is not None or trajectory is not None)
    record = jit(im.make_rollout_fn(train_env, model, expert, record=True, record_predicted=predicted,
                                    **({"intention": intention, "trajectory": trajectory} if predicted else {})))
    validate = jit(im.make_rollout_fn(val_env, model, expert, record=False, intention=intention, trajectory=trajectory))
    # Where validation's intention inputs come from, logged with each validation (ground truth
    # when no predictor run is given: a training-time check, not a benchmark result).
    val_source = intention_source(model, intention, trajectory)
    update = make_update(model, cfg, compiler_options, mesh, remat)
    train_eps, val_eps = np.arange(train_env.num_episodes), np.arange(val_env.num_episodes)
    val_key = jax.random.PRNGKey(cfg.seed + 1)

    def val_metrics(p, beta: float) -> dict:
        m, _ = im.run_batched(validate, p, val_key, val_eps, beta, imitation.rollout_batch, mesh=mesh)
        return summarize(m)

    def checkpoint(r: int) -> None:
        save_checkpoint(checkpoint_path(run_dir, step), params=params, opt_state=opt_state, config=config,
                        step=step, extra={"round": r, "val": val, "expert_val": expert_val})

    if not expert_val:
        t0 = time.perf_counter()
        expert_val = val_metrics(params, 1.0)
        append_log(log_path, {"split": "val", "agent": "expert", "episodes": len(val_eps), **expert_val})
        log(f"expert (the ceiling) on val, {len(val_eps)} episodes: {_rates(expert_val)}  [{time.perf_counter() - t0:.0f} s]")

    parts = []
    for r, (steps, end) in enumerate(zip(round_steps, round_end)):
        path = run_dir / "data" / f"round_{r}.npz"
        start = end - steps
        if path.exists():
            parts.append(im.load_sequences(path))
        else:
            check_recordable(r, step, start, path, run_dir)
            # Round 0: the expert acts (behaviour cloning); later: the current policy (DAgger).
            agent, beta = ("expert", 1.0) if r == 0 else ("policy", 0.0)
            if step > start:
                log(f"round {r}: {path} is missing; recording it again (the expert's rollouts: same seed, same data)")
            t0 = time.perf_counter()
            key = jax.random.fold_in(jax.random.PRNGKey(cfg.seed), r)
            m, recs = im.run_batched(record, params, key, train_eps, beta, imitation.rollout_batch, mesh=mesh)
            parts.append(im.sequences(recs, imitation.seq_len, imitation.burn_in))
            im.save_sequences(path, parts[-1])
            append_log(log_path, {"step": step, "round": r, "split": "train", "agent": agent, "episodes": len(train_eps),
                                   "windows": len(parts[-1]["label"]), **summarize(m)})
            log(f"round {r}: recorded {len(train_eps)} train episodes, {agent} acting ({_rates(summarize(m))}): "
                f"{len(parts[-1]['label'])} windows  [{time.perf_counter() - t0:.0f} s]")
        if step >= end:
            continue
        data = place(im.concat_sequences(parts))
        n = len(data["label"])
        # The round's learning rates, read back once: a per-update read would wait for the
        # update queued before it and stall the device.
        schedule = np.asarray(jax.vmap(warmup_cosine(cfg.lr, min(cfg.warmup_steps, steps), steps))(jnp.arange(steps)))
        if step == start:
            opt_state = adam(cfg.lr).init(params)  # each round starts its own Adam
        params, opt_state = place((params, opt_state))
        losses, t_log, bad = [], time.perf_counter(), jnp.int32(-1)
        bar = tqdm(total=steps, initial=step - start, disable=not progress, unit="step", desc=f"round {r}", dynamic_ncols=True)
        while step < end:
            idx = window_indices(cfg.seed, step, n, cfg.batch)
            lr = float(schedule[step - start])
            params, opt_state, loss, grad_norm, bad = update(params, opt_state, data, idx, lr, step, bad)
            losses.append((loss, grad_norm))  # device scalars: read back only when logging
            step += 1
            bar.update(1)
            boundary = step == end or any(step % e == 0 for e in (cfg.log_every, cfg.val_every, cfg.ckpt_every))
            if not boundary:
                continue
            if int(bad) >= 0:  # the one host sync per log interval
                b = int(bad)
                bad_idx = window_indices(cfg.seed, b, n, cfg.batch).tolist()
                append_log(log_path, {"step": b, "round": r, "split": "train", "error": "non-finite loss",
                                       "indices": bad_idx})
                raise NonFiniteLoss(f"non-finite loss or gradient at update {b} (windows {bad_idx}); stopped, "
                                    f"last good checkpoint: {latest_checkpoint(run_dir)}", b, bad_idx)
            if step % cfg.log_every == 0 or step == end:
                mean_loss, mean_norm = np.asarray(jax.device_get(losses), np.float64).mean(0)
                rate = cfg.batch * len(losses) / (time.perf_counter() - t_log)
                append_log(log_path, {"step": step, "round": r, "split": "train", "loss": mean_loss,
                                       "grad_norm": mean_norm, "lr": lr, "windows": n, "samples_per_s": round(rate, 1)})
                bar.set_postfix(loss=f"{mean_loss:.4g}")
                losses, t_log = [], time.perf_counter()
            if step % cfg.val_every == 0 or step == end:
                val = val_metrics(params, 0.0)
                append_log(log_path, {"step": step, "round": r, "split": "val", "agent": "policy",
                                      "intention_source": val_source, **val})
                bar.write(f"update {step} (round {r}): policy on val: {_rates(val)}")
            if step % cfg.ckpt_every == 0 or step == end:
                checkpoint(r)
        bar.close()
    if not val:  # resumed at the very end of a run that never validated
        val = val_metrics(params, 0.0)
    return PolicyResult(params, val, expert_val, run_dir)


# -- CLI -------------------------------------------------------------------------------------------


def _hw(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"expected HxW like 112x448, got {text!r}") from None
    return h, w


def add_train_policy(sub: argparse._SubParsersAction) -> None:
    """Register `conav train policy`."""
    from conav_jax.models.policy import ABLATIONS

    p = sub.add_parser("policy", help="imitation-train the CoNav policy from the expert (BC, then DAgger)")
    add_train_args(p, TrainConfig(steps=2000, batch=16, lr=3e-4, warmup_steps=100, val_every=1000, ckpt_every=500))
    d = ImitationConfig()
    p.add_argument("--intention", default=None, help="intention run (conav train intention): validate with its predictions")
    p.add_argument("--trajectory", default=None, help="trajectory run (conav train trajectory): validate with its predictions")
    p.add_argument("--ablation", choices=sorted(ABLATIONS), default=d.ablation, help="intention inputs kept (Table 3)")
    p.add_argument("--dagger-rounds", type=int, default=d.dagger_rounds,
                   help="DAgger rounds after behaviour cloning (a finished run resumes with more)")
    p.add_argument("--dagger-steps", type=int, default=None,
                   help="updates per DAgger round (default: --steps); a resumed run may change it for the rounds to come")
    p.add_argument("--resolution", default="x".join(map(str, d.resolution)), help="panorama HxW")
    p.add_argument("--episodes", type=int, default=None, help="train episodes recorded (default: all)")
    p.add_argument("--val-episodes", type=int, default=None, help="val episodes validated on (default: all)")
    p.add_argument("--seq-len", type=int, default=d.seq_len, help="steps per training window")
    p.add_argument("--burn-in", type=int, default=d.burn_in, help="LSTM warm-up steps before each window")
    p.add_argument("--rollout-batch", type=int, default=d.rollout_batch, help="episodes per simulator call")
    p.add_argument("--remat", action="store_true",
                   help="recompute the CNN per window step in the backward pass: less memory (112x448 windows "
                   "at batch >= 256 need it on an H100), ~1.7x the update time")
    p.add_argument("--train-intentions", choices=TRAIN_INTENTIONS, default=d.train_intentions,
                   help="intention inputs in the training data: ground truth (the paper) or the predictor runs' outputs")
    p.add_argument("--object-saliency", action=argparse.BooleanOptionalAction, default=d.object_saliency,
                   help="with the object input, also read it as a saliency map over the panorama (default: on; "
                   "--no-object-saliency reads the object distribution as a vector only)")
    p.set_defaults(func=run_train_policy)


def run_train_policy(args: argparse.Namespace) -> int:
    imitation = ImitationConfig(
        ablation=args.ablation, resolution=_hw(args.resolution), episodes=args.episodes,
        val_episodes=args.val_episodes, dagger_rounds=args.dagger_rounds, dagger_steps=args.dagger_steps,
        seq_len=args.seq_len, burn_in=args.burn_in, rollout_batch=args.rollout_batch,
        train_intentions=args.train_intentions, object_saliency=args.object_saliency,
    )
    for flag, run in (("--intention", args.intention), ("--trajectory", args.trajectory)):
        if run is not None and not Path(run).is_dir():
            raise FileNotFoundError(f"{flag} run directory not found: {run}")
    from conav_jax.parallel import make_mesh
    from train.loop import NonFiniteLoss

    try:
        result = train_policy(
            args.data, args.out, train_config_from_args(args), imitation,
            intention_run=args.intention, trajectory_run=args.trajectory, progress=not args.no_progress,
            mesh=make_mesh(args.devices), remat=args.remat,
        )
    except NonFiniteLoss as e:
        print(f"conav train policy: {e}")
        return 1
    print(f"policy run: {result.run_dir}")
    print(f"val expert (ceiling): {_rates(result.expert_val)}")
    print(f"val policy:           {_rates(result.val)}")
    return 0
