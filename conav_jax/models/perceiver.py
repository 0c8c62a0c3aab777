"""Long-term intention predictor (paper sec. 4.1): a Perceiver over RGB-D frames of the human.

frames `(B, N, h, w, 4)` (crops of the panorama around the human, envs.human_crop; runs from
before it read the panorama's front quarter), float or as `encode_frames` stores them (uint8),
and a valid `mask (B, N)` -> patch tokens (linear patch embedding + learned patch position +
sinusoidal frame index) -> a learned latent array cross-attends to the
valid tokens -> latent self-attention blocks -> mean-pooled latent -> activity (107) and object
(51) logits of what the human does next (B), and, with `activity_a_head`, logits of the
activity being watched (A). `intention_probs` turns them into the predicted distributions:
with the A head, through the shipped causal activity graph, p(B) = sum_A p(A | frames) P(B | A),
mixed with the direct B head. Recognising A from its motion and object is what the frames
show; the step to B is a structural prior: P(B | A) counted on the training episodes
(`transition_from_counts`: how often each link of the generator's graph follows A where the
scenes hold both objects; its ties fall where the scenes make them, not by activity id), or
the graph's links alone, uniform, where a run has no counts. A model trained on a few scenes
otherwise has to learn that step from their labels (and memorises the scenes instead:
BENCHMARKS.md). `intention_routes` gives each route alone, so results can be reported with and
without that prior.
`lowest_entropy_average` is the paper's inference-time smoothing of predictions.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from conav_jax import nn
from conav_jax.data.activities import NUM_ACTIVITIES
from conav_jax.data.categories import NUM_CATEGORIES

Params = dict


@dataclass(frozen=True)
class PerceiverConfig:
    """Sizes of the intention Perceiver. The frame defaults to the crop at the sensor's default
    resolution; the widths are small, and twice the width (dim 128, 32 latents) did no better
    on the small preset's minival split (2,000 updates, four viewpoints per episode)."""

    # Frame (h, w) in pixels: the crop around the human, taken from the panorama at its own
    # resolution (64x64 of a 112x448 panorama frames a standing human 2-3 m away whole).
    # Runs from before the crop read 32x32 front views and say so in their config.
    image_hw: tuple[int, int] = (64, 64)
    channels: int = 4  # RGB in [0, 1] + depth in metres
    patch_size: int = 8  # square patches; must divide h and w
    max_depth_m: float = 10.0  # depth is divided by this and clipped to [0, 1] (also in encode_frames)
    dim: int = 64  # token and latent width
    num_latents: int = 16
    num_heads: int = 4  # head width = dim // num_heads
    num_blocks: int = 2  # latent self-attention blocks after the cross-attention
    mlp_ratio: int = 2  # MLP hidden width = mlp_ratio * dim
    num_activities: int = NUM_ACTIVITIES  # the shipped activity graph's
    num_objects: int = NUM_CATEGORIES  # conav_jax.data.categories
    # Also classify activity A and predict B through the activity graph (needs the graph's
    # 107 activities and 51 categories). Checkpoints written before this field had no A head.
    activity_a_head: bool = True
    # Weight of the graph route (p(A | frames) through P(B | A), a structural prior: see
    # transition_from_counts) in p(B) and p(object B); the rest: the direct heads.
    graph_mix: float = 0.8
    # Weigh activities A and B by whether the robot's panoramas have shown their object category
    # so far (`intention_routes`' objects_seen and unseen_weights; envs.agents.predictors keeps
    # the set from each recorded panorama's `segmentation` observation: oracle segmentation). The
    # generator puts B at an object of the scene, and a scene holds few of the 51 categories, so
    # a category seen is evidence for it. Inference only: the trained weights do not depend on
    # it. Runs written before it had none.
    seen_objects: bool = False

    def __post_init__(self):
        if not 0.0 <= self.graph_mix <= 1.0:
            raise ValueError(f"graph_mix must be in [0, 1], got {self.graph_mix}")

    @property
    def num_patches(self) -> int:
        h, w = self.image_hw
        return (h // self.patch_size) * (w // self.patch_size)


class IntentionLogits(NamedTuple):
    """Unnormalised class scores: `activity (B, num_activities)` and `object (B, num_objects)`
    of activity B; `activity_a (B, num_activities)` of the watched activity A (None without
    the A head)."""

    activity: jax.Array
    object: jax.Array
    activity_a: jax.Array | None = None


def graph_tables(config: PerceiverConfig) -> tuple[np.ndarray, np.ndarray]:
    """(P(B | A) `(A, B)` row-stochastic over the graph's links, uniform over all activities for
    an A without links; object of B `(B, num_objects)` one-hot) from the shipped activity graph.
    ValueError if the config's class counts are not the graph's."""
    return _graph_tables(config.num_activities, config.num_objects)


@functools.lru_cache(maxsize=4)
def _graph_tables(num_activities: int, num_objects: int) -> tuple[np.ndarray, np.ndarray]:
    from conav_jax.data.activities import load_activity_graph
    from conav_jax.data.categories import CATEGORY_NAMES

    graph = load_activity_graph()
    n, m = len(graph.activities), len(CATEGORY_NAMES)
    if (num_activities, num_objects) != (n, m):
        raise ValueError(
            f"activity_a_head predicts through the activity graph ({n} activities, {m} categories); "
            f"the config has {num_activities} / {num_objects}: set activity_a_head=False"
        )
    counts = np.zeros((n, n), np.float64)
    for link in graph.links:
        counts[link.a, link.b] += 1.0
    rows = counts.sum(1, keepdims=True)
    transition = np.where(rows > 0, counts / np.maximum(rows, 1.0), 1.0 / n).astype(np.float32)
    objects = np.zeros((n, m), np.float32)
    objects[np.arange(n), [graph.object_of(i) for i in range(n)]] = 1.0
    transition.flags.writeable = objects.flags.writeable = False  # shared by every caller
    return transition, objects


class IntentionRoutes(NamedTuple):
    """The predicted distributions of activity B `(..., num_activities)` and object B
    `(..., num_objects)` by route: `direct` from the B heads alone (what the frames taught the
    model); `graph_prior` from the A head through P(B | A) alone (the run's counts, else the
    generator's graph), a structural prior (None without the A head); `mixed`, what the
    predictor outputs: their mix with weight `graph_mix` on the graph route (`direct` without
    the A head)."""

    direct: tuple[jax.Array, jax.Array]
    graph_prior: tuple[jax.Array, jax.Array] | None
    mixed: tuple[jax.Array, jax.Array]


def count_transitions(activity_a: np.ndarray, activity_b: np.ndarray) -> list[list[int]]:
    """The (A, B) activity pairs of episodes as sorted [A, B, count] triples (a run config's
    JSON). ValueError for arrays that are not 1-D of one length."""
    a, b = np.asarray(activity_a), np.asarray(activity_b)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"activity_a and activity_b must be 1-D of one length, got {a.shape} and {b.shape}")
    pairs, counts = np.unique(np.stack([a, b], 1).reshape(-1, 2), axis=0, return_counts=True)
    return [[int(x), int(y), int(c)] for (x, y), c in zip(pairs, counts)]


