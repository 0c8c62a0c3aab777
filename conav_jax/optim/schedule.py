"""Learning-rate schedules: functions `step -> lr`, jittable on a traced integer step.

`step` counts updates already applied (0 for the first update), as `AdamState.step` does.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

Schedule = Callable[[jax.Array | int], jax.Array]


def warmup_cosine(
    peak_lr: float, warmup_steps: int, total_steps: int, final_lr: float = 0.0
) -> Schedule:
    """Linear warm-up from 0 to `peak_lr` over `warmup_steps`, then half-cosine decay to
    `final_lr` at `total_steps`, constant after.

    `lr(s) = peak * s / warmup` for `s < warmup`;
    `lr(s) = final + (peak - final) * (1 + cos(pi * (s - warmup) / (total - warmup))) / 2` up to
    `total`. With `warmup_steps=0` the schedule starts at `peak_lr`.
    """
    if not 0 <= warmup_steps <= total_steps:
        raise ValueError(f"need 0 <= warmup_steps <= total_steps, got {warmup_steps}, {total_steps}")

    def schedule(step: jax.Array | int) -> jax.Array:
        s = jnp.asarray(step, jnp.float32)
        warm = peak_lr * s / max(warmup_steps, 1)
        frac = jnp.clip((s - warmup_steps) / max(total_steps - warmup_steps, 1), 0.0, 1.0)
        cosine = final_lr + (peak_lr - final_lr) * 0.5 * (1.0 + jnp.cos(jnp.pi * frac))
        return jnp.where(s < warmup_steps, warm, cosine)

    return schedule
