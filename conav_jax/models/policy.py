"""CoNav LSTM policy (paper sec. 4.2): panorama + pose + human position + intentions -> action.

obs -> CNN(rgbd) -> flatten -> linear; pose (x, y, sin yaw, cos yaw) and human position ->
linear; each enabled intention input (activity probs, object probs, future trajectory) ->
its own linear -> concat -> LSTM -> `action (B, 2)` in [-1, 1] (tanh) and `value (B,)`.
Disabled intention inputs (the paper's Table 3 ablation) are never read and have no weights.

With the object input and `object_saliency` (the default), the predicted object distribution
is also read *where it is in the panorama*: each pixel's object category comes from the env's
`segmentation` observation (privileged: the stand-in for the semantic segmenter a real robot
would run; the RGB's instance materials do not give categories away), and the pixel's saliency is the predicted
probability of that category relative to the most likely one. The saliency map is a fifth CNN
channel, and per azimuth sector its peak and the nearest salient depth feed the LSTM directly.
A probability vector alone says *what* the human will use; without a map the policy had to
learn from a few thousand demonstrations which pixels show it, and did not (README).

The same network serves the paper's goal-navigation baselines (envs.agents.goalnav): without
the human's position (`use_human_pos`), given a goal category as `object_probs` (the object-goal
agent), or a goal image (`goal_image`: the forward quarter, RGB, of a panorama rendered where the
goal is seen from) encoded by a small CNN of its own and fed to the LSTM beside the rest (the
image-goal agent).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from conav_jax import nn
from conav_jax.data.activities import NUM_ACTIVITIES
from conav_jax.data.categories import NUM_CATEGORIES
from conav_jax.nn.lstm import LSTMState

Params = dict
Obs = dict[str, jax.Array]
# The observation keys `prepare_panorama` makes of a step's panorama (the CNN's input image, and
# the saliency channel's bearing features); `encode` reads them in place of `rgbd`.
PANORAMA_IMAGE, PANORAMA_BEARING = "panorama_image", "panorama_bearing"

# PolicyConfig.conv_dtype -> conav_jax.nn.conv's compute_dtype (None: no cast, float32 throughout).
CONV_DTYPES = {"float32": None, "bfloat16": jnp.bfloat16}

# Panorama encoders, as (conv_channels, conv_kernels, conv_strides) of PolicyConfig. "conv":
# stride-2 convolutions, the network of every run in results/ and of the shipped policy.
# "patch": the first layer embeds each 4x4 pixel block by one linear map (kernel = stride = 4)
# in place of the first two stride-2 convolutions, to the same grid (a 16th of each side, 64
# channels) with a third of the convolution work: 1.9x the 112x448 imitation update on a GPU
# (BENCHMARKS.md).
ENCODERS = {
    "conv": ((16, 32, 32, 64), (5, 3, 3, 3), None),
    "patch": ((32, 32, 64), (4, 3, 3), (4, 2, 2)),
}
DEFAULT_ENCODER = "conv"

ABLATIONS = {
    # name: (use_activity, use_object, use_trajectory), rows 1-5 of the paper's Table 3
    "none": (False, False, False),
    "activity": (True, False, False),
    "object": (False, True, False),
    "activity_object": (True, True, False),
    "all": (True, True, True),
}


@dataclass(frozen=True)
class PolicyConfig:
    """Sizes and input switches of the CoNav policy."""

    resolution: tuple[int, int] = (112, 448)  # panorama (H, W) in pixels
    # The panorama CNN, one SAME conv per entry (ENCODERS); a layer whose kernel equals its
    # stride embeds non-overlapping patches (conav_jax.nn.conv). Strides None: 2 for each
    # layer, as every run had before strides could be set.
    conv_channels: tuple[int, ...] = ENCODERS[DEFAULT_ENCODER][0]
    conv_kernels: tuple[int, ...] = ENCODERS[DEFAULT_ENCODER][1]
    conv_strides: tuple[int, ...] | None = ENCODERS[DEFAULT_ENCODER][2]
    visual_dim: int = 256  # flattened CNN features -> this width
    # Layer-normalise the visual embedding before its ReLU. Without it, Adam at lr 1e-3 moves the
    # flatten layer's many weights together (fan-in H/16 * W/16 * 64 at 112x448 with the patch
    # encoder) until its outputs grow large, most units die and the LSTM saturates: the policy's
    # action stops depending on its inputs (results/paper_112x448_live_visual_norm). Runs written
    # before this field had none (False when absent).
    visual_norm: bool = False
    state_dim: int = 32  # pose + human position embedding width
    intention_dim: int = 32  # embedding width of each enabled intention input
    hidden: int = 256  # LSTM width
    max_depth_m: float = 10.0  # depth is divided by this and clipped to [0, 1]
    position_scale_m: float = 10.0  # positions (pose, human, trajectory) are divided by this
    num_activities: int = NUM_ACTIVITIES  # the shipped activity graph's
    num_objects: int = NUM_CATEGORIES  # conav_jax.data.categories
    horizon: int = 5  # future trajectory length
    use_activity: bool = True
    use_object: bool = True
    use_trajectory: bool = True
    # With use_object: the object-B saliency channel and its per-sector bearing features
    # (module docstring). Checkpoints written before this field had none (False when absent).
    object_saliency: bool = True
    saliency_sectors: int = 16  # azimuth sectors of the bearing features; must divide the width
    init_log_std: float = -0.5  # initial action log-std (PPO only)
    # The human's position (robot frame) in the state input. The goal-navigation baselines
    # read none: an ObjectNav or ImageNav policy knows only its goal.
    use_human_pos: bool = True
    # A goal image `goal_image (goal_image_hw..., 3)` RGB in [0, 1], through its own stride-2
    # CNN (one conv per entry) and a linear layer of goal_dim to the LSTM (the image-goal agent).
    goal_image: bool = False
    goal_conv_channels: tuple[int, ...] = (16, 32, 32)
    goal_conv_kernels: tuple[int, ...] = (3, 3, 3)
    goal_dim: int = 64
    # Dtype of every convolution the policy runs (the panorama CNN and the goal-image CNN) and
    # of the activations between its layers: "float32" or "bfloat16". At 112x448 the CNN
    # dominates the imitation update; bf16 halves its memory traffic and runs it on tensor
    # cores, which accumulate in float32 (conav_jax.nn.conv); the CNN's output is widened to
    # float32. Parameters, the loss, the optimizer and the LSTM stay float32.
    conv_dtype: str = "float32"

    def __post_init__(self):
        if not len(self.conv_channels) == len(self.conv_kernels) == len(self.strides) or min(self.strides, default=1) < 1:
            raise ValueError("conv_channels, conv_kernels and conv_strides need one entry per conv layer, strides >= 1; "
                             f"got {self.conv_channels}, {self.conv_kernels}, {self.conv_strides}")
        if self.conv_dtype not in CONV_DTYPES:
            raise ValueError(f"unknown conv_dtype {self.conv_dtype!r}; expected one of {sorted(CONV_DTYPES)}")
        if self.uses_saliency and (self.saliency_sectors < 1 or self.resolution[1] % self.saliency_sectors):
            raise ValueError(f"saliency_sectors ({self.saliency_sectors}) must divide the panorama width {self.resolution[1]}")
        if self.goal_image and (len(self.goal_conv_channels) != len(self.goal_conv_kernels) or self.resolution[1] % 4):
            raise ValueError("goal_conv_channels and goal_conv_kernels need one entry per conv layer, and the goal "
                             f"image (a quarter of the panorama) a width divisible by 4, got {self.resolution[1]}")

    @property
    def strides(self) -> tuple[int, ...]:
        """The panorama CNN's stride per layer (conv_strides, or 2 each)."""
        return self.conv_strides if self.conv_strides is not None else (2,) * len(self.conv_channels)

    @property
    def conv_compute_dtype(self):
        """conav_jax.nn.conv's `compute_dtype` for conv_dtype (None: plain float32)."""
        return CONV_DTYPES[self.conv_dtype]

    @property
    def uses_saliency(self) -> bool:
        return self.use_object and self.object_saliency

    @property
    def goal_image_hw(self) -> tuple[int, int]:
        """(H, W) of the goal image: the forward quarter of a panorama of resolution
        (envs.panorama.front_view)."""
        return self.resolution[0], self.resolution[1] // 4