def transition_from_counts(config: PerceiverConfig, triples) -> np.ndarray:
    """P(B | A) `(A, B)` float32, row-stochastic, from [A, B, count] triples (count_transitions
    of training episodes); an A no episode starts with keeps the graph's uniform row
    (graph_tables). ValueError for activities out of range or negative counts."""
    n = config.num_activities
    t = np.asarray(triples, np.int64).reshape(-1, 3)
    if t.size and (t[:, :2].min() < 0 or t[:, :2].max() >= n or t[:, 2].min() < 0):
        raise ValueError(f"transition counts need activities in [0, {n}) and counts >= 0, got {t.tolist()[:4]}...")
    counts = np.zeros((n, n), np.float64)
    np.add.at(counts, (t[:, 0], t[:, 1]), t[:, 2])
    rows = counts.sum(1, keepdims=True)
    return np.where(rows > 0, counts / np.maximum(rows, 1.0), graph_tables(config)[0]).astype(np.float32)


def activity_objects(config: PerceiverConfig) -> np.ndarray:
    """The object category of each activity `(num_activities,)` int, from the shipped graph."""
    return np.argmax(graph_tables(config)[1], axis=1)


UNSEEN_WEIGHT_KEYS = ("activity_a", "activity_b")


def check_unseen_weights(weights) -> dict:
    """`weights` ({"activity_a": w, "activity_b": w}, seen_object_weights') as floats, or
    ValueError naming what is wrong: other keys, or a weight not finite and >= 0 (a run's config
    is read back from JSON; a missing key would silently drop its activities)."""
    if not isinstance(weights, dict) or set(weights) != set(UNSEEN_WEIGHT_KEYS):
        raise ValueError(f"unseen weights must be a mapping with keys {UNSEEN_WEIGHT_KEYS}, got {weights!r}")
    out = {}
    for k in UNSEEN_WEIGHT_KEYS:
        try:
            w = float(weights[k])
        except (TypeError, ValueError):
            raise ValueError(f"unseen weight {k} must be a number, got {weights[k]!r}") from None
        if not np.isfinite(w) or w < 0.0:
            raise ValueError(f"unseen weight {k} must be finite and >= 0, got {w}")
        out[k] = w
    return out


