"""Training the long-term intention predictor (paper sec. 4.1).

The train env and a validation env (`train_intention`; `train_intention_from_data` builds them
from a dataset directory) -> each env's sensor renders, from each robot start pose, F panoramas
(112x448 by default) during activity A, each cropped around the human where the robot sees it
(envs.agents.predictors.intention_frame: the crop the predictor takes at every step) and stored
as uint8 (one jitted call, rendered in chunks) -> Perceiver trained on a random prefix of the
frames, cross-entropy on activity B (107), object B (51) and the watched activity A -> top-1/
top-5 on the validation split (minival by default: the reported val split stays unseen) by
route, the predictor's output and the direct heads with and without the generator's activity
graph (a structural prior), against the "most frequent B given A" prior and chance -> a run
that envs.agents.predictors loads as the per-step predictor agents act with.
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
from conav_jax.data.episodes import read_manifest
from conav_jax.geometry import to_frame, wrap_angle_np
from conav_jax.models import perceiver
from conav_jax.models.perceiver import PerceiverConfig
from conav_jax.models.policy import categories_in_view
from conav_jax.nav.navigation import line_of_sight
from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.agents.predictors import (
    DEFAULT_FRAMES,
    VIEWS,
    FrameSpec,
    frame_spacing,
    intention_frame,
    perceiver_config_from_run,
)
from conav_jax.envs.human_crop import human_crop
from conav_jax.envs.panorama import front_view
from conav_jax.envs.rollout import jit_with_bank
from conav_jax.train.env_checks import check_same_data, check_sensor, check_split
from conav_jax.train.loop import TrainConfig, TrainResult, train

# The predictor's schedule unless a run gives its own (`conav train intention`'s defaults).
INTENTION_TRAIN = TrainConfig(steps=6000, batch=64, lr=3e-4, weight_decay=0.01)

KIND = runs.INTENTION


@dataclasses.dataclass(frozen=True)
class IntentionDataConfig:
    """How the frame sequences are rendered."""

    # Panorama (H, W) rendered, the sensor's default. The "human" view crops the model's
    # image_hw from it at this resolution, so the agents' env must render it too (the
    # predictor checks); "front" resizes the front quarter to image_hw (any resolution).
    resolution: tuple[int, int] = SensorConfig.resolution
    # What the panoramas' RGB shows (SensorConfig.materials); the predictor's env must render it too.
    materials: str = SensorConfig.materials
    frames: int = DEFAULT_FRAMES  # F: frames per episode, spread evenly over activity A
    # What a frame shows (envs.agents.predictors.VIEWS): "human", the panorama cropped around
    # the human; "front", the front quarter (the input before the crop, for comparison).
    view: str = "human"
    # Robot poses each training episode is rendered from: its start pose, then viewpoints - 1
    # drawn as the generator draws start poses (`robot_poses`). The robot watches the human
    # from wherever it drives, and 2,000 episodes of one viewpoint each leave the Perceiver
    # memorising the training scenes. Validation always uses the start pose alone. On the small
    # preset's minival, 4 viewpoints named the watched activity A 0.42 top-1 (1 viewpoint:
    # 0.28; 8 and 16: 0.37 and 0.41) after 3,000 updates, and 0.46 after 6,000.
    viewpoints: int = 4
    # Mirror each training sample left-right with probability 1/2 (a fresh draw every update;
    # an activity means the same done to either side). Validation frames are never mirrored.
    mirror: bool = False
    # Recolour each training sample (`recolour_frames`: its RGB channels permuted and scaled, one
    # draw for all its frames, a fresh one every update). Instance colours come from one palette
    # every category shares, so a predictor can memorise which colour marks which object in the
    # training scenes and learn nothing that carries to new ones; recoloured, it must read shape,
    # depth and motion. Depth is never changed; validation frames are never recoloured.
    recolour: bool = False

    def __post_init__(self):
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")
        if self.viewpoints < 1:
            raise ValueError(f"viewpoints must be >= 1, got {self.viewpoints}")
        if self.view not in VIEWS:
            raise ValueError(f"view must be one of {VIEWS}, got {self.view!r}")


# -- dataset -------------------------------------------------------------------------------------


def activity_a_steps(t_walk_start: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Steps `(N, F)` spread evenly over each episode's activity A, `[0, t_walk_start)`, and the
    number of distinct ones `(N,)` (= F unless activity A has fewer steps; the rest repeat
    the last step and are masked in training)."""
    length = np.maximum(np.asarray(t_walk_start, np.int64), 1)
    num = np.minimum(length, frames)
    pos = np.arange(frames)[None, :]
    # Even spacing over [0, length - 1] using num points; positions past num repeat the last.
    steps = np.round(np.minimum(pos, num[:, None] - 1) * (length[:, None] - 1) / np.maximum(num[:, None] - 1, 1))
    return steps.astype(np.int32), num.astype(np.int32)


