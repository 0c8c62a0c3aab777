"""CoNav LSTM policy (paper sec. 4.2): panorama + pose + human position + intentions -> action.

obs -> CNN(rgbd) -> flatten -> linear; pose (x, y, sin yaw, cos yaw) and human position ->
linear; each enabled intention input (activity probs, object probs, future trajectory) ->
its own linear -> concat -> LSTM -> `action (B, 2)` in [-1, 1] (tanh) and `value (B,)`.
Disabled intention inputs (the paper's Table 3 ablation) are never read and have no weights.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import jax
import jax.numpy as jnp

from conav_jax import nn
from conav_jax.nn.lstm import LSTMState

Params = dict
Obs = dict[str, jax.Array]

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

    image_hw: tuple[int, int] = (112, 448)  # panorama (H, W) in pixels
    conv_channels: tuple[int, ...] = (16, 32, 32, 64)  # one stride-2 SAME conv per entry
    conv_kernels: tuple[int, ...] = (5, 3, 3, 3)
    visual_dim: int = 256  # flattened CNN features -> this width
    state_dim: int = 32  # pose + human position embedding width
    intention_dim: int = 32  # embedding width of each enabled intention input
    hidden: int = 256  # LSTM width
    max_depth_m: float = 10.0  # depth is divided by this and clipped to [0, 1]
    position_scale_m: float = 10.0  # positions (pose, human, trajectory) are divided by this
    num_activities: int = 107
    num_objects: int = 51
    horizon: int = 5  # future trajectory length
    use_activity: bool = True
    use_object: bool = True
    use_trajectory: bool = True
    init_log_std: float = -0.5  # initial action log-std (PPO only)


def ablation_config(base: PolicyConfig, name: str) -> PolicyConfig:
    """`base` with the intention switches of a Table 3 row: none | activity | object |
    activity_object | all."""
    if name not in ABLATIONS:
        raise ValueError(f"unknown ablation {name!r}; expected one of {sorted(ABLATIONS)}")
    act, obj, traj = ABLATIONS[name]
    return dataclasses.replace(base, use_activity=act, use_object=obj, use_trajectory=traj)


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


def _conv_stack(params: list, x: jax.Array) -> jax.Array:
    """Stride-2 SAME convs with ReLU: `(..., H, W, 4) -> (..., ~H / 2^n, ~W / 2^n, C_last)`."""
    for layer in params:
        x = jax.nn.relu(nn.conv.apply(layer, x, stride=2, padding="SAME"))
    return x


def init(key: jax.Array, config: PolicyConfig) -> Params:
    """Parameters for `config`; the CNN output size is derived by shape evaluation."""
    if len(config.conv_channels) != len(config.conv_kernels):
        raise ValueError("conv_channels and conv_kernels need one entry per conv layer")
    intentions = _intention_inputs(config)
    keys = iter(jax.random.split(key, len(config.conv_channels) + 5 + len(intentions)))
    in_ch = (4, *config.conv_channels[:-1])
    convs = [
        nn.conv.init(next(keys), i, o, k)
        for i, o, k in zip(in_ch, config.conv_channels, config.conv_kernels)
    ]
    image = jax.ShapeDtypeStruct((1, *config.image_hw, 4), jnp.float32)
    _, fh, fw, fc = jax.eval_shape(_conv_stack, convs, image).shape
    lstm_in = config.visual_dim + config.state_dim + config.intention_dim * len(intentions)
    return {
        "convs": convs,
        "visual": nn.linear.init(next(keys), fh * fw * fc, config.visual_dim),
        "state": nn.linear.init(next(keys), 6, config.state_dim),
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


def encode(params: Params, config: PolicyConfig, obs: Obs) -> jax.Array:
    """Per-step features fed to the LSTM: obs with leading dims `(...)` -> `(..., lstm_in)`.
    Reads `rgbd (..., H, W, 4)`, `gps_compass (..., 3)`, `human_pos (..., 2)` and only the
    enabled intention keys."""
    rgbd = obs["rgbd"].astype(jnp.float32)  # float16 panoramas widen here, per call
    depth = jnp.clip(rgbd[..., 3:] / config.max_depth_m, 0.0, 1.0)
    image = jnp.concatenate([rgbd[..., :3], depth], axis=-1)
    feat = _conv_stack(params["convs"], image)
    feat = feat.reshape(*feat.shape[:-3], -1)
    visual = jax.nn.relu(nn.linear.apply(params["visual"], feat))

    pose, scale = obs["gps_compass"], config.position_scale_m
    xy, yaw = pose[..., :2], pose[..., 2:]
    # Yaw as sin/cos: no jump at +-pi.
    state = jnp.concatenate([xy / scale, jnp.sin(yaw), jnp.cos(yaw), obs["human_pos"] / scale], axis=-1)
    parts = [visual, jax.nn.relu(nn.linear.apply(params["state"], state))]
    for name in _intention_inputs(config):
        value = obs[name]
        if name == "future_traj":
            value = value.reshape(*value.shape[:-2], -1) / config.position_scale_m
        parts.append(jax.nn.relu(nn.linear.apply(params["intentions"][name], value)))
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
) -> tuple[jax.Array, jax.Array, LSTMState]:
    """A `T`-step rollout for truncated BPTT. obs values `(B, T, ...)`, `resets (B, T)` bool ->
    `(actions (B, T, 2), values (B, T), final_carry)`; equals calling `apply` step by step.
    The CNN runs once over all B*T frames; only the LSTM is scanned over time. With `remat`
    the CNN runs one time step at a time under `jax.checkpoint` and is recomputed for the
    gradient: activation memory of B frames instead of B*T, for 1.7x the update's time at
    32x128 on an H100 (112x448 windows of 32 steps do not fit an H100 at batch 256 without
    it; with it they run at batch 1024; BENCHMARKS.md). `prepare` maps stored observations to
    the model's (e.g. compact uint8 panoramas to float rgbd); with `remat` it runs per step
    inside the checkpoint, so the widened frames never exist for all T steps at once."""
    prepare = prepare or (lambda obs: obs)
    if remat:
        # The step's frames are sliced inside the checkpoint, so only the index is saved per
        # step and the (B, T, ...) inputs are neither copied nor widened to float32 whole.
        @jax.checkpoint
        def per_step(t):
            obs = jax.tree.map(lambda x: jax.lax.dynamic_index_in_dim(x, t, 1, keepdims=False), obs_seq)
            return encode(params, config, prepare(obs))

        num_steps = jax.tree.leaves(obs_seq)[0].shape[1]
        features = jax.lax.map(per_step, jnp.arange(num_steps))  # (T, B, F)
    else:
        features = jnp.swapaxes(encode(params, config, prepare(obs_seq)), 0, 1)  # (T, B, F)
    time_resets = None if resets is None else jnp.swapaxes(resets, 0, 1)
    carry, hs = nn.lstm.lstm_scan(params["lstm"], carry, features, time_resets)
    actions, values = _heads(params, jnp.swapaxes(hs, 0, 1))
    return actions, values, carry