def _keep(probs: jax.Array, keep: jax.Array, unseen_weight=0.0) -> jax.Array:
    """`probs (..., C)` with the classes `keep (..., C)` does not hold weighed by
    `unseen_weight` (0: dropped), renormalised; rows left with no mass stay as they were
    (nothing seen yet says nothing)."""
    kept = probs * jnp.where(keep, 1.0, unseen_weight)
    total = jnp.sum(kept, axis=-1, keepdims=True)
    return jnp.where(total > 0.0, kept / jnp.where(total > 0.0, total, 1.0), probs)


def seen_object_weights(objects_seen: np.ndarray, object_a: np.ndarray, object_b: np.ndarray) -> dict:
    """How much less likely a category is to be activity A's (B's) object when the robot has
    not seen it than when it has: {"activity_a": w, "activity_b": w}, each the odds ratio, over
    samples `objects_seen (N, num_objects)` bool with their objects `object_a`, `object_b (N,)`,
    of "not seen" for the true object against the other categories (naive Bayes: given what was
    seen, a hypothesis' likelihood is this ratio, or 1, by its own object's indicator; the rest
    is common to all). Counts start at 1 (add-one smoothing). ValueError for shapes that do not
    fit."""
    seen = np.asarray(objects_seen, bool)
    if seen.ndim != 2 or len(object_a) != len(seen) or len(object_b) != len(seen):
        raise ValueError(f"objects_seen must be (N, C) beside (N,) objects, got {seen.shape}, "
                         f"{np.shape(object_a)}, {np.shape(object_b)}")
    out = {}
    for name, obj in zip(UNSEEN_WEIGHT_KEYS, (object_a, object_b)):
        mine = seen[np.arange(len(seen)), np.asarray(obj)]
        others_seen = seen.sum() - mine.sum()
        others = seen.size - len(seen)
        odds_mine = (np.sum(~mine) + 1.0) / (np.sum(mine) + 1.0)
        odds_others = (others - others_seen + 1.0) / (others_seen + 1.0)
        out[name] = float(odds_mine / odds_others)
    return out


def intention_routes(config: PerceiverConfig, logits: IntentionLogits, transition=None,
                     objects_seen: jax.Array | None = None, unseen_weights: dict | None = None) -> IntentionRoutes:
    """Each route's (activity B, object B) probabilities, see IntentionRoutes. `transition`:
    P(B | A) `(A, B)` for the graph route (a run's `transition_from_counts`); None: the graph's
    links, uniform (graph_tables). `objects_seen (..., num_objects)` bool: the object categories
    the robot has seen (PerceiverConfig.seen_objects); with it every route weighs the activities
    of objects not seen by `unseen_weights` ({"activity_a": w, "activity_b": w}, from
    `seen_object_weights`; None: 0, dropped): A in the graph route, B in both, each P(B | A) row
    renormalised (the generator draws B among the links whose objects the scene holds); None:
    unweighted."""
    direct = jax.nn.softmax(logits.activity, axis=-1), jax.nn.softmax(logits.object, axis=-1)
    hi = jax.lax.Precision.HIGHEST  # probabilities: keep float32 on the GPU
    seen_activity = None
    weights = dict.fromkeys(UNSEEN_WEIGHT_KEYS, 0.0) if unseen_weights is None else check_unseen_weights(unseen_weights)
    w_a, w_b = weights["activity_a"], weights["activity_b"]
    if objects_seen is not None:
        if objects_seen.shape[-1] != config.num_objects:
            raise ValueError(f"objects_seen must be (..., {config.num_objects}), got {objects_seen.shape}")
        seen_activity = jnp.take(objects_seen, jnp.asarray(activity_objects(config)), axis=-1)  # (..., A)
        direct = _keep(direct[0], seen_activity, w_b), _keep(direct[1], objects_seen, w_b)
    if logits.activity_a is None:
        return IntentionRoutes(direct, None, direct)
    graph_transition, objects = graph_tables(config)
    transition = graph_transition if transition is None else transition
    if np.shape(transition) != graph_transition.shape:
        raise ValueError(f"transition must have shape {graph_transition.shape}, got {np.shape(transition)}")
    p_a = jax.nn.softmax(logits.activity_a, axis=-1)
    if seen_activity is None:
        via_b = jnp.matmul(p_a, jnp.asarray(transition), precision=hi)
    else:  # a P(B | A) of each sample's own: rows over the seen Bs
        rows = _keep(jnp.broadcast_to(jnp.asarray(transition), (*seen_activity.shape[:-1], *transition.shape)),
                     seen_activity[..., None, :], w_b)
        via_b = jnp.einsum("...a,...ab->...b", _keep(p_a, seen_activity, w_a), rows, precision=hi)
        if w_b == 0.0:  # a seen A whose successors are all unseen keeps its whole row above
            via_b = _keep(via_b, seen_activity)
    via_obj = jnp.matmul(via_b, jnp.asarray(objects), precision=hi)
    w = config.graph_mix
    mixed = (1.0 - w) * direct[0] + w * via_b, (1.0 - w) * direct[1] + w * via_obj
    return IntentionRoutes(direct, (via_b, via_obj), mixed)


