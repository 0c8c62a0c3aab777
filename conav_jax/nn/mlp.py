"""Multi-layer perceptron: a stack of dense layers with an activation between them.

`x (..., sizes[0]) -> (..., sizes[-1])`; params `{"layers": [linear params, ...]}`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax

from conav_jax.nn import linear

Params = dict[str, list[linear.Params]]


def init(key: jax.Array, sizes: Sequence[int], **linear_kwargs) -> Params:
    """One dense layer per consecutive pair in `sizes` (e.g. `(64, 128, 64)` = 2 layers).
    `linear_kwargs` (scheme, scale, dtype) apply to every layer."""
    if len(sizes) < 2:
        raise ValueError(f"an MLP needs at least input and output sizes, got {tuple(sizes)}")
    keys = jax.random.split(key, len(sizes) - 1)
    return {
        "layers": [
            linear.init(k, i, o, **linear_kwargs) for k, i, o in zip(keys, sizes[:-1], sizes[1:])
        ]
    }


def apply(
    params: Params,
    x: jax.Array,
    *,
    activation: Callable[[jax.Array], jax.Array] = jax.nn.gelu,
) -> jax.Array:
    """Activation after every layer but the last (the output stays linear)."""
    layers = params["layers"]
    for layer in layers[:-1]:
        x = activation(linear.apply(layer, x))
    return linear.apply(layers[-1], x)
