"""The intention and trajectory predictors of trained runs, as agents use them while acting.

`load_intention_predictor(run)` turns a `conav train intention` run into a per-env, per-step
predictor: front views go into a frame ring buffer, the Perceiver reads them, and the output
is the mean of the lowest-entropy recent predictions (paper sec. 4.2). `load_trajectory_predictor
(run)` turns a `conav train trajectory` run into `predict(history) -> next positions`. Both
close over their parameters, are jittable and vmappable, and run inside the agents' `act`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp

from conav_jax import runs
from conav_jax.models import perceiver
from conav_jax.models import trajectory as traj_model
from conav_jax.models.perceiver import PerceiverConfig
from conav_jax.models.trajectory import TrajectoryConfig


class IntentionCarry(NamedTuple):
    """Per-env state of the predictor (arrays; vmap it for a batch of envs)."""

    frames: jax.Array  # (F, h, w, 4) the last F recorded frames, oldest first
    num_frames: jax.Array  # int32: frames recorded so far, capped at F
    activity_history: jax.Array  # (P, num_activities) the last P predictions, oldest first
    object_history: jax.Array  # (P, num_objects)
    num_predictions: jax.Array  # int32: predictions recorded so far, capped at P
    t: jax.Array  # int32: step() calls so far


class IntentionPredictor(NamedTuple):
    """A trained Perceiver with its parameters closed over, for one env (jittable, vmappable).

    `init() -> carry`; `step(carry, front) -> (activity_probs (107,), object_probs (51,),
    carry)` with `front (H, W/4, 4)` float, the env's `obs["front"]` at any resolution."""

    config: PerceiverConfig
    frame_stride: int
    init: Callable[[], IntentionCarry]
    step: Callable[[IntentionCarry, jax.Array], tuple[jax.Array, jax.Array, IntentionCarry]]


def _push(buffer: jax.Array, count: jax.Array, item: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Append `item` to a ring buffer kept oldest-first: fill slots 0.., then shift left."""
    size = buffer.shape[0]
    full = count >= size
    buffer = jnp.where(full, jnp.roll(buffer, -1, axis=0), buffer)
    return buffer.at[jnp.minimum(count, size - 1)].set(item), jnp.minimum(count + 1, size)


def make_intention_predictor(
    params, config: PerceiverConfig, frames: int, frame_stride: int = 1, history: int = 16, top_k: int = 5
) -> IntentionPredictor:
    """A predictor that records a frame every `frame_stride` calls (training frames were that
    far apart), keeps the last `frames`, runs the Perceiver on them and returns the mean of
    the `top_k` lowest-entropy of the last `history` predictions (paper sec. 4.2)."""
    h, w = config.image_hw
    f32 = jnp.float32

    def init() -> IntentionCarry:
        zero = jnp.zeros((), jnp.int32)
        return IntentionCarry(
            jnp.zeros((frames, h, w, config.channels), f32), zero,
            jnp.zeros((history, config.num_activities), f32), jnp.zeros((history, config.num_objects), f32),
            zero, zero,
        )

    def step(carry: IntentionCarry, front: jax.Array):
        if front.ndim != 3 or front.shape[-1] != config.channels:
            raise ValueError(f"front must be (H, W, {config.channels}), got {front.shape}")
        record = carry.t % frame_stride == 0
        frame = front.astype(f32)
        if frame.shape[:2] != (h, w):
            frame = jax.image.resize(frame, (h, w, config.channels), "linear")
        buf, n = _push(carry.frames, carry.num_frames, frame)
        buf, n = jnp.where(record, buf, carry.frames), jnp.where(record, n, carry.num_frames)
        mask = jnp.arange(frames) < n
        act_p, obj_p = (x[0] for x in perceiver.intention_probs(config, perceiver.apply(params, config, buf[None], mask[None])))
        # Only a new frame adds a prediction: repeated steps on the same buffer would
        # otherwise crowd the history with one prediction.
        act_h, m = _push(carry.activity_history, carry.num_predictions, act_p)
        obj_h, _ = _push(carry.object_history, carry.num_predictions, obj_p)
        act_h = jnp.where(record, act_h, carry.activity_history)
        obj_h = jnp.where(record, obj_h, carry.object_history)
        m = jnp.where(record, m, carry.num_predictions)
        valid = (jnp.arange(history) < m)[None]
        act = perceiver.lowest_entropy_average(act_h[None], valid, top_k)[0]
        obj = perceiver.lowest_entropy_average(obj_h[None], valid, top_k)[0]
        return act, obj, IntentionCarry(buf, n, act_h, obj_h, m, carry.t + 1)

    return IntentionPredictor(config, frame_stride, init, step)


def load_intention_predictor(
    run_dir: str | Path, frame_stride: int | None = None, history: int = 16, top_k: int = 5
) -> IntentionPredictor:
    """The latest checkpoint of a `conav train intention` run as a predictor. `frame_stride`
    defaults to the training frames' median spacing in steps (rounded). FileNotFoundError /
    ValueError naming the run when it is missing or of another kind."""
    ckpt = runs.load_run(run_dir, runs.INTENTION)
    cfg = dict(ckpt.config["model"])
    cfg["image_hw"] = tuple(cfg["image_hw"])
    cfg.setdefault("activity_a_head", False)  # runs from before the A head had none
    data = ckpt.config["data"]
    stride = frame_stride if frame_stride is not None else max(1, int(round(data["frame_spacing_steps"])))
    return make_intention_predictor(ckpt.params, PerceiverConfig(**cfg), data["frames"], stride, history, top_k)


class TrajectoryPredictor(NamedTuple):
    """A trained trajectory model, params closed over. `predict(history (..., k, 2) m) ->
    (..., horizon, 2) m` in the same frame (e.g. the robot's); jittable and vmappable."""

    config: TrajectoryConfig
    predict: Callable[[jax.Array], jax.Array]


def load_trajectory_predictor(run_dir: str | Path) -> TrajectoryPredictor:
    """The latest checkpoint of a `conav train trajectory` run as a predictor (FileNotFoundError /
    ValueError naming the run when it is missing or of another kind)."""
    ckpt = runs.load_run(run_dir, runs.TRAJECTORY)
    config = TrajectoryConfig(**ckpt.config["model"])
    params = ckpt.params

    def predict(history: jax.Array) -> jax.Array:
        if history.shape[-2:] != (config.history, 2):
            raise ValueError(f"history must be (..., {config.history}, 2), got {history.shape}")
        last = history[..., -1:, :]
        # Trained on histories relative to their last point: predict there, shift back.
        return traj_model.apply(params, config, history - last) + last

    return TrajectoryPredictor(config, predict)