# Fields added after runs were written: a run's config stores them only where they differ from
# their defaults (`config_dict`), so a run written before them still resumes (its stored config
# compares equal), and `envs.agents.policy.policy_config_from_dict` fills in the defaults.
LATER_FIELDS = ("use_human_pos", "goal_image", "goal_conv_channels", "goal_conv_kernels", "goal_dim", "conv_dtype",
                "conv_strides", "visual_norm")
# The goal encoder's keys come from this fold of init's key, so configs without a goal image
# draw every other parameter exactly as before the goal input existed.
_GOAL_KEY_FOLD = 0x60A1


def config_dict(config: PolicyConfig) -> dict:
    """What a run stores as its "model": the config's fields, LATER_FIELDS only where they
    differ from the defaults."""
    default = PolicyConfig()
    return {k: v for k, v in dataclasses.asdict(config).items()
            if k not in LATER_FIELDS or v != getattr(default, k)}


def ablation_config(base: PolicyConfig, name: str) -> PolicyConfig:
    """`base` with the intention switches of a Table 3 row: none | activity | object |
    activity_object | all."""
    if name not in ABLATIONS:
        raise ValueError(f"unknown ablation {name!r}; expected one of {sorted(ABLATIONS)}")
    act, obj, traj = ABLATIONS[name]
    return dataclasses.replace(base, use_activity=act, use_object=obj, use_trajectory=traj)


