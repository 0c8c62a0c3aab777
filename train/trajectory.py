"""Training the short-term intention (trajectory) predictor.

The train and val splits' episodes (of envs, or their EpisodeSplits alone: `train_trajectory`;
`train_trajectory_from_data` loads them from a dataset directory) -> their `root_xy` -> windows
of k past + 5 future positions (mostly while walking, some standing), relative to the last past
point -> train/loop.py on an L2 loss -> val ADE/FDE (m) against constant velocity -> a run that
envs.agents.predictors loads for agents.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from conav_jax.provenance import PROVENANCE_KEY, provenance
from conav_jax import runs
from conav_jax.data.episodes import EpisodeSplit, load_split
from conav_jax.models import trajectory as traj_model
from conav_jax.models.trajectory import TrajectoryConfig
from conav_jax.motion.phases import PHASE_WALK
from conav_jax.envs import ConavEnv
from conav_jax.train.env_checks import check_same_data, check_split
from conav_jax.train.loop import TrainConfig, TrainResult, train

KIND = runs.TRAJECTORY
# The predictor's schedule unless a run gives its own (`conav train trajectory`'s defaults).
TRAJECTORY_TRAIN = TrainConfig(steps=3000, batch=256, lr=2e-3)


@dataclasses.dataclass(frozen=True)
class TrajectoryDataConfig:
    """Which windows of the episodes become samples."""

    standing_fraction: float = 0.2  # standing windows kept, as a fraction of the walking ones
    max_train_windows: int = 500_000  # random subsample above this (bounds device memory)
    max_val_windows: int = 20_000  # val ADE/FDE runs over at most this many windows
    seed: int = 0  # which standing windows / which subsample


def trajectory_windows(
    root_xy: np.ndarray,
    phase: np.ndarray,
    t_end: np.ndarray,
    history: int,
    horizon: int,
    standing_fraction: float,
    max_windows: int,
    seed: int,
) -> dict[str, np.ndarray]:
    """Windows of `history + horizon` consecutive positions lying inside `[0, t_end]`.

    `root_xy (N, T, 2)` m, `phase (N, T)`, `t_end (N,)` -> `{"history": (M, history, 2),
    "future": (M, horizon, 2)}` float32 metres, both relative to the last history point (so
    `history[:, -1] == 0`). Every window touching a walking step is kept, plus a random
    `standing_fraction` of that many windows in which the human stands (activities A/B);
    above `max_windows` a random subset. Order: by episode, then time.
    """
    n, t = phase.shape
    w = history + horizon
    if t < w:
        raise ValueError(f"episodes of {t} steps are shorter than one window ({w} steps)")
    # Walking steps in [s, s + w) for every window start s, from a cumulative count.
    walk = np.concatenate([np.zeros((n, 1), np.int32), np.cumsum(phase == PHASE_WALK, axis=1, dtype=np.int32)], 1)
    starts = np.arange(t - w + 1)
    walking = (walk[:, starts + w] - walk[:, starts]) > 0  # (N, S)
    inside = starts[None, :] + w - 1 <= np.asarray(t_end)[:, None]
    ep_walk, s_walk = np.nonzero(walking & inside)
    ep_stand, s_stand = np.nonzero(~walking & inside)
    rng = np.random.default_rng(seed)
    n_stand = min(len(ep_stand), int(round(standing_fraction * len(ep_walk))))
    pick = rng.choice(len(ep_stand), n_stand, replace=False)
    ep = np.concatenate([ep_walk, ep_stand[pick]])
    s = np.concatenate([s_walk, s_stand[pick]])
    if len(ep) > max_windows:
        keep = rng.choice(len(ep), max_windows, replace=False)
        ep, s = ep[keep], s[keep]
    if len(ep) == 0:
        raise ValueError("no window of the episodes lies inside [0, t_end]")
    order = np.lexsort((s, ep))
    ep, s = ep[order], s[order]
    xy = np.asarray(root_xy, np.float32)[ep[:, None], s[:, None] + np.arange(w)]  # (M, w, 2)
    xy = xy - xy[:, history - 1 : history]
    return {"history": xy[:, :history], "future": xy[:, history:]}


def split_windows(
    split: EpisodeSplit, model: TrajectoryConfig, data: TrajectoryDataConfig, max_windows: int
) -> dict[str, np.ndarray]:
    """`trajectory_windows` of one split's episodes."""
    eps = split.episodes
    return trajectory_windows(
        eps["root_xy"], eps["phase"], eps["t_end"], model.history, model.horizon,
        data.standing_fraction, max_windows, data.seed,
    )


