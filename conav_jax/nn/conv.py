"""2-D convolution over NHWC images: `x (..., H, W, C_in) -> (..., H', W', C_out)`.

Kernel `w (kh, kw, C_in, C_out)` (HWIO), bias `b (C_out,)`; stride and padding are chosen at
apply time so the params stay arrays only. Built on `lax.conv_general_dilated`.

Mixed precision (`compute_dtype`, e.g. bfloat16): the image and kernel are rounded to it for
the convolution, which accumulates in and returns float32; parameters stay float32. On GPUs
this halves the convolution's memory traffic and runs it on tensor cores.
"""

from __future__ import annotations

import functools
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


def _conv(x: jax.Array, w: jax.Array, stride: tuple[int, int], padding: Padding, out_dtype=None) -> jax.Array:
    return lax.conv_general_dilated(
        x, w, window_strides=stride, padding=padding, dimension_numbers=("NHWC", "HWIO", "NHWC"),
        preferred_element_type=out_dtype,
    )


# `x` and `w` in a low-precision dtype, float32 out. JAX's transpose rules would widen the
# operands to the float32 gradient's dtype, so the backward pass (two of the three convolutions
# of an update) would run in float32. This VJP rounds the incoming gradient to the operands'
# dtype instead, so all three run in it (GPUs accumulate such convolutions in float32); the
# image and kernel gradients come back in it and `apply`'s casts widen them to float32.
@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def _mixed_conv(x: jax.Array, w: jax.Array, stride: tuple[int, int], padding: Padding) -> jax.Array:
    return _conv(x, w, stride, padding, jnp.float32)


def _mixed_conv_fwd(x, w, stride, padding):
    return _mixed_conv(x, w, stride, padding), (x, w)  # residuals low-precision: half the memory


def _mixed_conv_bwd(stride, padding, residuals, g):
    x, w = residuals
    _, vjp = jax.vjp(lambda x, w: _conv(x, w, stride, padding), x, w)
    return vjp(g.astype(x.dtype))


_mixed_conv.defvjp(_mixed_conv_fwd, _mixed_conv_bwd)


def apply(
    params: Params,
    x: jax.Array,
    *,
    stride: int | tuple[int, int] = 1,
    padding: Padding = "SAME",
    compute_dtype: jnp.dtype | None = None,
) -> jax.Array:
    """`x (..., H, W, C_in) -> (..., H', W', C_out)`; leading dims are flattened into one batch.

    SAME: `H' = ceil(H / stride)`; VALID: `H' = (H - kh) // stride + 1`. `compute_dtype`
    (e.g. `jnp.bfloat16`): the convolution's operands are rounded to it and it returns float32
    (module docstring); None: it runs in the dtype of `x` and the params.
    """
    lead, image = x.shape[:-3], x.shape[-3:]
    x = x.reshape((-1, *image))
    if compute_dtype is None:
        y = _conv(x, params["w"], _pair(stride), padding)
    else:
        y = _mixed_conv(x.astype(compute_dtype), params["w"].astype(compute_dtype), _pair(stride), padding)
    y = y + params["b"]
    return y.reshape((*lead, *y.shape[1:]))
