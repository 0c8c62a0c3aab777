"""The CoNav policy and the predictors it reads, shipped with the package (`conav eval --agent
conav --pretrained`, `conav demo`): runs trained on the `paper` preset, kept as parameters only
(no optimiser state), so evaluating a policy that works needs no download and no training.

Each run is a directory like any training run's (`policy/`, and the predictors it reads:
`intention/` when it reads activities or objects, `trajectory/` when it reads the trajectory
input; one `ckpt_*.npz` each); `PROVENANCE.json` says how they were made and how they score.
`export_runs` writes them from finished runs, at float32 or, to fit the package, float16
(loading widens them exactly to the model's float32) or int8 for the largest matrices
(`conav_jax.checkpoints.quantize_int8`: one scale per output unit; loading gives float32)."""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import jax
import numpy as np

from conav_jax import runs
from conav_jax.checkpoints import checkpoint_path, latest_checkpoint, quantize_int8, save_checkpoint

PRETRAINED_DIR = Path(__file__).resolve().parent
PRETRAINED_RUNS = ("policy", "intention", "trajectory")
# A predictor ships with a policy that reads it; a policy that reads none ships alone (and a
# policy whose predictor is missing refuses to build rather than read ground truth instead).
REQUIRED_RUNS = ("policy",)
PROVENANCE_FILE = "PROVENANCE.json"
SIZE_LIMIT_BYTES = 5_000_000  # what the package may carry
# export_runs' weights_dtype: the stored precision of parameters (optimiser state is never shipped).
# "int8": float leaves of at least INT8_MIN_ENTRIES entries (the policy's flatten layer) as int8
# with a float32 scale per output unit, the other float leaves as float16.
WEIGHT_DTYPES = ("float32", "float16", "int8")
INT8_MIN_ENTRIES = 1 << 20


def pretrained_runs(root: Path = PRETRAINED_DIR) -> dict[str, Path]:
    """{"policy": DIR[, "intention": DIR][, "trajectory": DIR]}: the shipped runs (each predictor
    where shipped). FileNotFoundError naming what is missing (an install without the package
    data)."""
    found = {name: Path(root) / name for name in PRETRAINED_RUNS if latest_checkpoint(Path(root) / name) is not None}
    missing = [str(Path(root) / name) for name in REQUIRED_RUNS if name not in found]
    if missing:
        raise FileNotFoundError(f"the pretrained runs are missing from this install: {', '.join(missing)} "
                                "(reinstall the package with its data)")
    return found


def export_runs(policy_run: Path, intention_run: Path | None, provenance: dict, root: Path = PRETRAINED_DIR,
                trajectory_run: Path | None = None, weights_dtype: str = "float32") -> int:
    """Write the latest checkpoints of a finished policy run (`conav train policy` or `conav
    train live`) and of the predictor runs it read (`intention_run`, `trajectory_run`; None for
    one it did not read) into `root`, parameters only, their floating-point leaves stored as
    `weights_dtype` (WEIGHT_DTYPES); the policy's config stops naming its predictor runs (paths of
    the machine it was trained on), the rest of each config is kept. Returns the bytes written;
    ValueError (nothing replaced) when they exceed SIZE_LIMIT_BYTES, or when the predictor runs
    the policy's config names differ (by directory name, or by being named at all) from those
    given."""
    if weights_dtype not in WEIGHT_DTYPES:
        raise ValueError(f"weights_dtype {weights_dtype!r}: expected one of {', '.join(WEIGHT_DTYPES)}")
    policy = runs.load_run(policy_run, runs.POLICY)  # FileNotFoundError / ValueError naming the run
    given = {"intention": intention_run, "trajectory": trajectory_run}
    for name, run in given.items():
        named = policy.config.get(f"{name}_run")
        if (named is None) != (run is None) or named is not None and Path(named).name != Path(run).name:
            raise ValueError(f"{policy_run} read the {name} run {named}, not {run}")
    shipped = {"policy": (policy, {**policy.config, "intention_run": None, "trajectory_run": None})}
    for name, run in given.items():
        if run is not None:
            ckpt = runs.load_run(run, name)
            shipped[name] = (ckpt, ckpt.config)
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=root) as tmp:  # nothing replaced unless all of it fits
        written = [save_checkpoint(checkpoint_path(Path(tmp) / name, ckpt.step),
                                   params=_stored(ckpt.params, weights_dtype), opt_state=None,
                                   config=cfg, step=ckpt.step, extra=ckpt.extra)
                   for name, (ckpt, cfg) in shipped.items()]
        total = sum(p.stat().st_size for p in written)
        if total > SIZE_LIMIT_BYTES:
            raise ValueError(f"the pretrained runs take {total} bytes, over the package's {SIZE_LIMIT_BYTES}")
        for name in PRETRAINED_RUNS:
            shutil.rmtree(root / name, ignore_errors=True)
            if name in shipped:
                shutil.move(str(Path(tmp) / name), root / name)
    (root / PROVENANCE_FILE).write_text(json.dumps(provenance, indent=1) + "\n")
    return total


def _stored(params, weights_dtype: str):
    """`params` with their float32 and float16 leaves (a run exported before) stored as
    `weights_dtype` (WEIGHT_DTYPES; other leaves as they are)."""
    def cast(leaf):
        leaf = np.asarray(leaf)
        if leaf.dtype not in (np.float32, np.float16):
            return leaf
        if weights_dtype == "int8":
            return quantize_int8(leaf) if leaf.ndim >= 2 and leaf.size >= INT8_MIN_ENTRIES else leaf.astype(np.float16)
        return leaf.astype(weights_dtype)

    return jax.tree_util.tree_map(cast, params)
