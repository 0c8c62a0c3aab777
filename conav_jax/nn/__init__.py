"""Hand-written neural-network layers as pure functions over plain parameter pytrees.

Each module is one layer: `init(key, ...sizes) -> params` (a dict of arrays) and
`apply(params, x, ...)`. Use them by module: `nn.linear.init(key, 3, 8)`, `nn.linear.apply(p, x)`.
"""

from conav_jax.nn import attention, conv, embedding, linear, lstm, mlp, norm

__all__ = ["attention", "conv", "embedding", "linear", "lstm", "mlp", "norm"]
