"""The intention and trajectory predictors of trained runs, as agents use them while acting.

`load_intention_predictor(run)` turns a `conav train intention` run into a per-env, per-step
predictor: the observation's panorama, cropped around the human (`obs["rgbd"]` at
`obs["human_pos"]`, envs.human_crop; `intention_frame`, which also makes the training frames),
goes into a frame ring buffer every `frame_stride` steps, the Perceiver reads it on those
steps, and the output is the mean of the lowest-entropy recent predictions (paper sec. 4.2). `load_trajectory_predictor
(run)` turns a `conav train trajectory` run into `predict(history) -> next positions`. Both
close over their parameters, are jittable and vmappable, and run inside the agents' `act`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from conav_jax import runs
from conav_jax.config import TaskConfig
from conav_jax.models import perceiver
from conav_jax.models import trajectory as traj_model
from conav_jax.models.perceiver import PerceiverConfig
from conav_jax.models.policy import categories_in_view
from conav_jax.models.trajectory import TrajectoryConfig
from conav_jax.envs.agents.base import ORACLE_SEGMENTATION
from conav_jax.envs.config import materials_of_run
from conav_jax.envs.human_crop import human_crop
from conav_jax.envs.panorama import front_view

# What a Perceiver frame shows: "human", the panorama cropped around the human at its own
# resolution; "front", the panorama's front quarter resized to the frame (runs from before
# the crop; a run's config without a view is one of those).
VIEWS = ("human", "front")


# Frames per episode an intention run is trained on and its predictor keeps (the Perceiver's
# sequence), spread evenly over activity A.
DEFAULT_FRAMES = 16


def frame_spacing(t_walk_start: np.ndarray, frames: int) -> float:
    """Median steps between consecutive training frames of episodes whose activity A lasts
    `t_walk_start` steps, `frames` per episode: a predictor's default stride."""
    length = np.maximum(np.asarray(t_walk_start), 1)
    return float(np.median(np.maximum((length - 1) / max(frames - 1, 1), 1.0)))


def spacing_stride(spacing_steps: float) -> int:
    """The frame stride (steps, >= 1) of a frame spacing."""
    return max(1, int(round(spacing_steps)))


class FrameSpec(NamedTuple):
    """How a run's frames were made from the panorama, which the predictor repeats."""

    view: str  # one of VIEWS
    resolution: tuple[int, int]  # (H, W) of the panoramas the run was trained on
    camera_height_m: float = TaskConfig.camera_height_m  # where the crop's rows look
    materials: str = "flat"  # SensorConfig.materials of the panoramas the run was trained on


def intention_frame(spec: FrameSpec, config: PerceiverConfig, rgbd: jax.Array, human_pos: jax.Array) -> jax.Array:
    """One Perceiver frame `(h, w, 4)` uint8 (perceiver.encode_frames) from a panorama `rgbd
    (H, W, 4)` and the human's position `(2,)` m in the robot frame: what training stored and
    what the predictor records. ValueError when the panorama is not the resolution the run was
    trained on for the "human" view (a crop of another resolution shows the human at another
    size), or when the shapes do not fit (envs.human_crop)."""
    if spec.view not in VIEWS:
        raise ValueError(f"unknown intention view {spec.view!r}; expected one of {VIEWS}")
    if rgbd.ndim != 3 or rgbd.shape[-1] != config.channels:
        raise ValueError(f"rgbd must be (H, W, {config.channels}), got {rgbd.shape}")
    h, w = config.image_hw
    if spec.view == "front":
        frame = front_view(rgbd).astype(jnp.float32)
        if frame.shape[:2] != (h, w):
            frame = jax.image.resize(frame, (h, w, config.channels), "linear")
    else:
        if tuple(rgbd.shape[:2]) != tuple(spec.resolution):
            sh, sw = spec.resolution
            raise ValueError(
                f"the intention predictor crops {h}x{w} frames from {sh}x{sw} panoramas (its training "
                f"resolution) but got {rgbd.shape[0]}x{rgbd.shape[1]}; render the env with "
                f"SensorConfig(resolution=({sh}, {sw}))")
        frame = human_crop(rgbd.astype(jnp.float32), human_pos, (h, w), spec.camera_height_m)
    return perceiver.encode_frames(frame, config.max_depth_m)


