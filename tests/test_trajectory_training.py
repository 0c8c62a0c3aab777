"""Trajectory predictor training: windows from episodes, a run that learns, the predictor API."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conav_jax.models import trajectory as traj_model
from conav_jax.models.trajectory import TrajectoryConfig
from conav_jax.motion.phases import (
    PHASE_ACTIVITY_A,
    PHASE_ACTIVITY_B,
    PHASE_DONE,
    PHASE_WALK,
)
from conav_jax.checkpoints import latest_checkpoint, load_checkpoint
from conav_jax.runs import read_log
from conav_jax.envs.agents.predictors import load_trajectory_predictor
from conav_jax.train.loop import TrainConfig, train
from conav_jax.train.trajectory import (
    TrajectoryDataConfig,
    make_val_fn,
    run_config,
    train_trajectory,
    train_trajectory_from_data,
    trajectory_loss,
    trajectory_windows,
)

FAST = {"xla_backend_optimization_level": 0}
MODEL = TrajectoryConfig(hidden=16)


def curving_walks(n, t=60, seed=0):
    """Walks turning left at a constant rate (0.03-0.08 rad per step) at 0.8-1.3 m/s:
    constant velocity misses the turn, a trained model need not."""
    rng = np.random.default_rng(seed)
    speed = rng.uniform(0.08, 0.13, n)[:, None]  # m per 0.1 s step
    turn = rng.uniform(0.03, 0.08, n)[:, None]
    heading = rng.uniform(-np.pi, np.pi, n)[:, None] + turn * np.arange(t)
    xy = np.cumsum(np.stack([speed * np.cos(heading), speed * np.sin(heading)], -1), axis=1)
    return xy.astype(np.float32), np.full((n, t), PHASE_WALK, np.int8), np.full(n, t - 1)


def test_windows_are_relative_to_the_last_past_point_and_inside_the_episode():
    t = 45
    phase = np.full((2, t), PHASE_DONE, np.int8)
    phase[:, :20], phase[:, 20:30], phase[:, 30:41] = PHASE_ACTIVITY_A, PHASE_WALK, PHASE_ACTIVITY_B
    t_end = np.array([40, 40])
    xy = np.random.default_rng(0).normal(size=(2, t, 2)).astype(np.float32)
    xy[:, 41:] = np.nan  # past t_end: must never be read
    # 13-step windows starting at s in [0, 28]; those touching the walk [20, 30): s in [8, 28].
    walking = trajectory_windows(xy, phase, t_end, 8, 5, 0.0, 10**6, 0)
    assert walking["history"].shape == (2 * 21, 8, 2) and walking["future"].shape == (2 * 21, 5, 2)
    h, f = walking["history"], walking["future"]
    assert np.all(np.isfinite(h)) and np.all(np.isfinite(f))
    np.testing.assert_array_equal(h[:, -1], 0.0)
    np.testing.assert_allclose(np.concatenate([h[0], f[0]]), xy[0, 8:21] - xy[0, 15], atol=1e-6)
    # 16 standing windows exist (s in [0, 7]); a fraction 0.2 of 42 walking ones keeps 8.
    assert len(trajectory_windows(xy, phase, t_end, 8, 5, 0.2, 10**6, 0)["history"]) == 42 + 8
    assert len(trajectory_windows(xy, phase, t_end, 8, 5, 1.0, 10**6, 0)["history"]) == 42 + 16
    assert trajectory_windows(xy, phase, t_end, 8, 5, 1.0, 5, 0)["history"].shape == (5, 8, 2)


@pytest.fixture(scope="module")
def curving_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("traj_run")
    val = trajectory_windows(*curving_walks(8, seed=1), 8, 5, 0.0, 10**6, 0)
    result = train(
        run_dir,
        lambda p, b, k: trajectory_loss(p, MODEL, b, k),
        traj_model.init(jax.random.PRNGKey(0), MODEL),
        trajectory_windows(*curving_walks(16), 8, 5, 0.0, 10**6, 0),
        TrainConfig(steps=60, batch=32, lr=1e-2, warmup_steps=5, log_every=60, val_every=60, ckpt_every=60),
        run_config(MODEL, TrajectoryDataConfig(), None),
        val_fn=make_val_fn(MODEL, val, FAST),
        progress=False,
        compiler_options=FAST,
    )
    return run_dir, result


def test_short_training_beats_constant_velocity_on_curving_walks(curving_run):
    run_dir, result = curving_run
    v = result.val
    assert v["ade_m"] < 0.5 * v["cv_ade_m"] and v["fde_m"] < 0.5 * v["cv_fde_m"]
    assert [r["split"] for r in read_log(run_dir)] == ["train", "val"]


def test_predictor_works_in_the_callers_frame(curving_run):
    run_dir, _ = curving_run
    predictor = load_trajectory_predictor(run_dir)
    assert predictor.config == MODEL
    xy, _, _ = curving_walks(1, t=8, seed=2)
    history = jnp.asarray(xy[0] + np.array([3.0, -2.0], np.float32))  # far from the origin
    future = jax.jit(predictor.predict)(history)
    assert future.shape == (5, 2)
    shifted = jax.jit(predictor.predict)(history + 10.0)
    np.testing.assert_allclose(shifted, future + 10.0, atol=1e-4)
    with pytest.raises(ValueError, match="history"):
        predictor.predict(jnp.zeros((4, 2)))


def test_a_run_on_an_env_and_a_split_resumes_from_the_data_directory(tiny_data, tmp_path):
    from conav_jax.data.episodes import load_split, read_manifest
    from conav_jax.envs import ConavEnv

    train_split, val_env = load_split(tiny_data, "train"), ConavEnv(str(tiny_data), "val")
    cfg = TrainConfig(steps=2, batch=8, warmup_steps=0, log_every=1, val_every=2, ckpt_every=2)
    with pytest.raises(ValueError, match="train_env holds the 'val' split; expected 'train'"):
        train_trajectory(val_env, val_env, tmp_path / "run", cfg, MODEL, progress=False, compiler_options=FAST)
    assert not (tmp_path / "run").exists()
    result = train_trajectory(train_split, val_env, tmp_path / "run", cfg, MODEL, progress=False,
                              compiler_options=FAST)
    assert result.step == 2 and result.val["ade_m"] > 0
    config = load_checkpoint(latest_checkpoint(tmp_path / "run")).config
    assert config["data"]["content_hash"] == read_manifest(tiny_data)["content_hash"]  # the splits' dataset
    # The data directory's form writes the same config: it resumes the finished run, training no more.
    resumed = train_trajectory_from_data(tiny_data, tmp_path / "run", cfg, MODEL, progress=False,
                                         compiler_options=FAST)
    assert resumed.step == 2 and [r["split"] for r in read_log(tmp_path / "run")] == ["train", "train", "val", "val"]


def test_cli_registers_the_trajectory_command():
    from conav_jax.eval.cli import build_parser

    args = build_parser().parse_args(["train", "trajectory", "--data", "D", "--out", "R", "--steps", "7", "--lr", "0.5"])
    assert (args.data, args.out, args.steps, args.lr) == ("D", "R", 7, 0.5)
