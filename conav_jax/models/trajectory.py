"""Short-term intention predictor: the human's next 5 root positions from the last k.

history `(..., k, 2)` metres, any frame -> step deltas, rotated so the recent heading is +x and
scaled to ~unit size -> LSTM -> MLP -> 5 corrections to constant velocity -> rotated back and
accumulated from the last position -> `(..., 5, 2)` in the input frame. The correction head
starts at zero, so an untrained model is exactly the constant-velocity baseline.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from conav_jax import nn

Params = dict


@dataclass(frozen=True)
class TrajectoryConfig:
    """Sizes of the trajectory predictor."""

    history: int = 8  # k past positions, the current one included
    horizon: int = 5  # future positions predicted, one per control step
    hidden: int = 64  # LSTM and MLP width
    step_scale_m: float = 0.1  # typical step length (1 m/s at 0.1 s): deltas are divided by it
    min_heading_m: float = 1e-3  # below this displacement over the history, no rotation


def init(key: jax.Array, config: TrajectoryConfig) -> Params:
    """LSTM over 2-D deltas and an MLP head whose last layer is zero (constant velocity)."""
    k_lstm, k_mlp = jax.random.split(key)
    head = nn.mlp.init(k_mlp, (config.hidden, config.hidden, 2 * config.horizon))
    head["layers"][-1]["w"] = jnp.zeros_like(head["layers"][-1]["w"])
    return {"lstm": nn.lstm.init(k_lstm, 2, config.hidden), "head": head}


def _heading_frame(history: jax.Array, min_norm: float) -> jax.Array:
    """Rotation `(..., 2, 2)` whose rows are the unit heading (first to last position) and its
    left normal: `R @ v` expresses `v` in a frame where the human walks along +x. Identity
    when the human has barely moved, where the heading is noise."""
    disp = history[..., -1, :] - history[..., 0, :]
    norm = jnp.linalg.norm(disp, axis=-1, keepdims=True)
    moving = norm > min_norm
    u = jnp.where(moving, disp / jnp.where(moving, norm, 1.0), jnp.array([1.0, 0.0]))
    return jnp.stack([u, jnp.stack([-u[..., 1], u[..., 0]], -1)], axis=-2)


def apply(params: Params, config: TrajectoryConfig, history: jax.Array) -> jax.Array:
    """`history (..., k, 2)` metres, oldest first, k >= 2 -> `(..., horizon, 2)` metres, same frame.

    Only differences of positions enter the network, and they are rotated into the heading
    frame, so the prediction moves and turns with the input frame.
    """
    if history.shape[-2] < 2:
        raise ValueError(f"need at least 2 past positions, got history shape {history.shape}")
    rot = _heading_frame(history, config.min_heading_m)
    deltas = jnp.einsum("...ij,...tj->...ti", rot, jnp.diff(history, axis=-2))
    xs = jnp.moveaxis(deltas / config.step_scale_m, -2, 0)  # time-major for the scan
    carry = nn.lstm.initial_state(xs.shape[1:-1], config.hidden, xs.dtype)
    _, hs = nn.lstm.lstm_scan(params["lstm"], carry, xs)
    correction = nn.mlp.apply(params["head"], hs[-1]).reshape(*hs.shape[1:-1], config.horizon, 2)
    future_deltas = deltas[..., -1:, :] + config.step_scale_m * correction
    future_deltas = jnp.einsum("...ji,...tj->...ti", rot, future_deltas)  # back: R^T @ v
    return history[..., -1:, :] + jnp.cumsum(future_deltas, axis=-2)


def constant_velocity(history: jax.Array, horizon: int = 5) -> jax.Array:
    """Baseline: repeat the last step. `history (..., k, 2)` -> `(..., horizon, 2)`."""
    last = history[..., -1:, :]
    velocity = last - history[..., -2:-1, :]
    steps = jnp.arange(1, horizon + 1, dtype=history.dtype)[:, None]
    return last + steps * velocity


def ade_fde(pred: jax.Array, target: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Average and final displacement error per sample, metres: `(..., T, 2)` x 2 -> `(...)`, `(...)`.
    Take `.mean()` for the dataset figures."""
    dist = jnp.linalg.norm(pred - target, axis=-1)
    return jnp.mean(dist, axis=-1), dist[..., -1]