def intention_probs(config: PerceiverConfig, logits: IntentionLogits, transition=None,
                    objects_seen: jax.Array | None = None, unseen_weights: dict | None = None
                    ) -> tuple[jax.Array, jax.Array]:
    """(activity B probabilities `(..., num_activities)`, object B probabilities
    `(..., num_objects)`): the direct heads' softmax, and with the A head their mix with the
    graph route (weight `graph_mix`; `transition`, `objects_seen`, `unseen_weights` as
    intention_routes); `intention_routes(...).mixed`."""
    return intention_routes(config, logits, transition, objects_seen, unseen_weights).mixed


def encode_frames(frames: jax.Array, max_depth_m: float) -> jax.Array:
    """Frames `(..., 4)` float (RGB in [0, 1], depth m) as uint8: RGB and depth / `max_depth_m`,
    clipped to [0, 1], in 255 steps. RGB of 8-bit colours comes back exactly; depth to within
    max_depth_m / 510 (2 cm at 10 m). A quarter of float32's memory, for the training sets and
    the predictor's frame buffer; `apply` reads them as they are."""
    rgb, depth = frames[..., :3], frames[..., 3:]
    unit = jnp.concatenate([rgb, depth / max_depth_m], axis=-1)
    return jnp.round(jnp.clip(unit, 0.0, 1.0) * 255.0).astype(jnp.uint8)


