"""2-D convolution over NHWC images: `x (..., H, W, C_in) -> (..., H', W', C_out)`.

Kernel `w (kh, kw, C_in, C_out)` (HWIO), bias `b (C_out,)`; stride and padding are chosen at
apply time so the params stay arrays only. Built on `lax.conv_general_dilated`.
"""

from __future__ import annotations

import math
from typing import Literal

import jax
import jax.numpy as jnp
from jax import lax

Params = dict[str, jax.Array]
Padding = Literal["SAME", "VALID"]


def _pair(v: int | tuple[int, int]) -> tuple[int, int]:
    return (v, v) if isinstance(v, int) else tuple(v)


def init(
    key: jax.Array,
    in_channels: int,
    out_channels: int,
    kernel_size: int | tuple[int, int],
    *,
    dtype: jnp.dtype = jnp.float32,
) -> Params:
    """LeCun-normal kernel (fan-in = kh * kw * C_in) and zero bias."""
    kh, kw = _pair(kernel_size)
    fan_in = kh * kw * in_channels
    w = jax.random.normal(key, (kh, kw, in_channels, out_channels), dtype) / math.sqrt(fan_in)
    return {"w": w, "b": jnp.zeros((out_channels,), dtype)}


def apply(
    params: Params,
    x: jax.Array,
    *,
    stride: int | tuple[int, int] = 1,
    padding: Padding = "SAME",
) -> jax.Array:
    """`x (..., H, W, C_in) -> (..., H', W', C_out)`; leading dims are flattened into one batch.

    SAME: `H' = ceil(H / stride)`; VALID: `H' = (H - kh) // stride + 1`.
    """
    lead, image = x.shape[:-3], x.shape[-3:]
    y = lax.conv_general_dilated(
        x.reshape((-1, *image)),
        params["w"],
        window_strides=_pair(stride),
        padding=padding,
        dimension_numbers=("NHWC", "HWIO", "NHWC"),
    )
    y = y + params["b"]
    return y.reshape((*lead, *y.shape[1:]))