def frame_spec(env: ConavEnv, data: IntentionDataConfig) -> FrameSpec:
    """How `env`'s panoramas become frames: the view, the sensor's resolution and its camera
    height (the predictor repeats it from the run's config)."""
    sensor = env.config.sensor
    return FrameSpec(data.view, sensor.resolution, float(env.task.camera_height_m))


# Keeps the viewpoints' draws apart from every other seeded draw.
_VIEWPOINT_SALT = 0x71E3
# Viewpoints face the human up to this far off, as the generator turns start poses (the crop
# follows the human wherever it is; the front view needs it ahead).
_VIEWPOINT_YAW_JITTER_RAD = 0.25


def robot_poses(env: ConavEnv, viewpoints: int, tries: int = 64) -> np.ndarray:
    """Robot poses `(N, viewpoints, 3)` (x m, y m, yaw rad) to render each episode from: its
    start pose, then `viewpoints - 1` drawn per (episode, viewpoint) as the generator draws
    start poses: a free cell at the task's start distance from the human's activity-A spot
    with a clear line of sight, facing the human give or take 0.25 rad; the start pose again
    where `tries` draws find none."""
    eps = env.split.episodes
    starts = np.asarray(eps["robot_start"], np.float32)
    out = np.repeat(starts[:, None], viewpoints, axis=1)
    lo, hi = env.task.robot_start_distance_m
    for e in range(len(starts)):
        grid = env.split.navs[int(eps["scene_index"][e])].grid
        human = np.asarray(eps["root_xy"][e, 0], np.float64)
        for v in range(1, viewpoints):
            rng = np.random.default_rng(np.random.SeedSequence([_VIEWPOINT_SALT, e, v]))
            for _ in range(tries):
                r, a = rng.uniform(lo, hi), rng.uniform(-np.pi, np.pi)
                xy = human + r * np.array([np.cos(a), np.sin(a)])
                if grid.is_free(xy) and line_of_sight(grid, xy, human):
                    jitter = rng.uniform(-_VIEWPOINT_YAW_JITTER_RAD, _VIEWPOINT_YAW_JITTER_RAD)
                    out[e, v] = (xy[0], xy[1], wrap_angle_np(a + np.pi + jitter))  # facing the human
                    break
    return out


