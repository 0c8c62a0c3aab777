"""A generic, resumable training loop for our `init/apply` models (purejaxrl-style).

data (dict of `(N, ...)` arrays, put on the device once) -> minibatch indices drawn from
`(seed, step)` -> `loss_fn` -> clipped gradients -> Adam(W) on a warm-up + cosine schedule,
`log_every` updates per jitted `lax.scan` chunk -> scalars to Python -> log.jsonl, tqdm,
validation and atomic checkpoints. The batch of update `s` depends only on `(seed, s)`, so a
run resumed from a checkpoint draws exactly the batches an uninterrupted run would. With a
device mesh (conav_jax.parallel) the data, parameters and optimiser state are replicated and
each gathered minibatch is split over the devices: the same batches, the same losses.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from tqdm import tqdm

from conav_jax.checkpoints import checkpoint_path, latest_checkpoint, save_checkpoint
from conav_jax.optim import Optimizer, adam, clip_by_global_norm, warmup_cosine
from conav_jax.parallel import check_divisible, constrain_batch, replicate, replicated
from conav_jax.runs import LOG_FILE, append_log, finite_or_none, resume

PyTree = Any
# loss_fn(params, batch, key) -> (scalar loss, dict of scalar metrics to log). `batch` is `data`
# indexed on its leading axis by `batch` sample indices; `key` is for per-sample randomness.
LossFn = Callable[[PyTree, dict, jax.Array], tuple[jax.Array, dict]]
# Fields that only change how often things happen, not the trained weights: they may differ
# between a run and its resumption.
CADENCE_FIELDS = ("log_every", "val_every", "ckpt_every")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation and bookkeeping of one training run."""

    steps: int = 2000  # total updates (a resumed run continues up to this count)
    batch: int = 64  # samples per update, drawn uniformly with replacement
    lr: float = 1e-3  # peak learning rate
    warmup_steps: int = 100  # linear warm-up, then cosine decay to 0 at `steps`
    weight_decay: float = 0.0  # > 0 makes Adam AdamW (decoupled, every leaf)
    grad_clip: float = 1.0  # global L2 norm limit of the gradient
    seed: int = 0  # fixes every minibatch and every loss-side random draw
    log_every: int = 50  # updates per jitted chunk; train scalars are logged after each
    val_every: int = 500  # updates between validations (and one at the end)
    ckpt_every: int = 1000  # updates between checkpoints (and one at the end)

    def __post_init__(self):
        for name in ("steps", "batch", "log_every", "val_every", "ckpt_every"):
            if getattr(self, name) <= 0:
                raise ValueError(f"TrainConfig.{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.warmup_steps <= self.steps:
            raise ValueError(f"TrainConfig.warmup_steps must be in [0, steps={self.steps}], got {self.warmup_steps}")
        if self.lr <= 0 or self.grad_clip <= 0 or self.weight_decay < 0:
            raise ValueError(
                f"need lr > 0, grad_clip > 0, weight_decay >= 0; got {self.lr}, {self.grad_clip}, {self.weight_decay}"
            )

    def optimisation(self) -> dict:
        """The fields that determine the trained weights (stored in, and checked against, the
        checkpoint's config)."""
        return {k: v for k, v in dataclasses.asdict(self).items() if k not in CADENCE_FIELDS}


class StepInfo(NamedTuple):
    """What one update reports: `loss` and `grad_norm` (before clipping) scalars, the loss's
    `aux` metrics, and the batch's sample indices `(batch,)`."""

    loss: jax.Array
    grad_norm: jax.Array
    aux: dict
    indices: jax.Array


class NonFiniteLoss(FloatingPointError):
    """A loss or gradient turned inf/NaN; carries the update step and the batch's indices."""

    def __init__(self, message: str, step: int, indices: list[int]):
        super().__init__(message)
        self.step, self.indices = step, indices


class TrainResult(NamedTuple):
    """What `train` returns: the final state and the last validation metrics."""

    params: PyTree
    opt_state: PyTree
    step: int  # updates applied
    val: dict  # the last validation metrics ({} without val_fn)
    run_dir: Path


def make_optimizer(cfg: TrainConfig) -> Optimizer:
    return adam(warmup_cosine(cfg.lr, cfg.warmup_steps, cfg.steps), weight_decay=cfg.weight_decay)


def num_samples(data: PyTree) -> int:
    """Common leading size N of every array in `data` (a dict, possibly nested); ValueError if
    they differ or N = 0."""
    leaves, _ = jax.tree_util.tree_flatten_with_path(data)
    sizes = {jax.tree_util.keystr(p): int(np.shape(x)[0]) if np.ndim(x) else -1 for p, x in leaves}
    if not sizes or len(set(sizes.values())) != 1 or min(sizes.values()) <= 0:
        raise ValueError(f"data arrays need one common, non-zero leading size; got {sizes}")
    return next(iter(sizes.values()))


def make_update(loss_fn: LossFn, optimizer: Optimizer, cfg: TrainConfig, n: int, mesh: Mesh | None = None):
    """`update(params, opt_state, data) -> (params, opt_state, StepInfo)`: one pure training
    step (its aux gains the learning rate "lr" it used). The step index is `opt_state.step`;
    minibatch indices and the loss's key derive from `(cfg.seed, step)` alone. With a `mesh`
    the gathered minibatch is split over its devices."""
    base = jax.random.PRNGKey(cfg.seed)
    schedule = warmup_cosine(cfg.lr, cfg.warmup_steps, cfg.steps)

    def update(params, opt_state, data):
        k_idx, k_loss = jax.random.split(jax.random.fold_in(base, opt_state.step))
        idx = jax.random.randint(k_idx, (cfg.batch,), 0, n)
        batch = constrain_batch(jax.tree.map(lambda x: jnp.take(x, idx, axis=0), data), mesh)
        (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, batch, k_loss)
        grads, grad_norm = clip_by_global_norm(grads, cfg.grad_clip)
        lr = schedule(opt_state.step)
        params, opt_state = optimizer.update(grads, opt_state, params)
        return params, opt_state, StepInfo(loss, grad_norm, {**aux, "lr": lr}, idx)

    return update


def make_chunk(update, batch: int):
    """`chunk(params, opt_state, data, length) -> (params, opt_state, bad_step, bad_indices,
    sums)`: `length` updates in one `lax.scan`. The first update whose loss or gradient norm is
    not finite is not applied, nor is any after it: `bad_step` is its step (-1 if none),
    `bad_indices` its batch, and the returned state the last good one. `sums` holds the sums
    of loss, grad norm and aux over the applied updates, and their count `n`."""

    def chunk(params, opt_state, data, length):
        init = (params, opt_state, jnp.int32(-1), jnp.zeros((batch,), jnp.int32))
        (params, opt_state, bad_step, bad_idx), (ok, scalars) = jax.lax.scan(
            lambda carry, _: guarded(update, carry, data), init, None, length)
        sums = {k: jnp.sum(jnp.where(ok, v, 0.0)) for k, v in scalars.items()}
        sums["n"] = jnp.sum(ok)
        return params, opt_state, bad_step, bad_idx, sums

    return chunk


def make_single(update, batch: int):
    """`single(params, opt_state, data, bad_step, bad_indices, sums) -> the same, one update
    later`: `make_chunk`'s body as one call, its non-finite guard and running sums carried by
    the caller on the device (so calls queue up without a host sync). For XLA:CPU, where a
    convolution's update inside a scan runs many times slower than the same update alone."""

    def single(params, opt_state, data, bad_step, bad_idx, sums):
        (params, opt_state, bad_step, bad_idx), (ok, scalars) = guarded(update, (params, opt_state, bad_step, bad_idx), data)
        sums = {**{k: sums[k] + jnp.where(ok, v, 0.0) for k, v in scalars.items()}, "n": sums["n"] + ok}
        return params, opt_state, bad_step, bad_idx, sums

    return single


def guarded(update, carry, data):
    """One update unless an earlier one was not finite: `carry` = (params, opt_state, bad_step,
    bad_indices) -> (the new carry, (applied, scalars))."""
    params, opt_state, bad_step, bad_idx = carry
    new_params, new_opt, info = update(params, opt_state, data)
    finite = jnp.isfinite(info.loss) & jnp.isfinite(info.grad_norm)
    ok = finite & (bad_step < 0)
    first_bad = ~finite & (bad_step < 0)
    params, opt_state = jax.tree.map(lambda new, old: jnp.where(ok, new, old), (new_params, new_opt), (params, opt_state))
    bad_step = jnp.where(first_bad, opt_state.step, bad_step)
    bad_idx = jnp.where(first_bad, info.indices, bad_idx)
    return (params, opt_state, bad_step, bad_idx), (ok, {"loss": info.loss, "grad_norm": info.grad_norm, **info.aux})


@functools.lru_cache(maxsize=16)
def _jitted(loss_fn: LossFn, cfg: TrainConfig, n: int, compiler_options: tuple, mesh: Mesh | None, scan: bool):
    """The jitted chunk (or single update), shared by runs of one process with the same loss,
    optimisation, data size and mesh (so a resumed or repeated run reuses its compiled code).
    With a mesh all its outputs (parameters, optimiser state, scalars) are replicated."""
    update = make_update(loss_fn, make_optimizer(cfg), cfg, n, mesh)
    options = dict(compiler_options) or None
    out = None if mesh is None else replicated(mesh)
    if scan:
        return jax.jit(make_chunk(update, cfg.batch), static_argnames="length", compiler_options=options, out_shardings=out), update
    return jax.jit(make_single(update, cfg.batch), compiler_options=options, out_shardings=out), update


def _next_boundary(step: int, cfg: TrainConfig) -> int:
    """The next step after `step` at which something is logged, validated or saved."""
    nxt = [(step // e + 1) * e for e in (cfg.log_every, cfg.val_every, cfg.ckpt_every)]
    return min(*nxt, cfg.steps)


def train(
    run_dir: str | Path,
    loss_fn: LossFn,
    params: PyTree,
    data: dict,
    cfg: TrainConfig,
    config: dict,
    val_fn: Callable[[PyTree], dict] | None = None,
    progress: bool = True,
    compiler_options: dict | None = None,
    mesh: Mesh | None = None,
    scan_updates: bool = True,
    resume_ignore: tuple[str, ...] = (),
    log_extra: dict | None = None,
    desc: str | None = None,
) -> TrainResult:
    """Train `params` on `data` for `cfg.steps` updates, resuming from `run_dir` if it holds a
    checkpoint.

    - `config`: JSON-able dict describing the run, with at least "kind" (e.g. "trajectory") and
      the model config; the checkpoint stores it plus `cfg.optimisation()` under "train". A
      resumed run must match it exactly, else ValueError naming the first differing key; the
      dotted keys in `resume_ignore` may differ (e.g. "train.steps": a longer schedule).
    - `data`: dict (may nest) of arrays sharing the leading size N, numpy or jax; put on the
      device once. `loss_fn` gets it indexed by `cfg.batch` sample indices.
    - `val_fn(params) -> dict of floats`, run every `cfg.val_every` updates and at the end.
    - `compiler_options`: passed to `jax.jit` (tests use a low XLA optimisation level).
    - `mesh` (conav_jax.parallel.make_mesh): data-parallel over its devices; `data`, params and
      optimiser state replicated, each minibatch split (ValueError unless `cfg.batch` divides
      by the device count). The same batches as without it, so the same losses up to the
      order of float sums.
    - `scan_updates`: updates between log points run as one `lax.scan` (one call); False runs
      each update as its own call, queued without a host sync (XLA:CPU runs a convolution's
      update in a scan many times slower). Same updates, same results.
    - `log_extra`: entries added to every log record (e.g. a DAgger round); `desc` labels the
      progress bar.
    Raises NonFiniteLoss (naming the step and the batch's sample indices) when a loss or
    gradient goes inf/NaN; nothing is saved then, so the last checkpoint stays the last good one.
    """
    if "kind" not in config:
        raise ValueError("config needs a 'kind' entry (e.g. 'trajectory', 'intention')")
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    log_path = run_dir / LOG_FILE
    full_config = {**config, "train": cfg.optimisation()}
    n = num_samples(data)
    if mesh is not None:
        check_divisible(cfg.batch, mesh, "TrainConfig.batch")
    data = jax.device_put(data) if mesh is None else replicate(data, mesh)
    opt_state = make_optimizer(cfg).init(params)
    extra = dict(log_extra or {})

    step = 0
    ckpt = resume(run_dir, full_config, params, opt_state, ignore=resume_ignore)
    if ckpt is not None:
        params, opt_state, step = ckpt.params, ckpt.opt_state, ckpt.step
    if mesh is not None:
        params, opt_state = replicate((params, opt_state), mesh)

    cadence_free = dataclasses.replace(cfg, **{k: 1 for k in CADENCE_FIELDS})
    compiled, update = _jitted(loss_fn, cadence_free, n, tuple(sorted((compiler_options or {}).items())), mesh, scan_updates)
    if not scan_updates:  # the guard's start and the running sums the single updates add to
        info = jax.eval_shape(update, params, opt_state, data)[2]
        zero_sums = {k: jnp.float32(0.0) for k in ("loss", "grad_norm", *info.aux)} | {"n": jnp.int32(0)}
        fresh_tail = (jnp.int32(-1), jnp.zeros((cfg.batch,), jnp.int32), zero_sums)
        if mesh is not None:  # placed as the update returns them, or its second call compiles again
            fresh_tail = replicate(fresh_tail, mesh)
    val: dict = {}

    def validate(at: int) -> None:
        nonlocal val
        val = {k: float(v) for k, v in val_fn(params).items()}
        append_log(log_path, {"step": at, "split": "val", **extra, **val})

    def run_updates(params, opt_state, length):
        if scan_updates:
            return compiled(params, opt_state, data, length=length)
        carry = (params, opt_state, *fresh_tail)
        for _ in range(length):
            carry = compiled(carry[0], carry[1], data, *carry[2:])
        return carry

    bar = tqdm(total=cfg.steps, initial=step, disable=not progress, unit="step", dynamic_ncols=True, desc=desc)
    start = time.perf_counter()
    try:
        while step < cfg.steps:
            end = _next_boundary(step, cfg)
            t0 = time.perf_counter()
            new_params, new_opt, bad_step, bad_idx, sums = run_updates(params, opt_state, end - step)
            bad = int(bad_step)  # the one sync per log interval
            if bad >= 0:
                indices = [int(i) for i in np.asarray(bad_idx)]
                append_log(log_path, {"step": bad, "split": "train", **extra, "error": "non-finite loss", "indices": indices})
                last = latest_checkpoint(run_dir)
                raise NonFiniteLoss(
                    f"non-finite loss or gradient at update step {bad} (batch sample indices {indices}); "
                    f"stopped, last good checkpoint: {last if last is not None else 'none'}",
                    bad,
                    indices,
                )
            params, opt_state = new_params, new_opt
            sums = {k: float(v) for k, v in sums.items()}
            rate = cfg.batch * (end - step) / (time.perf_counter() - t0)
            step = end
            if step % cfg.log_every == 0 or step == cfg.steps:
                count = max(sums.pop("n"), 1.0)
                record = {k: finite_or_none(v / count) for k, v in sums.items()}
                record["samples_per_s"] = round(rate, 1)
                append_log(log_path, {"step": step, "split": "train", **extra, **record,
                                       "elapsed_s": round(time.perf_counter() - start, 2)})
                bar.set_postfix(loss=f"{record['loss']:.4g}", samples_s=f"{rate:.0f}")
            bar.update(end - bar.n)
            if val_fn is not None and (step % cfg.val_every == 0 or step == cfg.steps):
                validate(step)
            if step % cfg.ckpt_every == 0 or step == cfg.steps:
                save_checkpoint(
                    checkpoint_path(run_dir, step), params=params, opt_state=opt_state,
                    config=full_config, step=step, extra={"val": val},
                )
    finally:
        bar.close()
    if val_fn is not None and not val:  # resumed at or past the end: still report metrics
        validate(step)
    return TrainResult(params, opt_state, step, val, run_dir)
