"""Training the long-term intention predictor (paper sec. 4.1).

episodes -> the env's sensor renders, from each robot start pose, F front views of the human
during activity A (one jitted, vmapped call) -> Perceiver trained on a random prefix of the
frames, cross-entropy on activity B (107) and object B (51) -> val top-1/top-5 against the
"most frequent B given A" prior and chance -> a run that envs.agents.predictors loads as the
per-step predictor agents act with.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from conav_jax import runs
from conav_jax.data.episodes import read_manifest
from conav_jax.models import perceiver
from conav_jax.models.perceiver import PerceiverConfig
from envs import ConavEnv, EnvConfig, SensorConfig
from envs.panorama import front_view
from train.loop import TrainConfig, TrainResult, train

KIND = runs.INTENTION


@dataclasses.dataclass(frozen=True)
class IntentionDataConfig:
    """How the frame sequences are rendered."""

    # Panorama (H, W) rendered; the front view is H x W/4, resized to the model's input. Rendering
    # at the agent's env resolution makes training frames pass the predictor's own resize.
    sensor_hw: tuple[int, int] = (32, 128)
    frames: int = 16  # F: frames per episode, spread evenly over activity A

    def __post_init__(self):
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")


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


def make_front_renderer(env: ConavEnv, image_hw: tuple[int, int], chunk: int, compiler_options: dict | None = None):
    """A jitted `render(episodes (M,), steps (M,)) -> (front (M, h, w, 4) float32,
    human_pixels (M,) int32)`: the env sensor's front view from the episode's robot start pose
    with the human posed at that step, resized to `image_hw`, and how many of the sensor's
    front-view pixels hit the human. Frames are rendered `chunk` at a time, each chunk vmapped."""
    human_start = env.layout.human_start

    def one(episode, t):
        rgbd, ids = env.render_at(episode, env.bank.robot_start[episode], t)  # from the start pose
        front = front_view(rgbd)
        if front.shape[:2] != tuple(image_hw):
            front = jax.image.resize(front, (*image_hw, front.shape[-1]), "linear")
        return front, jnp.sum(front_view(ids[..., None]) >= human_start, dtype=jnp.int32)

    def render(episodes, steps):
        return jax.lax.map(lambda x: one(*x), (episodes, steps), batch_size=chunk)

    return jax.jit(render, compiler_options=compiler_options)


def render_split(
    env: ConavEnv,
    model: PerceiverConfig,
    data: IntentionDataConfig,
    chunk: int = 256,
    compiler_options: dict | None = None,
) -> dict:
    """The intention dataset of every episode of `env`'s bank, rendered `chunk` frames at a time:
    `frames (N, F, h, w, 4)` float16 (RGB in [0, 1], depth m), `num_frames (N,)` int32,
    `activity (N,)`, `object (N,)` int32 labels (activity B, object B), `activity_a (N,)`, and
    `human_pixels (N, F)` int32, the sensor's front-view pixels showing the human."""
    eps = env.split.episodes
    steps, num = activity_a_steps(eps["t_walk_start"], data.frames)
    n, f = steps.shape
    render = make_front_renderer(env, model.image_hw, chunk, compiler_options)
    front, human = render(jnp.repeat(jnp.arange(n, dtype=jnp.int32), f), jnp.asarray(steps.reshape(-1)))
    return {
        # float16 halves device memory; depth keeps ~5 mm at 10 m, plenty at 32x32.
        "frames": front.reshape(n, f, *front.shape[1:]).astype(jnp.float16),
        "num_frames": jnp.asarray(num),
        "activity": jnp.asarray(eps["activity_b"], jnp.int32),
        "object": jnp.asarray(eps["object_b"], jnp.int32),
        "activity_a": jnp.asarray(eps["activity_a"], jnp.int32),
        "human_pixels": human.reshape(n, f),
    }


def make_env(data_dir: str | Path, split: str, data: IntentionDataConfig) -> ConavEnv:
    """The env of one split with the sensor resolution the frames are rendered at."""
    h, w = data.sensor_hw
    return ConavEnv(data_dir, split, EnvConfig(sensor=SensorConfig(height=h, width=w)))


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


def _cross_entropy(logits: jax.Array, labels: jax.Array) -> jax.Array:
    logp = jax.nn.log_softmax(logits, axis=-1)
    return -jnp.mean(jnp.take_along_axis(logp, labels[:, None], axis=-1))


