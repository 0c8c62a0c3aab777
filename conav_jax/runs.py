"""Run directories: what `conav train ...` writes and everything downstream reads back.

A run directory holds `ckpt_<step>.npz` checkpoints (conav_jax.checkpoints; the config inside
names the run's `kind`) and `log.jsonl`, one JSON record per line (train losses, validations).
Training resumes from the latest checkpoint of the same config (`resume`, which also trims
the log back to that step); agents and predictors load the latest checkpoint of a run of the
kind they expect (`load_run`). No JAX computation here: paths, JSON and checkpoints only.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from conav_jax.checkpoints import (
    Checkpoint,
    latest_checkpoint,
    load_checkpoint,
    read_checkpoint_meta,
)

PyTree = Any
LOG_FILE = "log.jsonl"

# The kinds of run, as recorded in each checkpoint's config["kind"].
INTENTION = "intention"  # conav train intention: the Perceiver intention predictor
TRAJECTORY = "trajectory"  # conav train trajectory: the human trajectory predictor
POLICY = "policy"  # conav train policy: the LSTM policy by imitation (BC, DAgger)
PPO = "ppo"  # conav train rl: PPO on the brax env
OBJECTNAV = "objectnav"  # conav train objectnav: the object-goal baseline by imitation of the object-goal planner
IMAGENAV = "imagenav"  # conav train imagenav: the image-goal baseline by imitation of the goal planner
RUN_KINDS = (INTENTION, TRAJECTORY, POLICY, PPO, OBJECTNAV, IMAGENAV)

# Config keys renamed (to the new dotted key) or dropped (None) after runs were written, by the
# run's kind: a stored config is read under today's names, so older runs load and resume as
# they did. The panorama size is `resolution` everywhere; a live run's env no longer repeats it.
_PANORAMA = {"model.image_hw": "model.resolution"}
RENAMED_CONFIG_KEYS: dict[str, dict[str, str | None]] = {
    POLICY: {**_PANORAMA, "env.sensor_hw": None}, PPO: _PANORAMA, OBJECTNAV: _PANORAMA, IMAGENAV: _PANORAMA,
    INTENTION: {"data.sensor_hw": "data.resolution"},
}


def upgrade_config(config: dict) -> dict:
    """`config` (a checkpoint's) with the keys RENAMED_CONFIG_KEYS lists for its kind renamed or
    dropped; a copy, the input unchanged. ValueError where a renamed key meets its new name."""
    renames = RENAMED_CONFIG_KEYS.get(config.get("kind"), {})
    if not renames:
        return config
    out = json.loads(json.dumps(config))
    for old, new in renames.items():
        *parents, leaf = old.split(".")
        node = out
        for k in parents:
            node = node.get(k) if isinstance(node, dict) else None
        if not isinstance(node, dict) or leaf not in node:
            continue
        value = node.pop(leaf)
        if new is None:
            continue
        *parents, leaf = new.split(".")
        target = out
        for k in parents:
            target = target.setdefault(k, {})
        if leaf in target:
            raise ValueError(f"checkpoint config holds both {old} and {new}")
        target[leaf] = value
    return out


def append_log(path: str | Path, record: dict) -> None:
    """Append one JSON record (a line) to a run's log."""
    with open(path, "a") as f:
        f.write(json.dumps(record) + "\n")


def read_log(run_dir: str | Path) -> list[dict]:
    """The records of `run_dir/log.jsonl`, in order; FileNotFoundError naming the run if absent."""
    path = Path(run_dir) / LOG_FILE
    if not path.is_file():
        raise FileNotFoundError(f"no {LOG_FILE} in {run_dir}")
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def trim_log(path: Path, step: int) -> None:
    """Keep only records up to `step` (and those without one): a resumed run re-logs what came
    after its checkpoint."""
    if not path.is_file():
        return
    keep = [line for line in path.read_text().splitlines() if line.strip() and json.loads(line).get("step", 0) <= step]
    path.write_text("".join(line + "\n" for line in keep))


def finite_or_none(x) -> float | None:
    """`float(x)`, or None where it is inf/NaN (JSON has no NaN)."""
    v = float(x)
    return v if math.isfinite(v) else None


def resume(run_dir: str | Path, config: dict, params: PyTree, opt_state: PyTree,
           ignore: tuple[str, ...] = ()) -> Checkpoint | None:
    """The latest checkpoint of `run_dir`, loaded against `config` and the state's structure,
    with the run's log trimmed to its step; None for a fresh run (whose stale log, belonging to
    no state we can continue, is removed). ValueError naming the first difference when the
    checkpoint is of another config (`ignore`: dotted config keys a resumed run may change)."""
    log_path = Path(run_dir) / LOG_FILE
    found = latest_checkpoint(run_dir)
    if found is None:
        log_path.unlink(missing_ok=True)
        return None
    try:
        ckpt = load_checkpoint(found, config=config, params_like=params, opt_state_like=opt_state, ignore=ignore,
                               upgrade=upgrade_config)
    except ValueError as e:
        raise ValueError(f"cannot resume {run_dir}: {e}") from None
    trim_log(log_path, ckpt.step)
    return ckpt


def _latest(run_dir: str | Path, kind: str) -> Path:
    if kind not in RUN_KINDS:
        raise ValueError(f"unknown run kind {kind!r}; expected one of {RUN_KINDS}")
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{kind} run directory not found: {run_dir}")
    found = latest_checkpoint(run_dir)
    if found is None:
        raise FileNotFoundError(f"no checkpoint (ckpt_*.npz) in {run_dir}")
    return found


def _check_kind(found: Path, config: dict, kind: str) -> None:
    got = config.get("kind")
    if got != kind:
        command = {INTENTION: "train intention", TRAJECTORY: "train trajectory", POLICY: "train policy", PPO: "train rl",
                   OBJECTNAV: "train objectnav", IMAGENAV: "train imagenav"}
        raise ValueError(f"{found} is a {got!r} run, expected {kind!r} (a `conav {command[kind]}` run)")


def run_config(run_dir: str | Path, kind: str) -> dict:
    """The config of the latest checkpoint of a run of `kind`, read without its arrays (cheap:
    for checks before anything is built). Errors as `load_run`."""
    found = _latest(run_dir, kind)
    config = upgrade_config(read_checkpoint_meta(found)["config"])
    _check_kind(found, config, kind)
    return config


def load_run(run_dir: str | Path, kind: str, params_like: PyTree = None) -> Checkpoint:
    """The latest checkpoint of a run of `kind` (params checked against `params_like` if
    given). FileNotFoundError for a missing directory or checkpoint, ValueError for a run of
    another kind, naming the kind found and the command that makes the one expected."""
    found = _latest(run_dir, kind)
    ckpt = load_checkpoint(found, upgrade=upgrade_config)
    _check_kind(found, ckpt.config, kind)
    if params_like is not None:
        ckpt = load_checkpoint(found, params_like=params_like, upgrade=upgrade_config)
    return ckpt