def encoder_config(base: PolicyConfig, name: str) -> PolicyConfig:
    """`base` with the panorama encoder `name` of ENCODERS."""
    if name not in ENCODERS:
        raise ValueError(f"unknown encoder {name!r}; expected one of {sorted(ENCODERS)}")
    channels, kernels, strides = ENCODERS[name]
    return dataclasses.replace(base, conv_channels=channels, conv_kernels=kernels, conv_strides=strides)


def encoder_name(config: PolicyConfig) -> str:
    """The ENCODERS name of `config`'s panorama CNN, "custom" for any other."""
    layers = (config.conv_channels, config.conv_kernels, config.strides)
    for name in ENCODERS:
        named = encoder_config(PolicyConfig(), name)
        if (named.conv_channels, named.conv_kernels, named.strides) == layers:
            return name
    return "custom"


def _intention_inputs(config: PolicyConfig) -> dict[str, int]:
    """Enabled intention observations and their flat widths, in concatenation order."""
    widths = {}
    if config.use_activity:
        widths["activity_probs"] = config.num_activities
    if config.use_object:
        widths["object_probs"] = config.num_objects
    if config.use_trajectory:
        widths["future_traj"] = 2 * config.horizon
    return widths


def categories_in_view(segmentation: jax.Array) -> jax.Array:
    """The object categories an image shows: `(NUM_CATEGORIES,)` bool from its `segmentation
    (H, W)` (the env's observation key: each pixel's category, -1 for none), true for each
    category with at least one pixel."""
    if segmentation.ndim != 2:
        raise ValueError(f"segmentation must be (H, W), got {segmentation.shape}")
    cats = segmentation.reshape(-1)
    # Pixels of no category index past the end and are dropped.
    n = NUM_CATEGORIES
    return jnp.zeros(n, bool).at[jnp.where(cats >= 0, cats, n)].set(True, mode="drop")


def object_saliency(segmentation: jax.Array, object_probs: jax.Array) -> jax.Array:
    """Saliency `(..., H, W)` in [0, 1]: each pixel's category (`segmentation (..., H, W)`,
    -1 for none) under `object_probs (..., C)`, divided by the largest probability (the most
    likely category's pixels read 1, however unsure the prediction); 0 where the pixel shows no
    object."""
    cats = segmentation.astype(jnp.int32)
    probs = object_probs / jnp.maximum(jnp.max(object_probs, axis=-1, keepdims=True), 1e-6)
    flat = cats.reshape(*cats.shape[:-2], -1)
    picked = jnp.take_along_axis(probs, jnp.maximum(flat, 0), axis=-1)
    return jnp.where(flat >= 0, picked, 0.0).reshape(cats.shape)