class IntentionCarry(NamedTuple):
    """Per-env state of the predictor (arrays; vmap it for a batch of envs)."""

    frames: jax.Array  # (F, h, w, 4) uint8 (perceiver.encode_frames): the last F recorded frames, oldest first
    num_frames: jax.Array  # int32: frames recorded so far, capped at F
    activity_history: jax.Array  # (P, num_activities) the last P predictions, oldest first
    object_history: jax.Array  # (P, num_objects)
    num_predictions: jax.Array  # int32: predictions recorded so far, capped at P
    t: jax.Array  # int32: step() calls so far
    # bool: a recorded observation's human position held NaN. Its crop is in the buffer as some
    # uint8 value, so every later output is NaN: no prediction from a made-up view.
    bad_input: jax.Array
    # (num_objects,) bool: the object categories the recorded panoramas have shown (only with
    # PerceiverConfig.seen_objects; else it stays all False)
    objects_seen: jax.Array


class IntentionPredictor(NamedTuple):
    """A trained Perceiver with its parameters closed over, for one env (jittable, vmappable).

    `init() -> carry`; `step(carry, obs) -> (activity_probs (107,), object_probs (51,), carry)`
    with `obs` the env's observation of one env: it reads `obs["rgbd"]` (H, W, 4) and
    `obs["human_pos"]` (2,) (`intention_frame`). `privileged`: what it reads that a robot with
    the paper's sensors would not have (envs.agents.base), for the agents using it to list."""

    config: PerceiverConfig
    frame_stride: int
    spec: FrameSpec
    init: Callable[[], IntentionCarry]
    step: Callable[[IntentionCarry, Mapping[str, jax.Array]], tuple[jax.Array, jax.Array, IntentionCarry]]
    privileged: tuple[str, ...] = ()