def trajectory_loss(params, config: TrajectoryConfig, batch: dict, key: jax.Array):
    """Mean squared position error (m^2) over the horizon; aux: ADE (m)."""
    del key  # deterministic model, deterministic loss
    pred = traj_model.apply(params, config, batch["history"])
    ade, _ = traj_model.ade_fde(pred, batch["future"])
    return jnp.mean(jnp.sum(jnp.square(pred - batch["future"]), axis=-1)), {"ade_m": jnp.mean(ade)}


def make_val_fn(config: TrajectoryConfig, windows: dict, compiler_options: dict | None = None):
    """`val(params) -> {ade_m, fde_m, cv_ade_m, cv_fde_m}` over `windows`, metres; the
    constant-velocity figures are computed once."""
    hist, fut = jnp.asarray(windows["history"]), jnp.asarray(windows["future"])
    cv_ade, cv_fde = traj_model.ade_fde(traj_model.constant_velocity(hist, config.horizon), fut)
    baseline = {"cv_ade_m": float(cv_ade.mean()), "cv_fde_m": float(cv_fde.mean())}

    def model_errors(params, hist, fut):
        ade, fde = traj_model.ade_fde(traj_model.apply(params, config, hist), fut)
        return ade.mean(), fde.mean()

    model_errors = jax.jit(model_errors, compiler_options=compiler_options)

    def val(params) -> dict:
        ade, fde = model_errors(params, hist, fut)
        return {"ade_m": float(ade), "fde_m": float(fde), **baseline}

    return val


def run_config(model: TrajectoryConfig, data: TrajectoryDataConfig, content_hash: str | None) -> dict:
    """The checkpoint's config: what a resumed run must share."""
    return {
        "kind": KIND,
        "model": dataclasses.asdict(model),
        "data": {**dataclasses.asdict(data), "content_hash": content_hash},
        PROVENANCE_KEY: provenance(),  # reads no panorama: the code and the machine
    }


def train_trajectory(
    train_env: ConavEnv | EpisodeSplit,
    val_env: ConavEnv | EpisodeSplit,
    run_dir: str | Path,
    cfg: TrainConfig,
    model: TrajectoryConfig = TrajectoryConfig(),
    data: TrajectoryDataConfig = TrajectoryDataConfig(),
    progress: bool = True,
    compiler_options: dict | None = None,
    mesh: Mesh | None = None,
) -> TrainResult:
    """Train on the windows of `train_env`'s episodes (the train split), validate on
    `val_env`'s (the val split as `train_trajectory_from_data` loads it), both of one dataset,
    whose content hash the run records (see train.loop.train for resuming, errors and the
    data-parallel `mesh`). Either may be its EpisodeSplit alone: only the human's episodes
    are read, nothing is rendered."""
    train_split, val_split = (e.split if isinstance(e, ConavEnv) else e for e in (train_env, val_env))
    check_split(train_split, "train", "train_env")
    check_same_data(train_split, val_split)
    train_w = split_windows(train_split, model, data, data.max_train_windows)
    val_w = split_windows(val_split, model, data, data.max_val_windows)
    params = traj_model.init(jax.random.PRNGKey(cfg.seed), model)
    loss = lambda p, b, k: trajectory_loss(p, model, b, k)
    return train(
        run_dir, loss, params, train_w, cfg, run_config(model, data, train_split.content_hash),
        val_fn=make_val_fn(model, val_w, compiler_options), progress=progress, compiler_options=compiler_options, mesh=mesh,
    )


def train_trajectory_from_data(data_dir: str | Path, run_dir: str | Path, cfg: TrainConfig, *args,
                               **kwargs) -> TrainResult:
    """`train_trajectory` (the rest of its arguments) on the train and val splits of the dataset
    `data_dir` (their episodes alone: no env is built)."""
    return train_trajectory(load_split(data_dir, "train"), load_split(data_dir, "val"), run_dir, cfg, *args, **kwargs)
