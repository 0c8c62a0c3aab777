"""2-D convolution over NHWC images: `x (..., H, W, C_in) -> (..., H', W', C_out)`.

Kernel `w (kh, kw, C_in, C_out)` (HWIO), bias `b (C_out,)`; stride and padding are chosen at
apply time so the params stay arrays only. Built on `lax.conv_general_dilated`.

A convolution whose kernel equals its stride over an image it tiles exactly (SAME padding adds
nothing then) embeds non-overlapping patches: it runs as one matrix product over each patch's
pixels (`_conv_patches`), the same sums, where GPU convolution kernels starve on few input
channels.

Mixed precision (`compute_dtype`, e.g. bfloat16): the image, kernel and bias are rounded to it
and the output is in it, so a stack of such layers passes bfloat16 activations; GPU convolution
kernels accumulate bfloat16 products in float32. Parameters stay float32 (their gradients come
back in it through the casts). On GPUs this halves the convolutions' memory traffic, forward and
backward, and runs them on tensor cores.
"""

from __future__ import annotations

import functools
import math
from typing import Literal

import jax
import jax.numpy as jnp
from jax import lax
from jax import custom_batching

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


def _batch_of(args, batched, i):
    return [a[i] if b else a for a, b in zip(args, batched)]


@functools.lru_cache(maxsize=None)
def _convolution(stride: tuple[int, int], padding: Padding | tuple):
    """`(x (N, H, W, C), w (kh, kw, C, O)) -> (N, H', W', O)`, lax.conv_general_dilated's, with
    its own vmap rule. JAX batches a convolution whose kernel is batched (the runs of
    `train.live.train_live_seeds`, each with its own weights) as one grouped convolution, and
    GPU convolution kernels run grouped convolutions' weight gradients far slower than the
    groups' ungrouped convolutions one after another. Here a batched kernel runs as that many
    ungrouped convolutions, forward and backward, the same ones a lone run takes; a batched
    image alone joins the convolution's own batch. Unbatched, the same program as the plain
    convolution and its autodiff."""

    def plain(x, w):
        return lax.conv_general_dilated(x, w, window_strides=stride, padding=padding,
                                        dimension_numbers=("NHWC", "HWIO", "NHWC"))

    forward = custom_batching.custom_vmap(plain)

    @forward.def_vmap
    def _forward_batched(axis_size, in_batched, x, w):
        if in_batched[1]:
            return jnp.stack([forward(*_batch_of((x, w), in_batched, i)) for i in range(axis_size)]), True
        y = forward(x.reshape(-1, *x.shape[2:]), w)
        return y.reshape(axis_size, -1, *y.shape[1:]), True

    def gradients(x, w, g):
        return jax.vjp(plain, x, w)[1](g)

    backward = custom_batching.custom_vmap(gradients)

    @backward.def_vmap
    def _backward_batched(axis_size, in_batched, x, w, g):
        if in_batched[1]:
            grads = [backward(*_batch_of((x, w, g), in_batched, i)) for i in range(axis_size)]
            return tuple(jnp.stack(parts) for parts in zip(*grads)), (True, True)
        # A kernel shared by the batch (a per-example gradient): each example's kernel gradient
        # is its own, so JAX's batching of the plain gradient.
        axes = tuple(0 if b else None for b in in_batched)
        return jax.vmap(gradients, in_axes=axes)(x, w, g), (True, True)

    @jax.custom_vjp
    def convolution(x, w):
        return forward(x, w)

    convolution.defvjp(lambda x, w: (forward(x, w), (x, w)), lambda res, g: backward(*res, g))
    return convolution


def _conv(x: jax.Array, w: jax.Array, stride: tuple[int, int], padding: Padding) -> jax.Array:
    return _convolution(stride, padding)(x, w)