def saliency_bearing(config: PolicyConfig, saliency: jax.Array, depth_m: jax.Array) -> jax.Array:
    """Bearing features `(..., 2 * sectors)` of a saliency map and depth `(..., H, W)`: per
    azimuth sector (panorama columns, robot frame), the peak saliency and the nearest depth of
    its pixels at least half as salient as that peak (scaled by max_depth_m; 1 where none)."""
    s = config.saliency_sectors
    *lead, h, w = saliency.shape
    sal = saliency.reshape(*lead, h, s, w // s)
    depth = jnp.clip(depth_m / config.max_depth_m, 0.0, 1.0).reshape(*lead, h, s, w // s)
    peak = jnp.max(sal, axis=(-3, -1))
    salient = (sal >= 0.5 * peak[..., None, :, None]) & (sal > 0.0)
    near = jnp.min(jnp.where(salient, depth, 1.0), axis=(-3, -1))
    return jnp.concatenate([peak, near], axis=-1)


def _conv_stack(params: list, x: jax.Array, compute_dtype=None, strides: tuple[int, ...] | None = None,
                patches: bool = False) -> jax.Array:
    """SAME convs with ReLU at `strides` (default 2 each): `(..., H, W, C) -> (..., ~H / prod,
    ~W / prod, C_last)`, float32 out. With `compute_dtype` (conav_jax.nn.conv.apply's) the
    activations between the layers are in it, and a stride-2 first layer, whose few input
    channels starve GPU convolution kernels, runs over 2x2 pixel blocks when the image's sides
    are even (the same sums, faster; BENCHMARKS.md). `patches`: `x` is the image already laid
    out as the first layer's patches (nn.conv.to_patches; that layer embeds patches)."""
    strides = strides or (2,) * len(params)
    for i, (layer, stride) in enumerate(zip(params, strides, strict=True)):
        if i == 0 and patches:
            x = jax.nn.relu(nn.conv.apply_to_patches(layer, x, compute_dtype=compute_dtype))
            continue
        blocks = compute_dtype is not None and i == 0 and stride == 2 and x.shape[-3] % 2 == 0 and x.shape[-2] % 2 == 0
        x = jax.nn.relu(nn.conv.apply(layer, x, stride=stride, padding="SAME", compute_dtype=compute_dtype,
                                      space_to_depth=blocks))
    return x.astype(jnp.float32)


def first_layer_embeds_patches(config: PolicyConfig) -> bool:
    """Whether the panorama CNN's first layer embeds non-overlapping patches (kernel = stride,
    tiling the panorama): `prepare_panorama` then lays the image out as its patches."""
    k, s = config.conv_kernels[0], config.strides[0]
    return k == s and config.resolution[0] % k == 0 and config.resolution[1] % k == 0


def prepare_panorama(config: PolicyConfig, obs: Obs) -> Obs:
    """The parameter-free part of `encode` for a step's panorama: obs `rgbd (..., H, W, 4)` (and
    `segmentation`, `object_probs` with the saliency channel) -> {PANORAMA_IMAGE: the CNN's input
    image, rounded to conv_dtype, as the first layer's patches where it embeds patches
    (first_layer_embeds_patches); PANORAMA_BEARING (..., 2 * sectors) with the saliency channel}.
    `encode` reads these keys where an observation holds them, so a training window can store
    them once instead of preparing every frame on each pass over it (train.live); the
    result is the same."""
    rgbd = obs["rgbd"].astype(jnp.float32)  # float16 panoramas widen here, per call
    depth = jnp.clip(rgbd[..., 3:] / config.max_depth_m, 0.0, 1.0)
    channels = [rgbd[..., :3], depth]
    if config.uses_saliency:
        saliency = object_saliency(obs["segmentation"], obs["object_probs"].astype(jnp.float32))
        channels.append(saliency[..., None])
    image = jnp.concatenate(channels, axis=-1)
    if config.conv_compute_dtype is not None:
        image = image.astype(config.conv_compute_dtype)
    if first_layer_embeds_patches(config):
        image = nn.conv.to_patches(image, config.conv_kernels[0])
    out = {PANORAMA_IMAGE: image}
    if config.uses_saliency:
        out[PANORAMA_BEARING] = saliency_bearing(config, saliency, rgbd[..., 3])
    return out


def init(key: jax.Array, config: PolicyConfig) -> Params:
    """Parameters for `config`; the CNN output size is derived by shape evaluation."""
    intentions = _intention_inputs(config)
    keys = iter(jax.random.split(key, len(config.conv_channels) + 6 + len(intentions)))
    in_ch = (4 + config.uses_saliency, *config.conv_channels[:-1])
    convs = [
        nn.conv.init(next(keys), i, o, k)
        for i, o, k in zip(in_ch, config.conv_channels, config.conv_kernels)
    ]
    image = jax.ShapeDtypeStruct((1, *config.resolution, in_ch[0]), jnp.float32)
    _, fh, fw, fc = jax.eval_shape(lambda p, x: _conv_stack(p, x, strides=config.strides), convs, image).shape
    lstm_in = config.visual_dim + config.state_dim + config.intention_dim * (len(intentions) + config.uses_saliency)
    lstm_in += config.goal_dim if config.goal_image else 0
    saliency_key = next(keys)  # its place in the key order is the one the README's runs were initialised with
    params = {
        "convs": convs,
        "visual": nn.linear.init(next(keys), fh * fw * fc, config.visual_dim),
        "state": nn.linear.init(next(keys), 6 if config.use_human_pos else 4, config.state_dim),
        "intentions": {
            name: nn.linear.init(next(keys), width, config.intention_dim)
            for name, width in intentions.items()
        },
        "lstm": nn.lstm.init(next(keys), lstm_in, config.hidden),
        # Small action head: the untrained policy commands ~0 velocity, not saturated tanh.
        "action_head": nn.linear.init(next(keys), config.hidden, 2, scale=0.01),
        "value_head": nn.linear.init(next(keys), config.hidden, 1),
        "log_std": jnp.full((2,), config.init_log_std, jnp.float32),
    }
    if config.uses_saliency:
        params["saliency"] = nn.linear.init(saliency_key, 2 * config.saliency_sectors, config.intention_dim)
    if config.visual_norm:  # no key drawn: every other parameter as without it
        params["visual_norm"] = nn.norm.init(None, config.visual_dim)
    if config.goal_image:
        params.update(_init_goal_encoder(jax.random.fold_in(key, _GOAL_KEY_FOLD), config))
    return params


def _init_goal_encoder(key: jax.Array, config: PolicyConfig) -> Params:
    """"goal_convs" and "goal" (flattened CNN features -> goal_dim) of the goal-image encoder."""
    n = len(config.goal_conv_channels)
    keys = jax.random.split(key, n + 1)
    in_ch = (3, *config.goal_conv_channels[:-1])
    convs = [nn.conv.init(k, i, o, s) for k, i, o, s in zip(keys, in_ch, config.goal_conv_channels, config.goal_conv_kernels)]
    image = jax.ShapeDtypeStruct((1, *config.goal_image_hw, 3), jnp.float32)
    _, fh, fw, fc = jax.eval_shape(_conv_stack, convs, image).shape
    return {"goal_convs": convs, "goal": nn.linear.init(keys[n], fh * fw * fc, config.goal_dim)}


def encode(params: Params, config: PolicyConfig, obs: Obs) -> jax.Array:
    """Per-step features fed to the LSTM: obs with leading dims `(...)` -> `(..., lstm_in)`.
    Reads `rgbd (..., H, W, 4)` (with the saliency channel also `segmentation (..., H, W)`), or
    in their place the keys `prepare_panorama` makes of them, `gps_compass (..., 3)`,
    `human_pos (..., 2)` (with use_human_pos), only the enabled intention keys and, with
    goal_image, `goal_image (..., H, W/4, 3)`."""
    panorama = obs if PANORAMA_IMAGE in obs else prepare_panorama(config, obs)
    feat = _conv_stack(params["convs"], panorama[PANORAMA_IMAGE], config.conv_compute_dtype, config.strides,
                       patches=first_layer_embeds_patches(config))
    feat = feat.reshape(*feat.shape[:-3], -1)
    visual = nn.linear.apply(params["visual"], feat)
    if config.visual_norm:
        visual = nn.norm.apply(params["visual_norm"], visual)
    visual = jax.nn.relu(visual)

    pose, scale = obs["gps_compass"], config.position_scale_m
    xy, yaw = pose[..., :2], pose[..., 2:]
    # Yaw as sin/cos: no jump at +-pi.
    state = [xy / scale, jnp.sin(yaw), jnp.cos(yaw)] + ([obs["human_pos"] / scale] if config.use_human_pos else [])
    state = jnp.concatenate(state, axis=-1)
    parts = [visual, jax.nn.relu(nn.linear.apply(params["state"], state))]
    for name in _intention_inputs(config):
        value = obs[name]
        if name == "future_traj":
            value = value.reshape(*value.shape[:-2], -1) / config.position_scale_m
        parts.append(jax.nn.relu(nn.linear.apply(params["intentions"][name], value)))
    if config.uses_saliency:
        parts.append(jax.nn.relu(nn.linear.apply(params["saliency"], panorama[PANORAMA_BEARING])))
    if config.goal_image:
        goal = _conv_stack(params["goal_convs"], obs["goal_image"].astype(jnp.float32), config.conv_compute_dtype)
        parts.append(jax.nn.relu(nn.linear.apply(params["goal"], goal.reshape(*goal.shape[:-3], -1))))
    return jnp.concatenate(parts, axis=-1)


def _heads(params: Params, h: jax.Array) -> tuple[jax.Array, jax.Array]:
    action = jnp.tanh(nn.linear.apply(params["action_head"], h))
    value = nn.linear.apply(params["value_head"], h)[..., 0]
    return action, value


def initial_carry(config: PolicyConfig, batch: int) -> LSTMState:
    """Zero LSTM carry, `h` and `c` each `(batch, hidden)`."""
    return nn.lstm.initial_state((batch,), config.hidden)


def apply(
    params: Params,
    config: PolicyConfig,
    obs: Obs,
    carry: LSTMState,
    reset: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array, LSTMState]:
    """One control step. obs values `(B, ...)`; `reset (B,)` bool zeroes the carry first (an
    episode starts here) -> `(action (B, 2) in [-1, 1], value (B,), new_carry)`."""
    if reset is not None:
        carry = nn.lstm.reset_state(carry, reset)
    carry, h = nn.lstm.apply(params["lstm"], carry, encode(params, config, obs))
    action, value = _heads(params, h)
    return action, value, carry


def apply_sequence(
    params: Params,
    config: PolicyConfig,
    obs_seq: Obs,
    carry: LSTMState,
    resets: jax.Array | None = None,
    remat: bool = False,
    prepare: Callable[[Obs], Obs] | None = None,
    time_major: bool = False,
) -> tuple[jax.Array, jax.Array, LSTMState]:
    """A `T`-step rollout for truncated BPTT. obs values `(B, T, ...)`, `resets (B, T)` bool ->
    `(actions (B, T, 2), values (B, T), final_carry)`; equals calling `apply` step by step;
    with `time_major` every one of them `(T, B, ...)` instead (a rollout's own order: no
    transposition of the panoramas). The CNN runs once over all B*T frames; only the LSTM is
    scanned over time. With `remat` the CNN runs one time step at a time under
    `jax.checkpoint` and is recomputed for the gradient: activation memory of B frames instead
    of B*T. It is the faster update for large panoramas with the bfloat16 CNN, and float32
    112x448 windows of a few hundred sequences fit only with it (BENCHMARKS.md). `prepare` maps
    stored observations to the model's (e.g. compact uint8 panoramas to float rgbd); with
    `remat` it runs per step inside the checkpoint, so the widened frames never exist for all T
    steps at once."""
    prepare = prepare or (lambda obs: obs)
    time_axis = 0 if time_major else 1
    if remat:
        # The step's frames are sliced inside the checkpoint, so only the index is saved per
        # step and the inputs are neither copied nor widened to float32 whole.
        @jax.checkpoint
        def per_step(t):
            obs = jax.tree.map(lambda x: jax.lax.dynamic_index_in_dim(x, t, time_axis, keepdims=False), obs_seq)
            return encode(params, config, prepare(obs))

        num_steps = jax.tree.leaves(obs_seq)[0].shape[time_axis]
        features = jax.lax.map(per_step, jnp.arange(num_steps))  # (T, B, F)
    else:
        features = encode(params, config, prepare(obs_seq))
        features = features if time_major else jnp.swapaxes(features, 0, 1)  # (T, B, F)
    time_resets = resets if resets is None or time_major else jnp.swapaxes(resets, 0, 1)
    carry, hs = nn.lstm.lstm_scan(params["lstm"], carry, features, time_resets)
    actions, values = _heads(params, hs if time_major else jnp.swapaxes(hs, 0, 1))
    return actions, values, carry
