"""The CoNav policy and intention predictor shipped with the package (`conav eval --agent conav
--pretrained`, `conav demo`): runs trained on the `paper` preset, kept as parameters only (no
optimiser state), so evaluating a policy that works needs no download and no training.

Each run is a directory like any training run's (`policy/`, `intention/`: one `ckpt_*.npz`);
`PROVENANCE.json` says how they were made and how they score. `export_runs` writes them from
finished runs."""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

from conav_jax import runs
from conav_jax.checkpoints import checkpoint_path, latest_checkpoint, save_checkpoint

PRETRAINED_DIR = Path(__file__).resolve().parent
PRETRAINED_RUNS = ("policy", "intention")  # the shipped policy reads no trajectory input
PROVENANCE_FILE = "PROVENANCE.json"
SIZE_LIMIT_BYTES = 5_000_000  # what the package may carry


def pretrained_runs(root: Path = PRETRAINED_DIR) -> dict[str, Path]:
    """{"policy": DIR, "intention": DIR}: the shipped runs. FileNotFoundError naming what is
    missing (an install without the package data)."""
    dirs = {name: Path(root) / name for name in PRETRAINED_RUNS}
    missing = [str(d) for d in dirs.values() if latest_checkpoint(d) is None]
    if missing:
        raise FileNotFoundError(f"the pretrained runs are missing from this install: {', '.join(missing)} "
                                "(reinstall the package with its data)")
    return dirs


def export_runs(policy_run: Path, intention_run: Path, provenance: dict, root: Path = PRETRAINED_DIR) -> int:
    """Write the latest checkpoints of a finished `conav train policy` run and of the intention
    run it read into `root`, parameters only; the policy's config stops naming its predictor runs
    (paths of the machine it was trained on), the rest of each config is kept. Returns the bytes
    written; ValueError (nothing replaced) when they exceed SIZE_LIMIT_BYTES, or when the policy's
    config names an intention run of another directory name than `intention_run`."""
    policy = runs.load_run(policy_run, runs.POLICY)  # FileNotFoundError / ValueError naming the run
    intention = runs.load_run(intention_run, runs.INTENTION)
    named = policy.config.get("intention_run")
    if named is None or Path(named).name != Path(intention_run).name:
        raise ValueError(f"{policy_run} read the intention run {named}, not {intention_run}")
    config = {**policy.config, "intention_run": None, "trajectory_run": None}
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=root) as tmp:  # nothing replaced unless all of it fits
        written = [save_checkpoint(checkpoint_path(Path(tmp) / name, ckpt.step), params=ckpt.params, opt_state=None,
                                   config=cfg, step=ckpt.step, extra=ckpt.extra)
                   for name, ckpt, cfg in (("policy", policy, config), ("intention", intention, intention.config))]
        total = sum(p.stat().st_size for p in written)
        if total > SIZE_LIMIT_BYTES:
            raise ValueError(f"the pretrained runs take {total} bytes, over the package's {SIZE_LIMIT_BYTES}")
        for name in PRETRAINED_RUNS:
            shutil.rmtree(root / name, ignore_errors=True)
            shutil.move(str(Path(tmp) / name), root / name)
    (root / PROVENANCE_FILE).write_text(json.dumps(provenance, indent=1) + "\n")
    return total
