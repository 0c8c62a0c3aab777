"""Adam and AdamW (Kingma & Ba 2015; Loshchilov & Hutter 2019) with bias correction.

`opt = adam(lr)`; `state = opt.init(params)`; `params, state = opt.update(grads, state, params)`.
The learning rate is a float or a schedule `step -> lr` evaluated at the pre-update step count.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from conav_jax.optim.schedule import Schedule

PyTree = Any


class AdamState(NamedTuple):
    """`step`: int32 scalar, updates applied so far; `mu`, `nu`: first and second moment
    estimates, pytrees shaped like the params."""

    step: jax.Array
    mu: PyTree
    nu: PyTree


class Optimizer(NamedTuple):
    """A pair of pure functions, in the shape of `jax.example_libraries.optimizers`."""

    init: Callable[[PyTree], AdamState]
    update: Callable[[PyTree, AdamState, PyTree], tuple[PyTree, AdamState]]


def adam(
    learning_rate: float | Schedule,
    b1: float = 0.9,
    b2: float = 0.999,
    eps: float = 1e-8,
    weight_decay: float = 0.0,
) -> Optimizer:
    """Adam; with `weight_decay > 0` it is AdamW (decay decoupled from the gradient moments).

    Per leaf, with `t = step + 1` and `lr = learning_rate(step)`:
    `mu = b1 mu + (1 - b1) g`, `nu = b2 nu + (1 - b2) g^2`,
    `p -= lr * (mu / (1 - b1^t) / (sqrt(nu / (1 - b2^t)) + eps) + weight_decay * p)`.
    The decay is scaled by `lr` (as in PyTorch's AdamW), so a schedule anneals it too.
    It applies to every leaf; keep it 0 if biases and norms should not decay.
    """
    lr_fn = learning_rate if callable(learning_rate) else (lambda _: learning_rate)

    def init(params: PyTree) -> AdamState:
        # Two trees of their own: a program that donates its state may not be given one buffer twice.
        mu, nu = (jax.tree_util.tree_map(jnp.zeros_like, params) for _ in range(2))
        return AdamState(jnp.zeros((), jnp.int32), mu, nu)

    def update(grads: PyTree, state: AdamState, params: PyTree) -> tuple[PyTree, AdamState]:
        t = state.step + 1
        lr = lr_fn(state.step)
        mu = jax.tree_util.tree_map(lambda m, g: b1 * m + (1 - b1) * g, state.mu, grads)
        nu = jax.tree_util.tree_map(lambda v, g: b2 * v + (1 - b2) * jnp.square(g), state.nu, grads)
        c1 = 1 - b1 ** t.astype(jnp.float32)
        c2 = 1 - b2 ** t.astype(jnp.float32)

        def step_leaf(p: jax.Array, m: jax.Array, v: jax.Array) -> jax.Array:
            delta = (m / c1) / (jnp.sqrt(v / c2) + eps) + weight_decay * p
            return (p - lr * delta).astype(p.dtype)

        new_params = jax.tree_util.tree_map(step_leaf, params, mu, nu)
        return new_params, AdamState(t, mu, nu)

    return Optimizer(init, update)


def adamw(
    learning_rate: float | Schedule,
    weight_decay: float = 1e-2,
    b1: float = 0.9,
    b2: float = 0.999,
    eps: float = 1e-8,
) -> Optimizer:
    """AdamW: `adam` with decoupled weight decay (default 0.01, PyTorch's default)."""
    return adam(learning_rate, b1=b1, b2=b2, eps=eps, weight_decay=weight_decay)