def human_positions(env: ConavEnv, episodes: np.ndarray, steps: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """The human's root `(M, 2)` m at each step in the frame of each robot pose `(M, 3)`, as
    the env observes it (`obs["human_pos"]`). ValueError naming the episodes whose positions
    are not finite: a crop around NaN is no frame to learn from."""
    b = env.bank
    root = np.asarray(b.root_xy)[episodes, np.minimum(steps, b.max_steps - 1)]
    pos = np.asarray(to_frame(root, poses[:, :2], poses[:, 2]), np.float32)
    bad = ~np.isfinite(pos).all(axis=-1)
    if bad.any():
        raise ValueError(f"human positions are not finite in episodes {sorted(set(episodes[bad].tolist()))[:10]}")
    return pos


def make_renderer(env: ConavEnv, model: PerceiverConfig, spec: FrameSpec, chunk: int,
                  compiler_options: dict | None = None):
    """A jitted `render(episodes (M,), steps (M,), poses (M, 3), human_pos (M, 2)) -> (frames
    (M, h, w, 4) uint8, human_pixels (M,) int32, human_pixels_sensor (M,) int32, objects_seen
    (M, num_objects) bool)`: the env sensor's panorama from the robot pose with the human posed
    at that step of the episode, made into a frame by `intention_frame` (the predictor's own),
    the sensor pixels showing the human inside the frame's view and in the whole panorama, and
    the object categories the whole panorama shows (`categories_in_view`, what the predictor
    keeps with PerceiverConfig.seen_objects). `chunk` frames at a time."""
    human_start = env.layout.human_start
    h, w = model.image_hw

    def one(episode, t, pose, pos):
        rgbd, ids = env.render_at(episode, pose, t)
        frame = intention_frame(spec, model, rgbd, pos)
        human = (ids >= human_start).astype(jnp.float32)[..., None]
        # The human's pixels in the same view (a crop holds sensor pixels; the front view's
        # are counted before its resize).
        seen = front_view(human) if spec.view == "front" else human_crop(human, pos, (h, w), spec.camera_height_m)
        return (frame, jnp.sum(seen, dtype=jnp.int32), jnp.sum(human, dtype=jnp.int32),
                categories_in_view(env.segmentation(ids, episode)))

    def render(episodes, steps, poses, pos):
        return jax.lax.map(lambda x: one(*x), (episodes, steps, poses, pos), batch_size=chunk)

    # The episode bank as an argument: as constants, the paper split's made a 6 GB executable.
    return jit_with_bank(env, render, compiler_options=compiler_options)


def render_split(
    env: ConavEnv,
    model: PerceiverConfig,
    data: IntentionDataConfig,
    chunk: int = 256,
    compiler_options: dict | None = None,
    viewpoints: int | None = None,
) -> dict:
    """The intention dataset of every episode of `env`'s bank from `viewpoints` robot poses each
    (default `data.viewpoints`; 1: the start pose), rendered `chunk` frames at a time. N
    episodes give M = N x viewpoints samples, viewpoints of one episode next to each other:
    `frames (M, F, h, w, 4)` uint8 (perceiver.encode_frames of each `intention_frame`),
    `num_frames (M,)` int32, `activity (M,)`, `object (M,)` int32 labels (activity B, object
    B), `activity_a (M,)`, `human_pos (M, F, 2)` m (robot frame), and `human_pixels (M, F)` /
    `human_pixels_sensor (M, F)` int32, the sensor's pixels showing the human inside the
    frame's view / in the whole panorama, and `objects_seen (M, F, num_objects)` bool, the
    object categories each frame's whole panorama shows."""
    eps = env.split.episodes
    views = data.viewpoints if viewpoints is None else viewpoints
    steps, num = activity_a_steps(eps["t_walk_start"], data.frames)
    n, f = steps.shape
    poses = robot_poses(env, views)  # (N, V, 3)
    episodes = np.repeat(np.arange(n, dtype=np.int32), views * f)
    steps = np.repeat(steps[:, None], views, axis=1).reshape(-1)
    poses = np.repeat(poses.reshape(n * views, 1, 3), f, axis=1).reshape(-1, 3)
    pos = human_positions(env, episodes, steps, poses)
    render = make_renderer(env, model, frame_spec(env, data), chunk, compiler_options)
    frames, human, human_sensor, objects_seen = render(*map(jnp.asarray, (episodes, steps, poses, pos)))
    m = n * views
    per_sample = lambda key: jnp.asarray(np.repeat(np.asarray(eps[key], np.int32), views))  # noqa: E731
    return {
        # uint8: a quarter of float32's memory (2,000 samples of 16 64x64 crops: 0.5 GB).
        "frames": frames.reshape(m, f, *frames.shape[1:]),
        "num_frames": jnp.asarray(np.repeat(num, views)),
        "activity": per_sample("activity_b"),
        "object": per_sample("object_b"),
        "activity_a": per_sample("activity_a"),
        "human_pos": jnp.asarray(pos.reshape(m, f, 2)),
        "human_pixels": human.reshape(m, f),
        "human_pixels_sensor": human_sensor.reshape(m, f),
        "objects_seen": objects_seen.reshape(m, f, -1),
    }


def make_env(data_dir: str | Path, split: str, data: IntentionDataConfig) -> ConavEnv:
    """The env of one split with the sensor resolution and materials the frames are rendered at."""
    h, w = data.resolution
    return ConavEnv(data_dir, split, EnvConfig(sensor=SensorConfig(resolution=(h, w), materials=data.materials)))


# -- baselines and metrics -----------------------------------------------------------------------


def prior_scores(given_a: np.ndarray, target_b: np.ndarray, num_a: int, num_b: int) -> np.ndarray:
    """The "most frequent B given A" baseline as scores `(num_a, num_b)`: counts of B after A
    in the training labels, ties (and A never seen) broken by B's overall frequency, then by id."""
    counts = np.zeros((num_a, num_b), np.float64)
    np.add.at(counts, (np.asarray(given_a), np.asarray(target_b)), 1.0)
    overall = counts.sum(0)
    # Tie-breakers strictly smaller than one count: overall frequency, then lower id.
    tie = overall / (overall.sum() + 1.0) + (num_b - np.arange(num_b)) / (num_b * (overall.sum() + 1.0) ** 2)
    return counts + tie[None, :]


def topk_accuracy(scores: np.ndarray, labels: np.ndarray, k: int) -> float:
    """Share of rows of `scores (M, C)` whose label is among its k highest scores."""
    top = np.argsort(-np.asarray(scores), axis=-1, kind="stable")[:, :k]
    return float(np.mean(np.any(top == np.asarray(labels)[:, None], axis=-1)))


def baseline_metrics(train_labels: dict, val_labels: dict, model: PerceiverConfig) -> dict:
    """Prior and chance top-1/top-5 for activity and object on the val labels."""
    out = {}
    for head, num in (("activity", model.num_activities), ("object", model.num_objects)):
        scores = prior_scores(train_labels["activity_a"], train_labels[head], model.num_activities, num)
        val_scores = scores[np.asarray(val_labels["activity_a"])]
        for k in (1, 5):
            out[f"prior_{head}_top{k}"] = topk_accuracy(val_scores, val_labels[head], k)
            out[f"chance_{head}_top{k}"] = min(k, num) / num
    return out


# -- training ------------------------------------------------------------------------------------


def same_object_top1(config: PerceiverConfig, scores: np.ndarray, activity: np.ndarray) -> float:
    """Share of samples whose top-1 activity under `scores (N, num_activities)` is bound to the
    same object category as `activity (N,)`, the true one. Each object serves about three
    activities: for the watched activity A this separates not finding the object the human uses
    from not telling its activities' motions apart."""
    object_of = perceiver.activity_objects(config)
    return float(np.mean(object_of[np.argmax(scores, axis=1)] == object_of[activity]))


def _cross_entropy(logits: jax.Array, labels: jax.Array) -> jax.Array:
    logp = jax.nn.log_softmax(logits, axis=-1)
    return -jnp.mean(jnp.take_along_axis(logp, labels[:, None], axis=-1))


# Per-channel gains of `recolour_frames`, drawn uniformly in this range.
RECOLOUR_GAIN_RANGE = (0.6, 1.4)


def recolour_frames(frames: jax.Array, key: jax.Array) -> jax.Array:
    """`frames (B, F, h, w, 4)` (uint8 as `perceiver.encode_frames` stores them, or float: RGB in
    [0, 1], depth in metres) with each sample's RGB channels permuted (one of the six orders) and
    scaled by gains in RECOLOUR_GAIN_RANGE, clipped to [0, 1], one draw per sample for all its
    frames; depth unchanged; the dtype kept (uint8 rounded back to its 255 steps)."""
    b = frames.shape[0]
    k_perm, k_gain = jax.random.split(key)
    order = jax.vmap(lambda k: jax.random.permutation(k, 3))(jax.random.split(k_perm, b))  # (B, 3)
    gain = jax.random.uniform(k_gain, (b, 3), minval=RECOLOUR_GAIN_RANGE[0], maxval=RECOLOUR_GAIN_RANGE[1])
    is_uint8 = frames.dtype == jnp.uint8
    rgb = frames[..., :3].astype(jnp.float32) / (255.0 if is_uint8 else 1.0)
    rgb = jnp.take_along_axis(rgb, order[:, None, None, None, :], axis=-1) * gain[:, None, None, None, :]
    rgb = jnp.clip(rgb, 0.0, 1.0)
    if is_uint8:
        rgb = jnp.round(rgb * 255.0).astype(jnp.uint8)
    return jnp.concatenate([rgb.astype(frames.dtype), frames[..., 3:]], axis=-1)


def intention_loss(params, config: PerceiverConfig, batch: dict, key: jax.Array, mirror: bool = False,
                   recolour: bool = False):
    """CE(activity B) + CE(object B) (+ CE(activity A) with the A head); each sample sees a
    random prefix of 1..num_frames frames (the paper: the robot may have watched for any time);
    with `mirror`, its frames mirrored left-right with probability 1/2; with `recolour`, its
    frames recoloured (`recolour_frames`). Aux: each CE."""
    frames = batch["frames"]  # uint8 as rendered (or float): perceiver.apply reads either
    f = frames.shape[1]
    if mirror:
        key, k_mirror = jax.random.split(key)
        flip = jax.random.bernoulli(k_mirror, 0.5, (frames.shape[0],))
        frames = jnp.where(flip[:, None, None, None, None], frames[:, :, :, ::-1], frames)
    if recolour:
        key, k_colour = jax.random.split(key)
        frames = recolour_frames(frames, k_colour)
    seen = jax.random.randint(key, batch["num_frames"].shape, 1, batch["num_frames"] + 1)
    mask = jnp.arange(f)[None, :] < seen[:, None]
    logits = perceiver.apply(params, config, frames, mask)
    ce_a = _cross_entropy(logits.activity, batch["activity"])
    ce_o = _cross_entropy(logits.object, batch["object"])
    if logits.activity_a is None:
        return ce_a + ce_o, {"ce_activity": ce_a, "ce_object": ce_o}
    ce_watched = _cross_entropy(logits.activity_a, batch["activity_a"])
    return ce_a + ce_o + ce_watched, {"ce_activity": ce_a, "ce_object": ce_o, "ce_activity_a": ce_watched}


# Validation keys by route (perceiver.IntentionRoutes): the predictor's output has none; the
# direct heads alone and the A head through P(B | A) alone (a structural prior: the train
# split's counts of the generator's links) carry these suffixes.
ROUTE_SUFFIXES = {"mixed": "", "direct": "_direct", "graph_prior": "_generator_graph_prior"}


def make_val_fn(
    config: PerceiverConfig, val: dict, baselines: dict, batch: int = 256, compiler_options: dict | None = None,
    transition: np.ndarray | None = None, seen_objects: bool = False, unseen_weights: dict | None = None,
):
    """`val(params) -> dict`: top-1/top-5 of activity B and object B with every frame of activity
    A seen, by route (ROUTE_SUFFIXES): `activity_top1` etc. what the predictor outputs
    (`perceiver.intention_probs`), `activity_top1_direct` the direct heads without the graph
    prior, `activity_top1_generator_graph_prior` the A head through P(B | A) alone
    (`transition`, see perceiver.intention_routes), with `seen_objects` every route weighed by the
    object categories the sample's frames showed (`val["objects_seen"]`, `unseen_weights`);
    top-1/top-5 of the watched activity A
    with the A head, and how often its top-1 A uses the true A's object (`activity_a_object_top1`);
    plus the (constant) prior, chance and data figures of `baselines`."""
    f = val["frames"].shape[1]
    routes = [r for r in ROUTE_SUFFIXES if r != "graph_prior" or config.activity_a_head]

    def probs(params, frames, num, objects_seen):
        mask = jnp.arange(f)[None, :] < num[:, None]
        out = perceiver.apply(params, config, frames, mask)
        # What the robot has seen by the last frame the sample shows.
        seen = jnp.any(objects_seen & mask[..., None], axis=-2) if seen_objects else None
        by_route = perceiver.intention_routes(config, out, transition, seen, unseen_weights)._asdict()
        return {r: by_route[r] for r in routes}, out.activity_a

    # The data are arguments: closed over, they would be baked into the compiled program.
    def all_probs(params, frames, num, objects_seen):
        return jax.lax.map(lambda x: probs(params, *(v[None] for v in x)), (frames, num, objects_seen),
                           batch_size=batch)

    all_probs = jax.jit(all_probs, compiler_options=compiler_options)
    if seen_objects and "objects_seen" not in val:
        raise ValueError("seen_objects needs the samples' objects_seen (render_split's)")
    objects_seen = val["objects_seen"] if seen_objects else jnp.zeros(val["num_frames"].shape + (1, 1), bool)

    def run(params) -> dict:
        by_route, watched = jax.tree.map(lambda x: np.asarray(x)[:, 0],
                                         all_probs(params, val["frames"], val["num_frames"], objects_seen))
        out = {}
        for route, (act, obj) in by_route.items():
            for head, scores in (("activity", act), ("object", obj)):
                for k in (1, 5):
                    out[f"{head}_top{k}{ROUTE_SUFFIXES[route]}"] = topk_accuracy(scores, np.asarray(val[head]), k)
        if config.activity_a_head:
            for k in (1, 5):
                out[f"activity_a_top{k}"] = topk_accuracy(watched, np.asarray(val["activity_a"]), k)
            out["activity_a_object_top1"] = same_object_top1(config, watched, np.asarray(val["activity_a"]))
        return {**out, **baselines}

    return run


def run_config(model: PerceiverConfig, data: IntentionDataConfig, content_hash: str | None, spacing: float,
               camera_height_m: float, transition_counts: list[list[int]] | None = None,
               seen_object_weights: dict | None = None) -> dict:
    """The checkpoint's config: what a resumed run must share, and what the predictor needs
    (envs.agents.predictors.frame_spec_from_config reads the view, sensor and camera height;
    `transition_counts`, [A, B, count] of the train split's episodes, its P(B | A);
    `seen_object_weights`, perceiver.seen_object_weights of the train split, with
    PerceiverConfig.seen_objects)."""
    extra = {} if transition_counts is None else {"transition_counts": transition_counts}
    if seen_object_weights is not None:
        extra["seen_object_weights"] = seen_object_weights
    # `mirror`, `recolour` and `seen_objects` only where set: runs written before they existed
    # resume with the same config.
    data_fields = {k: v for k, v in dataclasses.asdict(data).items() if k not in ("mirror", "recolour") or v}
    model_fields = {k: v for k, v in dataclasses.asdict(model).items() if k != "seen_objects" or v}
    return {
        "kind": KIND,
        "model": model_fields,
        "data": {**data_fields, "content_hash": content_hash, "frame_spacing_steps": spacing,
                 "camera_height_m": camera_height_m, **extra},
        PROVENANCE_KEY: provenance(materials=data.materials, resolution=list(data.resolution), view=data.view),
    }


def data_metrics(val: dict) -> dict:
    """Sanity checks of the validation frames (a predictor cannot read an activity it never
    sees): the share of frames whose view shows the human, and the share of the human's sensor
    pixels that the views hold (the crop's rows leave the feet of a human closer than ~2 m)."""
    seen, total = np.asarray(val["human_pixels"]), np.asarray(val["human_pixels_sensor"])
    return {"val_frames_with_human": float(np.mean(seen > 0)),
            "val_human_pixels_in_view": float(seen.sum() / max(total.sum(), 1))}


def start_pose_weights(model: PerceiverConfig, samples: dict, viewpoints: int) -> dict:
    """perceiver.seen_object_weights of `render_split`'s samples from their episodes' start
    poses (the first of each `viewpoints`), every frame's objects together."""
    seen = np.asarray(samples["objects_seen"])[::viewpoints].any(axis=1)
    object_of = perceiver.activity_objects(model)
    object_a = object_of[np.asarray(samples["activity_a"])[::viewpoints]]
    return perceiver.seen_object_weights(seen, object_a, np.asarray(samples["object"])[::viewpoints])


def train_intention(
    train_env: ConavEnv,
    val_env: ConavEnv,
    run_dir: str | Path,
    cfg: TrainConfig,
    model: PerceiverConfig = PerceiverConfig(),
    data: IntentionDataConfig = IntentionDataConfig(),
    progress: bool = True,
    compiler_options: dict | None = None,
    mesh: Mesh | None = None,
) -> TrainResult:
    """Render `train_env` (the train split) and `val_env` (the split validated on, minival as
    `train_intention_from_data` builds it: hyper-parameters are chosen there, the reported val
    split stays unseen; its name is in every log record), both rendering `data.resolution` and
    `data.materials` (as `make_env` builds them) and from one dataset, whose content hash the
    run records; train on train, validate on val (`mesh`: data-parallel, see train.loop.train).
    ValueError naming the config field an env does not match, before anything is rendered."""
    check_split(train_env.split, "train", "train_env")
    check_same_data(train_env.split, val_env.split)
    for role, env in (("train_env", train_env), ("val_env", val_env)):
        check_sensor(env, role, data.resolution, "IntentionDataConfig.resolution", data.materials,
                     "IntentionDataConfig.materials")
    train_d = render_split(train_env, model, data, compiler_options=compiler_options)
    val_d = render_split(val_env, model, data, compiler_options=compiler_options, viewpoints=1)
    baselines = {**baseline_metrics(train_d, val_d, model), **data_metrics(val_d)}
    spacing = frame_spacing(train_env.split.episodes["t_walk_start"], data.frames)
    # P(B | A) of the graph route, counted on the train split's episodes.
    counts = perceiver.count_transitions(train_env.split.episodes["activity_a"], train_env.split.episodes["activity_b"])
    # The seen objects' odds, counted on the train split's start poses (as the robot starts).
    weights = start_pose_weights(model, train_d, data.viewpoints) if model.seen_objects else None
    config = run_config(model, data, train_env.split.content_hash, spacing, float(train_env.task.camera_height_m),
                        counts, weights)
    params = perceiver.init(jax.random.PRNGKey(cfg.seed), model)
    loss = lambda p, b, k: intention_loss(p, model, b, k, mirror=data.mirror, recolour=data.recolour)
    samples = {k: train_d[k] for k in ("frames", "num_frames", "activity", "object", "activity_a")}
    return train(
        run_dir, loss, params, samples, cfg, config,
        val_fn=make_val_fn(model, val_d, baselines, compiler_options=compiler_options,
                           transition=perceiver.transition_from_counts(model, counts),
                           seen_objects=model.seen_objects, unseen_weights=weights),
        progress=progress, compiler_options=compiler_options, mesh=mesh,
        log_extra={"val_split": val_env.split.name},
    )


def train_intention_from_data(data_dir: str | Path, run_dir: str | Path, cfg: TrainConfig,
                              model: PerceiverConfig = PerceiverConfig(), data: IntentionDataConfig = IntentionDataConfig(),
                              val_split: str = "minival", **kwargs) -> TrainResult:
    """`train_intention` on the train split and `val_split` (minival by default) of the dataset
    `data_dir`, each env rendering `data`'s resolution and materials (`make_env`); `kwargs` as
    `train_intention` takes them (progress, compiler_options, mesh)."""
    train_env, val_env = make_env(data_dir, "train", data), make_env(data_dir, val_split, data)
    return train_intention(train_env, val_env, run_dir, cfg, model, data, **kwargs)


def evaluate_run(run_dir: str | Path, data_dir: str | Path, split: str = "val",
                 compiler_options: dict | None = None) -> dict[str, dict]:
    """An intention run's accuracy on `split` of `data_dir` (its start viewpoint, every frame of
    activity A seen; make_val_fn's keys by route), with three graph routes: "counted", P(B | A)
    counted on the data's train split (what a run records and its predictor uses), "graph",
    the generator's links, uniform, and "counted_seen_objects", the counted P(B | A) with every
    route weighed by the object categories the robot's panoramas showed (what the predictor
    outputs with PerceiverConfig.seen_objects, whatever the run's setting; the run's recorded
    weights, else those of the train split's start poses, rendered here). FileNotFoundError /
    ValueError as runs.load_run, ValueError if the run was trained on other data (content hash)."""
    ckpt = runs.load_run(run_dir, runs.INTENTION)
    model = perceiver_config_from_run(ckpt.config["model"])
    names = {f.name for f in dataclasses.fields(IntentionDataConfig)}
    data = IntentionDataConfig(**{k: tuple(v) if isinstance(v, list) else v
                                  for k, v in ckpt.config["data"].items() if k in names})
    trained_on, here = ckpt.config["data"].get("content_hash"), read_manifest(data_dir).get("content_hash")
    if trained_on is not None and trained_on != here:
        raise ValueError(f"{run_dir} was trained on data with content hash {trained_on}; {data_dir} has {here}")
    train_env = make_env(data_dir, "train", data)
    train_eps = train_env.split.episodes
    env = make_env(data_dir, split, data)
    labels = render_split(env, model, data, compiler_options=compiler_options, viewpoints=1)
    train_labels = {"activity_a": train_eps["activity_a"], "activity": train_eps["activity_b"],
                    "object": train_eps["object_b"]}
    baselines = {**baseline_metrics(train_labels, labels, model), **data_metrics(labels)}
    counted = perceiver.transition_from_counts(model, perceiver.count_transitions(train_eps["activity_a"],
                                                                                  train_eps["activity_b"]))
    weights = ckpt.config["data"].get("seen_object_weights")
    if weights is None:
        weights = start_pose_weights(model, render_split(train_env, model, data, compiler_options=compiler_options,
                                                         viewpoints=1), 1)
    return {route: {**make_val_fn(model, labels, baselines, compiler_options=compiler_options, transition=t,
                                  seen_objects=seen, unseen_weights=weights)(ckpt.params),
                    **({f"unseen_weight_{k}": v for k, v in weights.items()} if seen else {})}
            for route, t, seen in (("counted", counted, False), ("graph", None, False),
                                   ("counted_seen_objects", counted, True))}