def _space_to_depth(x: jax.Array) -> jax.Array:
    """`(N, H, W, C) -> (N, H / 2, W / 2, 4C)`: each 2x2 block of pixels as one pixel, the
    block's row parity major, then its column parity, then the channel."""
    n, h, w, c = x.shape
    return x.reshape(n, h // 2, 2, w // 2, 2, c).transpose(0, 1, 3, 2, 4, 5).reshape(n, h // 2, w // 2, 4 * c)


def _block_kernel(w: jax.Array, pad_lo: tuple[int, int]) -> tuple[jax.Array, tuple[tuple[int, int], ...]]:
    """A stride-2 kernel `w (kh, kw, C, O)` whose input starts `pad_lo` pixels before the first
    as a stride-1 kernel over 2x2 blocks (`_space_to_depth`), and that conv's padding in blocks.
    Output i of the stride-2 conv reads pixel u = 2i - lo + t with tap t, i.e. block
    floor(u / 2) at parity u mod 2: tap t lands at block offset d = floor((t - lo) / 2), parity
    (t - lo) mod 2, so the block kernel spans offsets d_min..d_max and is zero where no tap lands."""
    taps = []
    for k, lo in zip(w.shape[:2], pad_lo):
        d_min, d_max = (0 - lo) // 2, (k - 1 - lo) // 2
        # index[d - d_min, parity] = the tap that lands there, k (a zero row appended) where none.
        index = [[2 * d + p + lo if 0 <= 2 * d + p + lo < k else k for p in (0, 1)] for d in range(d_min, d_max + 1)]
        taps.append((jnp.asarray(index), (-d_min, d_max)))
    (rows, pad_h), (cols, pad_w) = taps
    c, o = w.shape[2:]
    padded = jnp.pad(w, ((0, 1), (0, 1), (0, 0), (0, 0)))  # the zero tap
    blocks = padded[rows[:, :, None, None], cols[None, None, :, :]]  # (bh, 2, bw, 2, C, O)
    bh, bw = rows.shape[0], cols.shape[0]
    return blocks.transpose(0, 2, 1, 3, 4, 5).reshape(bh, bw, 4 * c, o), (pad_h, pad_w)


def _conv_space_to_depth(x: jax.Array, w: jax.Array) -> jax.Array:
    """The stride-2 SAME convolution of `x (N, H, W, C)`, H and W even, as a stride-1
    convolution over its 2x2 blocks: the same products and sums with 4x the input channels, in
    which GPU convolution kernels run several times faster when C is small. C is zero-padded to
    a multiple of 8 first (zero channels add nothing; whole tensor-core tiles)."""
    kh, kw = w.shape[:2]
    # XLA's SAME padding for stride 2 and even n: k - 2 in all, the smaller half first.
    pad_lo = tuple(max(k - 2, 0) // 2 for k in (kh, kw))
    extra = -x.shape[-1] % 8
    if extra:
        x = jnp.pad(x, ((0, 0), (0, 0), (0, 0), (0, extra)))
        w = jnp.pad(w, ((0, 0), (0, 0), (0, extra), (0, 0)))
    kernel, block_pad = _block_kernel(w, pad_lo)
    return _convolution((1, 1), block_pad)(_space_to_depth(x), kernel)


def _tiles(kernel: tuple[int, int], stride: tuple[int, int], image: tuple[int, ...]) -> bool:
    """Whether a convolution is a patch embedding: kernel == stride, and the image's sides are
    multiples of it (then SAME and VALID both pad nothing and leave no pixel over)."""
    return kernel == stride and image[0] % stride[0] == 0 and image[1] % stride[1] == 0


def to_patches(x: jax.Array, kernel: int | tuple[int, int]) -> jax.Array:
    """`x (..., H, W, C) -> (..., H / kh, W / kw, kh * kw * C)`, H and W multiples of the
    kernel: each non-overlapping kh x kw patch flattened row by row, as a kernel is. The input
    of `apply_to_patches`; a caller that keeps images for several passes of a patch embedding
    (a training window) lays them out once here instead of on every pass."""
    kh, kw = _pair(kernel)
    *lead, h, wd, c = x.shape
    if h % kh or wd % kw:
        raise ValueError(f"to_patches needs an image whose sides are multiples of the kernel {kh}x{kw}, got {h}x{wd}")
    x = x.reshape(-1, h // kh, kh, wd // kw, kw, c).transpose(0, 1, 3, 2, 4, 5)
    return x.reshape(*lead, h // kh, wd // kw, kh * kw * c)


def apply_to_patches(params: Params, patches: jax.Array, *, compute_dtype: jnp.dtype | None = None) -> jax.Array:
    """The patch embedding (kernel = stride) of an image laid out by `to_patches`: `patches
    (..., H', W', kh * kw * C_in) -> (..., H', W', C_out)`, the same sums as `apply` on the image.
    `compute_dtype` as `apply`'s."""
    w, b = params["w"], params["b"]
    if patches.shape[-1] != math.prod(w.shape[:3]):
        raise ValueError(f"patches of {patches.shape[-1]} values do not fit a {w.shape[0]}x{w.shape[1]} kernel over "
                         f"{w.shape[2]} channels")
    if compute_dtype is not None:
        patches, w, b = patches.astype(compute_dtype), w.astype(compute_dtype), b.astype(compute_dtype)
    return jnp.dot(patches, w.reshape(-1, w.shape[-1])) + b


def _conv_patches(x: jax.Array, w: jax.Array) -> jax.Array:
    """The convolution of `x (N, H, W, C)` by `w (kh, kw, C, O)` at stride (kh, kw), H and W
    multiples of them: each kh x kw patch, flattened row by row as the kernel is, times the
    flattened kernel."""
    return jnp.dot(to_patches(x, w.shape[:2]), w.reshape(-1, w.shape[-1]))


def apply(
    params: Params,
    x: jax.Array,
    *,
    stride: int | tuple[int, int] = 1,
    padding: Padding = "SAME",
    compute_dtype: jnp.dtype | None = None,
    space_to_depth: bool = False,
) -> jax.Array:
    """`x (..., H, W, C_in) -> (..., H', W', C_out)`; leading dims are flattened into one batch.

    SAME: `H' = ceil(H / stride)`; VALID: `H' = (H - kh) // stride + 1`. A kernel equal to
    its stride over an image it tiles runs as a patch embedding (module docstring). `compute_dtype`
    (e.g. `jnp.bfloat16`): the image and kernel are rounded to it and the output and bias are
    in it (module docstring); None: it runs in the dtype of `x` and the params.
    `space_to_depth`: a stride-2 SAME convolution of an image with even H and W runs as a
    stride-1 convolution over its 2x2 blocks (`_conv_space_to_depth`; the same sums, faster on
    GPUs for images of few channels); ValueError for any other convolution.
    """
    lead, image = x.shape[:-3], x.shape[-3:]
    x = x.reshape((-1, *image))
    w, b = params["w"], params["b"]
    if compute_dtype is not None:
        x, w, b = x.astype(compute_dtype), w.astype(compute_dtype), b.astype(compute_dtype)
    if space_to_depth:
        if _pair(stride) != (2, 2) or padding != "SAME" or image[0] % 2 or image[1] % 2:
            raise ValueError("space_to_depth needs a stride-2 SAME convolution of an image with even height and "
                             f"width; got stride {stride}, {padding}, image {image[0]}x{image[1]}")
        y = _conv_space_to_depth(x, w)
    elif _tiles(w.shape[:2], _pair(stride), image):
        y = _conv_patches(x, w)
    else:
        y = _conv(x, w, _pair(stride), padding)
    y = y + b
    return y.reshape((*lead, *y.shape[1:]))