def _push(buffer: jax.Array, count: jax.Array, item: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Append `item` to a ring buffer kept oldest-first: fill slots 0.., then shift left."""
    size = buffer.shape[0]
    full = count >= size
    buffer = jnp.where(full, jnp.roll(buffer, -1, axis=0), buffer)
    return buffer.at[jnp.minimum(count, size - 1)].set(item), jnp.minimum(count + 1, size)


def _frame_recorder(config: PerceiverConfig, spec: FrameSpec, frame_stride: int, unseen_weights: dict | None = None):
    """`record_frame(learned, record, rgbd, segmentation, human_pos, frames, num_frames, objects_seen)
    -> (frames, num_frames, objects_seen, activity_probs, object_probs)` for one env, `learned`
    being what the run learned, one for every lane (its Perceiver parameters, and its P(B | A)
    or None: perceiver.intention_routes): where `record`, the
    observation's frame (`intention_frame`) pushed into the buffer, with
    PerceiverConfig.seen_objects the categories the panorama shows (its `segmentation`) added to
    `objects_seen`, and
    the Perceiver's output on them; where not, the buffer and the set as they were and zeros
    (the caller keeps its history then). An env records one step in
    `frame_stride`, so most calls skip the crop, the push and the Perceiver: alone by `lax.cond`,
    and under vmap (where a per-lane `cond` would run both branches on every lane) by running
    them only on the recording lanes, gathered in chunks. Each lane's output is what the
    Perceiver gives it in a full batch, to float rounding."""
    shapes = (config.num_activities, config.num_objects)

    # Runs on the arrays (N, ...) of the lanes that record.
    def record_lanes(learned, rgbd, segmentation, human_pos, frames, num_frames, objects_seen):
        params, transition = learned
        new = jax.vmap(lambda r, p: intention_frame(spec, config, r, p))(rgbd, human_pos)
        frames, num_frames = jax.vmap(_push)(frames, num_frames, new)
        mask = jnp.arange(frames.shape[1]) < num_frames[:, None]
        restrict = None
        if config.seen_objects:
            objects_seen = objects_seen | jax.vmap(categories_in_view)(segmentation)
            restrict = objects_seen
        probs = perceiver.intention_probs(config, perceiver.apply(params, config, frames, mask), transition, restrict,
                                          unseen_weights)
        return (frames, num_frames, objects_seen, *probs)

    # What the run learned is an argument, not something the batching rule closes over: the
    # rule's Python runs again when the rollout is vmapped, and arrays it closed over would enter
    # the compiled program as constants even where the agent's weights are its arguments
    # (envs.agents.lift).
    @jax.custom_batching.custom_vmap
    def record_frame(learned, record, rgbd, segmentation, human_pos, frames, num_frames, objects_seen):
        def recorded():
            args = (rgbd, segmentation, human_pos, frames, num_frames, objects_seen)
            return tuple(x[0] for x in record_lanes(learned, *(x[None] for x in args)))
        return jax.lax.cond(record, recorded,
                            lambda: (frames, num_frames, objects_seen, *(jnp.zeros(n, jnp.float32) for n in shapes)))

    @record_frame.def_vmap
    def _batched(axis_size, in_batched, learned, record, *args):
        if any(jax.tree.leaves(in_batched[0])):
            raise ValueError("the intention predictor runs one set of parameters on every lane")
        record, *args = (x if batched else jnp.broadcast_to(x, (axis_size, *x.shape))
                         for x, batched in zip((record, *args), in_batched[1:]))
        rgbd, segmentation, human_pos, frames, num_frames, objects_seen = args
        # Lanes drift apart in step once episodes refill, so a step records on about
        # axis_size / frame_stride lanes: chunks twice that size take one pass on most steps.
        chunk = min(axis_size, 2 * -(-axis_size // frame_stride))
        passes = -(-axis_size // chunk)
        lanes = jnp.nonzero(record, size=passes * chunk, fill_value=axis_size)[0]  # recording lanes first
        count = jnp.sum(record)

        def body(carry):
            i, outs = carry
            idx = jax.lax.dynamic_slice(lanes, (i * chunk,), (chunk,))
            take = jnp.minimum(idx, axis_size - 1)
            done = record_lanes(learned, rgbd[take], segmentation[take], human_pos[take], frames[take],
                                num_frames[take], objects_seen[take])
            # Padding lanes point past the batch: their rows are dropped.
            return i + 1, tuple(out.at[idx].set(x, mode="drop") for out, x in zip(outs, done))

        outs = (frames, num_frames, objects_seen, *(jnp.zeros((axis_size, n), jnp.float32) for n in shapes))
        _, outs = jax.lax.while_loop(lambda c: c[0] * chunk < count, body, (jnp.zeros((), jnp.int32), outs))
        return outs, (True,) * len(outs)

    return record_frame


def make_intention_predictor(
    params, config: PerceiverConfig, frames: int, spec: FrameSpec, frame_stride: int = 1, history: int = 16,
    top_k: int = 5, transition: np.ndarray | None = None, unseen_weights: dict | None = None,
) -> IntentionPredictor:
    """A predictor that records a frame (`intention_frame` by `spec`) every `frame_stride`
    calls (training frames were that far apart), keeps the last `frames`, runs the Perceiver
    on them and returns the mean of the `top_k` lowest-entropy of the last `history`
    predictions (paper sec. 4.2). `transition`: the P(B | A) of its graph route
    (perceiver.intention_routes). With `config.seen_objects` it keeps the object categories its
    recorded panoramas show and weighs the activities of the others by `unseen_weights`
    (perceiver.seen_object_weights; listed as privileged: oracle segmentation)."""
    h, w = config.image_hw
    f32 = jnp.float32
    record_frame = _frame_recorder(config, spec, frame_stride, unseen_weights)

    def init() -> IntentionCarry:
        zero = jnp.zeros((), jnp.int32)
        return IntentionCarry(
            jnp.zeros((frames, h, w, config.channels), jnp.uint8), zero,
            jnp.zeros((history, config.num_activities), f32), jnp.zeros((history, config.num_objects), f32),
            zero, zero, jnp.zeros((), bool), jnp.zeros(config.num_objects, bool),
        )

    def step(carry: IntentionCarry, obs: Mapping[str, jax.Array]):
        if not isinstance(obs, Mapping) or "rgbd" not in obs or "human_pos" not in obs:
            raise ValueError("the intention predictor steps on the env's observation of one env, a mapping "
                             "with 'rgbd' (H, W, 4) and 'human_pos' (2,)")
        rgbd, human_pos = jnp.asarray(obs["rgbd"]), jnp.asarray(obs["human_pos"])
        # Bad input raises here, whether or not this step records: shapes always, a non-finite
        # position outside jit (under jit it turns the outputs NaN, below).
        jax.eval_shape(partial(intention_frame, spec, config), rgbd, human_pos)
        if not isinstance(human_pos, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(human_pos))):
            raise ValueError(f"human_pos must be finite, got {np.asarray(human_pos)}")
        record = carry.t % frame_stride == 0
        bad = carry.bad_input | (record & ~jnp.all(jnp.isfinite(human_pos)))
        if config.seen_objects and "segmentation" not in obs:
            raise ValueError("an intention predictor with seen_objects reads the observation's 'segmentation' "
                             "(each pixel's object category)")
        # Without seen_objects no category is read: a one-pixel stand-in keeps the signature.
        segmentation = jnp.asarray(obs["segmentation"]) if config.seen_objects else jnp.full((1, 1), -1, jnp.int32)
        buf, n, seen, act_p, obj_p = record_frame((params, transition), record, rgbd, segmentation, human_pos,
                                                  carry.frames, carry.num_frames, carry.objects_seen)
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
        act, obj = jnp.where(bad, jnp.nan, act), jnp.where(bad, jnp.nan, obj)
        return act, obj, IntentionCarry(buf, n, act_h, obj_h, m, carry.t + 1, bad, seen)

    privileged = (ORACLE_SEGMENTATION,) if config.seen_objects else ()
    return IntentionPredictor(config, frame_stride, spec, init, step, privileged)


def frame_spec_from_config(data: dict) -> FrameSpec:
    """The FrameSpec of a run's "data" config; runs from before the crop have no "view" and
    read front views, runs from before materials were rendered "flat"."""
    view = data.get("view", "front")
    if view not in VIEWS:
        raise ValueError(f"intention run with unknown view {view!r}; this version reads {VIEWS}")
    return FrameSpec(view, tuple(data["resolution"]), float(data.get("camera_height_m", TaskConfig.camera_height_m)),
                     materials_of_run({"data": data}))


def perceiver_config_from_run(model: dict) -> PerceiverConfig:
    """The PerceiverConfig of an intention run's JSON "model" (lists back to tuples; runs from
    before the A head had none)."""
    return PerceiverConfig(**{"activity_a_head": False,
                              **{k: tuple(v) if isinstance(v, list) else v for k, v in model.items()}})


def load_intention_predictor(
    run_dir: str | Path, frame_stride: int | None = None, history: int = 16, top_k: int = 5
) -> IntentionPredictor:
    """The latest checkpoint of a `conav train intention` run as a predictor. `frame_stride`
    defaults to the training frames' median spacing in steps (rounded). FileNotFoundError /
    ValueError naming the run when it is missing or of another kind."""
    ckpt = runs.load_run(run_dir, runs.INTENTION)
    data = ckpt.config["data"]
    stride = frame_stride if frame_stride is not None else spacing_stride(data["frame_spacing_steps"])
    model = perceiver_config_from_run(ckpt.config["model"])
    # P(B | A) counted on the run's train split; runs written before the counts step through
    # the graph's links, uniform.
    counts = data.get("transition_counts")
    transition = None if counts is None else perceiver.transition_from_counts(model, counts)
    weights = data.get("seen_object_weights")
    if model.seen_objects:
        if weights is None:
            raise ValueError(f"intention run {run_dir} weighs seen objects but records no seen_object_weights")
        try:
            weights = perceiver.check_unseen_weights(weights)
        except ValueError as e:
            raise ValueError(f"intention run {run_dir}: seen_object_weights: {e}") from None
    return make_intention_predictor(ckpt.params, model, data["frames"], frame_spec_from_config(data),
                                    stride, history, top_k, transition, weights)


class TrajectoryPredictor(NamedTuple):
    """A trained trajectory model, params closed over. `predict(history (..., k, 2) m) ->
    (..., horizon, 2) m` in the same frame (e.g. the robot's); jittable and vmappable."""

    config: TrajectoryConfig
    predict: Callable[[jax.Array], jax.Array]


def load_trajectory_predictor(run_dir: str | Path) -> TrajectoryPredictor:
    """The latest checkpoint of a `conav train trajectory` run as a predictor (FileNotFoundError /
    ValueError naming the run when it is missing or of another kind)."""
    ckpt = runs.load_run(run_dir, runs.TRAJECTORY)
    return trajectory_predictor(ckpt.params, TrajectoryConfig(**ckpt.config["model"]))


def trajectory_predictor(params, config: TrajectoryConfig) -> TrajectoryPredictor:
    """The trajectory model of these parameters as a predictor (a run's, or `init`'s)."""

    def predict(history: jax.Array) -> jax.Array:
        if history.shape[-2:] != (config.history, 2):
            raise ValueError(f"history must be (..., {config.history}, 2), got {history.shape}")
        last = history[..., -1:, :]
        # Trained on histories relative to their last point: predict there, shift back.
        return traj_model.apply(params, config, history - last) + last

    return TrajectoryPredictor(config, predict)
