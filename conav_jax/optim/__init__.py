"""Hand-written optimisation: Adam/AdamW, global-norm gradient clipping, learning-rate schedules.

An optimizer is `init(params) -> state` and `update(grads, state, params) -> (params, state)`;
its state is a pytree, so it jits, shards and checkpoints like the params.
"""

from conav_jax.optim.adam import AdamState, Optimizer, adam, adamw
from conav_jax.optim.clip import clip_by_global_norm, global_norm
from conav_jax.optim.schedule import Schedule, warmup_cosine

__all__ = [
    "AdamState",
    "Optimizer",
    "Schedule",
    "adam",
    "adamw",
    "clip_by_global_norm",
    "global_norm",
    "warmup_cosine",
]