def _block_init(key: jax.Array, config: PerceiverConfig, kv_dim: int) -> Params:
    """Pre-norm attention + MLP block; `kv_dim` is the width of what the latents attend to."""
    d = config.dim
    k_attn, k_mlp = jax.random.split(key)
    return {
        "norm_q": nn.norm.init(None, d),
        "norm_kv": nn.norm.init(None, kv_dim),
        "attn": nn.attention.init(k_attn, d, kv_dim, config.num_heads, d // config.num_heads),
        "norm_mlp": nn.norm.init(None, d),
        "mlp": nn.mlp.init(k_mlp, (d, config.mlp_ratio * d, d)),
    }


def _block_apply(
    params: Params, latents: jax.Array, kv: jax.Array, key_mask: jax.Array | None
) -> jax.Array:
    """`latents (B, L, d)` attend to `kv (B, S, kv_dim)` (masked), then MLP; both residual."""
    q = nn.norm.apply(params["norm_q"], latents)
    latents = latents + nn.attention.apply(params["attn"], q, nn.norm.apply(params["norm_kv"], kv), key_mask)
    return latents + nn.mlp.apply(params["mlp"], nn.norm.apply(params["norm_mlp"], latents))


def init(key: jax.Array, config: PerceiverConfig) -> Params:
    """Parameters for `config`; a stored frame count is not needed (any N works)."""
    h, w = config.image_hw
    p, d = config.patch_size, config.dim
    if h % p or w % p:
        raise ValueError(f"patch_size {p} must divide the frame size {config.image_hw}")
    if d % config.num_heads or d % 2:
        raise ValueError(f"dim {d} must be even and divisible by num_heads {config.num_heads}")
    if config.activity_a_head:
        graph_tables(config)  # the class counts must be the graph's
    keys = jax.random.split(key, 7 + config.num_blocks)
    params = {
        "patch_embed": nn.linear.init(keys[0], p * p * config.channels, d),
        "patch_pos": 0.02 * jax.random.normal(keys[1], (config.num_patches, d)),
        "latents": 0.02 * jax.random.normal(keys[2], (config.num_latents, d)),
        "cross": _block_init(keys[3], config, d),
        "blocks": [_block_init(k, config, d) for k in keys[7:]],
        "norm_out": nn.norm.init(None, d),
        "activity_head": nn.linear.init(keys[4], d, config.num_activities, scheme="glorot"),
        "object_head": nn.linear.init(keys[5], d, config.num_objects, scheme="glorot"),
    }
    if config.activity_a_head:
        params["activity_a_head"] = nn.linear.init(keys[6], d, config.num_activities, scheme="glorot")
    return params


def _patchify(frames: jax.Array, patch: int) -> jax.Array:
    """`(B, N, h, w, C) -> (B, N, (h/p)(w/p), p*p*C)`, patches in row-major order."""
    b, n, h, w, c = frames.shape
    x = frames.reshape(b, n, h // patch, patch, w // patch, patch, c)
    x = x.transpose(0, 1, 2, 4, 3, 5, 6)
    return x.reshape(b, n, (h // patch) * (w // patch), patch * patch * c)


def apply(
    params: Params, config: PerceiverConfig, frames: jax.Array, mask: jax.Array
) -> IntentionLogits:
    """`frames (B, N, h, w, 4)` float (RGB in [0, 1], depth in metres) or uint8 (`encode_frames`),
    `mask (B, N)` bool (True = a real frame) -> logits. Masked frames are ignored exactly,
    whatever they hold; a sample with no valid frame gets the latents' prior prediction."""
    b, n = frames.shape[:2]
    if frames.shape[2:] != (*config.image_hw, config.channels):
        raise ValueError(f"frames must be (B, N, {config.image_hw[0]}, {config.image_hw[1]}, {config.channels}), "
                         f"got {frames.shape}")
    if frames.dtype == jnp.uint8:  # encode_frames: every channel already in [0, 1] steps of 1/255
        frames = frames.astype(jnp.float32) / 255.0
    else:
        rgb, depth = frames[..., :3], frames[..., 3:]
        frames = jnp.concatenate([rgb, jnp.clip(depth / config.max_depth_m, 0.0, 1.0)], axis=-1)
    # Padding may hold anything (even NaN); zero it so 0-weight attention stays exactly 0.
    frames = jnp.where(mask[:, :, None, None, None], frames, 0.0).astype(jnp.float32)

    tokens = nn.linear.apply(params["patch_embed"], _patchify(frames, config.patch_size))
    time = nn.embedding.sinusoidal(jnp.arange(n), config.dim)  # (N, d), frame index
    tokens = tokens + params["patch_pos"] + time[:, None, :]
    tokens = tokens.reshape(b, n * config.num_patches, config.dim)
    token_mask = jnp.repeat(mask, config.num_patches, axis=1)

    latents = jnp.broadcast_to(params["latents"], (b, *params["latents"].shape))
    latents = _block_apply(params["cross"], latents, tokens, token_mask)
    for block in params["blocks"]:
        latents = _block_apply(block, latents, latents, None)
    pooled = jnp.mean(nn.norm.apply(params["norm_out"], latents), axis=1)
    return IntentionLogits(
        activity=nn.linear.apply(params["activity_head"], pooled),
        object=nn.linear.apply(params["object_head"], pooled),
        activity_a=nn.linear.apply(params["activity_a_head"], pooled) if config.activity_a_head else None,
    )


def lowest_entropy_average(prob_history: jax.Array, valid: jax.Array, k: int = 5) -> jax.Array:
    """The paper's inference smoothing: mean of the `k` lowest-entropy valid predictions.

    `prob_history (B, T, C)` probabilities, `valid (B, T)` bool -> `(B, C)`. With fewer than `k`
    valid steps, the mean of those; with none, the uniform distribution. Ties go to earlier steps.
    """
    p, valid = jnp.asarray(prob_history), jnp.asarray(valid)
    c = p.shape[-1]
    entropy = -jnp.sum(jnp.where(p > 0, p * jnp.log(jnp.where(p > 0, p, 1.0)), 0.0), axis=-1)
    score = jnp.where(valid, -entropy, -jnp.inf)  # top_k of -entropy = lowest entropy
    _, idx = jax.lax.top_k(score, min(k, p.shape[1]))
    chosen = jnp.take_along_axis(p, idx[..., None], axis=1)  # (B, k, C)
    weight = jnp.take_along_axis(valid, idx, axis=1).astype(p.dtype)[..., None]
    count = jnp.sum(weight, axis=1)
    mean = jnp.sum(chosen * weight, axis=1) / jnp.maximum(count, 1.0)
    return jnp.where(count > 0, mean, 1.0 / c)