def intention_loss(params, config: PerceiverConfig, batch: dict, key: jax.Array):
    """CE(activity B) + CE(object B) (+ CE(activity A) with the A head); each sample sees a
    random prefix of 1..num_frames frames (the paper: the robot may have watched for any time).
    Aux: each CE."""
    frames = batch["frames"].astype(jnp.float32)
    f = frames.shape[1]
    seen = jax.random.randint(key, batch["num_frames"].shape, 1, batch["num_frames"] + 1)
    mask = jnp.arange(f)[None, :] < seen[:, None]
    logits = perceiver.apply(params, config, frames, mask)
    ce_a = _cross_entropy(logits.activity, batch["activity"])
    ce_o = _cross_entropy(logits.object, batch["object"])
    if logits.activity_a is None:
        return ce_a + ce_o, {"ce_activity": ce_a, "ce_object": ce_o}
    ce_watched = _cross_entropy(logits.activity_a, batch["activity_a"])
    return ce_a + ce_o + ce_watched, {"ce_activity": ce_a, "ce_object": ce_o, "ce_activity_a": ce_watched}


def make_val_fn(
    config: PerceiverConfig, val: dict, baselines: dict, batch: int = 256, compiler_options: dict | None = None
):
    """`val(params) -> dict`: top-1/top-5 of the predicted activity B and object B (the
    predictor's output, `perceiver.intention_probs`) with every frame of activity A seen, top-1
    of the watched activity A with the A head, plus the (constant) prior and chance figures."""
    f = val["frames"].shape[1]

    def logits(params, frames, num):
        mask = jnp.arange(f)[None, :] < num[:, None]
        out = perceiver.apply(params, config, frames.astype(jnp.float32), mask)
        act, obj = perceiver.intention_probs(config, out)  # what the predictor outputs
        watched = act if out.activity_a is None else out.activity_a
        return act, obj, watched

    # The data are arguments: closed over, they would be baked into the compiled program.
    def all_logits(params, frames, num):
        return jax.lax.map(lambda x: logits(params, x[0][None], x[1][None]), (frames, num), batch_size=batch)

    all_logits = jax.jit(all_logits, compiler_options=compiler_options)

    def run(params) -> dict:
        act, obj, watched = (np.asarray(x)[:, 0] for x in all_logits(params, val["frames"], val["num_frames"]))
        out = {}
        for head, scores in (("activity", act), ("object", obj)):
            for k in (1, 5):
                out[f"{head}_top{k}"] = topk_accuracy(scores, np.asarray(val[head]), k)
        if config.activity_a_head:
            out["activity_a_top1"] = topk_accuracy(watched, np.asarray(val["activity_a"]), 1)
        return {**out, **baselines}

    return run


def run_config(model: PerceiverConfig, data: IntentionDataConfig, content_hash: str | None, spacing: float) -> dict:
    """The checkpoint's config: what a resumed run must share, and what the predictor needs."""
    return {
        "kind": KIND,
        "model": dataclasses.asdict(model),
        "data": {**dataclasses.asdict(data), "content_hash": content_hash, "frame_spacing_steps": spacing},
    }


def frame_spacing(t_walk_start: np.ndarray, frames: int) -> float:
    """Median steps between consecutive training frames: the predictor's default stride."""
    length = np.maximum(np.asarray(t_walk_start), 1)
    return float(np.median(np.maximum((length - 1) / max(frames - 1, 1), 1.0)))


def train_intention(
    data_dir: str | Path,
    run_dir: str | Path,
    cfg: TrainConfig,
    model: PerceiverConfig = PerceiverConfig(),
    data: IntentionDataConfig = IntentionDataConfig(),
    progress: bool = True,
    compiler_options: dict | None = None,
    mesh: Mesh | None = None,
) -> TrainResult:
    """Render both splits, train on train, validate on val (`mesh`: data-parallel, see
    train.loop.train)."""
    content_hash = read_manifest(data_dir).get("content_hash")
    train_env, val_env = make_env(data_dir, "train", data), make_env(data_dir, "val", data)
    train_d = render_split(train_env, model, data, compiler_options=compiler_options)
    val_d = render_split(val_env, model, data, compiler_options=compiler_options)
    baselines = baseline_metrics(train_d, val_d, model)
    # Share of val frames in which the robot's start pose sees the human: a sanity check
    # of the data (a predictor cannot read an activity it never sees).
    baselines["val_frames_with_human"] = float(jnp.mean(val_d["human_pixels"] > 0))
    spacing = frame_spacing(train_env.split.episodes["t_walk_start"], data.frames)
    params = perceiver.init(jax.random.PRNGKey(cfg.seed), model)
    loss = lambda p, b, k: intention_loss(p, model, b, k)
    samples = {k: train_d[k] for k in ("frames", "num_frames", "activity", "object", "activity_a")}
    return train(
        run_dir, loss, params, samples, cfg, run_config(model, data, content_hash, spacing),
        val_fn=make_val_fn(model, val_d, baselines, compiler_options=compiler_options),
        progress=progress, compiler_options=compiler_options, mesh=mesh,
    )
