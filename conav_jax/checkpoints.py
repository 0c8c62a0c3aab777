"""Checkpoints: params + optimizer state + run metadata in one atomically written `.npz` file.

The file is a zip (loadable by `np.load`) holding one `.npy` member per array, named by its
pytree key path (`params/encoder/conv/0/w.npy`), and a plain `meta.json` member (format version,
step, config, extra, and the tree structure needed to rebuild the pytrees without a template).
A leaf saved as an `Int8Array` (a shipped run's large weight matrices) is stored as int8 values
and one float32 scale per slice of its last axis, and loads as the float32 array they give.
A save writes a hidden temp sibling, fsyncs it and `os.replace`s it into place, so an
interrupted save leaves the previous file (or nothing) at the path, never a half-written one.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import os
import re
import sys
import uuid
import zipfile
from pathlib import Path
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from conav_jax.data.arrayio import fsync_dir
from conav_jax.provenance import PROVENANCE_KEY

FORMAT_VERSION = 1
META_MEMBER = "meta.json"
CHECKPOINT_RE = re.compile(r"^ckpt_(\d+)\.npz$")

PyTree = Any


class Checkpoint(NamedTuple):
    """What `load_checkpoint` returns. Arrays are jax arrays; `config`/`extra` are JSON values."""

    params: PyTree
    opt_state: PyTree
    config: dict
    step: int
    extra: dict


def checkpoint_path(run_dir: str | os.PathLike, step: int) -> Path:
    """`run_dir/ckpt_{step:08d}.npz`: the name `latest_checkpoint` looks for."""
    return Path(run_dir) / f"ckpt_{step:08d}.npz"


def latest_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    """The `ckpt_*.npz` in `run_dir` with the highest step, or None if there is none (or no dir).
    Temp files of interrupted saves are hidden dot-files and never match."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        return None
    found = [(int(m.group(1)), p) for p in run_dir.iterdir() if (m := CHECKPOINT_RE.match(p.name))]
    return max(found)[1] if found else None


class Int8Array(NamedTuple):
    """A float32 array kept as `values * scale`: int8 values of the array's shape and one
    float32 scale per slice of its last axis (a weight matrix's output unit). `quantize_int8`
    makes it; a checkpoint stores it in a quarter of the float32 bytes and loads it as the
    float32 array it stands for."""

    values: np.ndarray  # int8, the array's shape
    scale: np.ndarray  # float32, (shape[-1],)

    def dequantized(self) -> np.ndarray:
        return self.values.astype(np.float32) * self.scale


def quantize_int8(array) -> Int8Array:
    """Symmetric int8 quantisation of a float array with at least one axis, one scale per slice
    of its last axis: each value is rounded to the nearest of 255 steps across [-max|slice|,
    +max|slice|], so an entry is off by at most half a step (max|slice| / 254). A slice of zeros
    gets scale 1. ValueError for a non-finite entry or a scalar."""
    array = np.asarray(array, np.float32)
    if array.ndim == 0:
        raise ValueError("quantize_int8 needs an array with at least one axis, got a scalar")
    if not np.isfinite(array).all():
        raise ValueError("quantize_int8: the array holds NaN or inf")
    peak = np.abs(array).reshape(-1, array.shape[-1]).max(axis=0)
    scale = np.where(peak > 0, peak / 127.0, 1.0).astype(np.float32)
    values = np.clip(np.rint(array / scale), -127, 127).astype(np.int8)
    return Int8Array(values, scale)


# --- pytree <-> (JSON structure, named arrays) -------------------------------------------------


def _encode(node: Any, prefix: str, arrays: dict[str, np.ndarray]) -> dict:
    """Describe `node` as JSON and collect its leaves into `arrays` under slash-joined key paths.
    Supports what our params and optimizer states are made of: dicts with str keys, lists,
    tuples, NamedTuples, None and array leaves."""
    if node is None:
        return {"kind": "none"}
    if isinstance(node, Int8Array):  # before the NamedTuple case: it is one leaf, not a subtree
        values, scale = np.asarray(node.values), np.asarray(node.scale)
        if values.dtype != np.int8 or scale.dtype != np.float32 or scale.shape != values.shape[-1:]:
            raise TypeError(f"Int8Array at {prefix}: values {values.dtype}{list(values.shape)}, "
                            f"scale {scale.dtype}{list(scale.shape)}")
        arrays[prefix], arrays[f"{prefix}/int8_scale"] = values, scale  # a leaf has no children: no clash
        return {"kind": "int8", "name": prefix, "scale": f"{prefix}/int8_scale", "shape": list(values.shape)}
    if isinstance(node, dict):
        for k in node:
            if not isinstance(k, str) or "/" in k:
                raise TypeError(f"checkpoint dict keys must be str without '/', got {k!r} at {prefix}")
        return {"kind": "dict", "items": {k: _encode(v, f"{prefix}/{k}", arrays) for k, v in node.items()}}
    if isinstance(node, tuple) and hasattr(node, "_fields"):
        cls = type(node)
        return {
            "kind": "namedtuple",
            "class": f"{cls.__module__}:{cls.__qualname__}",
            "items": {f: _encode(getattr(node, f), f"{prefix}/{f}", arrays) for f in node._fields},
        }
    if isinstance(node, (list, tuple)):
        kind = "list" if isinstance(node, list) else "tuple"
        return {"kind": kind, "items": [_encode(v, f"{prefix}/{i}", arrays) for i, v in enumerate(node)]}
    if isinstance(node, (jax.Array, np.ndarray, np.generic, int, float, bool)):
        arr = np.asarray(node)
        arrays[prefix] = arr
        return {"kind": "array", "name": prefix, "shape": list(arr.shape), "dtype": arr.dtype.str}
    raise TypeError(f"cannot checkpoint a {type(node).__name__} at {prefix}")


def _namedtuple_class(spec: str) -> type:
    """Resolve `module:qualname`. Only our own package is imported on demand; other classes must
    already be loaded (a checkpoint never triggers imports of arbitrary modules)."""
    module_name, qualname = spec.split(":")
    if module_name == "conav_jax" or module_name.startswith("conav_jax."):
        module = importlib.import_module(module_name)
    elif module_name in sys.modules:
        module = sys.modules[module_name]
    else:
        raise ValueError(f"checkpoint holds a {spec} whose module is not loaded; pass a *_like template")
    obj: Any = module
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


def _decode(desc: dict, arrays: dict[str, np.ndarray]) -> Any:
    kind = desc["kind"]
    if kind == "none":
        return None
    if kind == "array":
        return arrays[desc["name"]]
    if kind == "int8":
        values, scale = arrays[desc["name"]], arrays[desc["scale"]]
        if (values.dtype != np.int8 or scale.dtype != np.float32 or list(values.shape) != desc["shape"]
                or scale.shape != values.shape[-1:]):  # a scale that broadcast would be silently wrong
            raise ValueError(f"int8 leaf {desc['name']}: values {values.dtype}{list(values.shape)}, scale "
                             f"{scale.dtype}{list(scale.shape)}, recorded shape {desc['shape']}")
        return Int8Array(values, scale).dequantized()
    if kind == "dict":
        return {k: _decode(v, arrays) for k, v in desc["items"].items()}
    if kind == "list":
        return [_decode(v, arrays) for v in desc["items"]]
    if kind == "tuple":
        return tuple(_decode(v, arrays) for v in desc["items"])
    if kind == "namedtuple":
        return _namedtuple_class(desc["class"])(**{k: _decode(v, arrays) for k, v in desc["items"].items()})
    raise ValueError(f"unknown node kind {kind!r}")


# --- save ---------------------------------------------------------------------------------------


def _config_dict(config: Any) -> dict:
    """A JSON round trip of the config (tuples become lists), so saved and expected compare alike."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        config = dataclasses.asdict(config)
    return json.loads(json.dumps(config))


def save_checkpoint(
    path: str | os.PathLike,
    *,
    params: PyTree,
    opt_state: PyTree,
    config: dict,
    step: int,
    extra: dict | None = None,
) -> Path:
    """Write one checkpoint file atomically and return its path.

    `config` (a dict, or a dataclass instance converted by `dataclasses.asdict`) and `extra`
    must be JSON-serialisable. Arrays are fetched to the host (a sharded array is gathered).
    """
    path = Path(path)
    arrays: dict[str, np.ndarray] = {}
    structure = {
        "params": _encode(params, "params", arrays),
        "opt_state": _encode(opt_state, "opt_state", arrays),
    }
    meta = {
        "format_version": FORMAT_VERSION,
        "step": int(step),
        "config": _config_dict(config),
        "extra": json.loads(json.dumps(extra or {})),
        "structure": structure,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        with open(tmp, "wb") as f:
            with zipfile.ZipFile(f, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
                zf.writestr(META_MEMBER, json.dumps(meta, indent=1))
                for name, arr in arrays.items():
                    with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
                        np.lib.format.write_array(member, arr, allow_pickle=False)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)
    return path


# --- load ---------------------------------------------------------------------------------------


def _first_config_mismatch(saved: Any, expected: Any, key: str = "", ignore: frozenset = frozenset()) -> str | None:
    """Dotted key and values of the first difference between two JSON values (keys in `ignore`
    excepted), else None."""
    if isinstance(saved, dict) and isinstance(expected, dict):
        for k in list(expected) + [k for k in saved if k not in expected]:
            sub = f"{key}.{k}" if key else str(k)
            if sub in ignore:
                continue
            if k not in saved:
                return f"{sub}: missing from the checkpoint, expected {expected[k]!r}"
            if k not in expected:
                return f"{sub}: saved {saved[k]!r}, not in the expected config"
            found = _first_config_mismatch(saved[k], expected[k], sub, ignore)
            if found:
                return found
        return None
    if saved != expected:
        return f"{key or '<root>'}: saved {saved!r} vs expected {expected!r}"
    return None


def _restore_like(name: str, loaded: PyTree, like: PyTree) -> PyTree:
    """Check `loaded` against the template's structure, shapes and dtypes; return it with the
    template's tree type (and sharding, where the template leaf has one). A float16 leaf where
    the template holds float32 (parameters stored at half precision) widens to it, exactly."""
    got, _ = jax.tree_util.tree_flatten_with_path(loaded)
    want, want_def = jax.tree_util.tree_flatten_with_path(like)
    got_paths = {jax.tree_util.keystr(p, simple=True, separator="/"): x for p, x in got}
    want_paths = [jax.tree_util.keystr(p, simple=True, separator="/") for p, _ in want]
    for p in want_paths:
        if p not in got_paths:
            raise ValueError(f"{name}/{p}: expected by the template, missing from the checkpoint")
    for p in got_paths:
        if p not in want_paths:
            raise ValueError(f"{name}/{p}: in the checkpoint, not in the template")
    leaves = []
    for p, (_, tmpl) in zip(want_paths, want):
        arr = got_paths[p]
        shape, dtype = tuple(tmpl.shape), np.dtype(tmpl.dtype)
        if arr.shape == shape and arr.dtype == np.float16 and dtype == np.float32:
            arr = arr.astype(np.float32)  # stored at half precision (a shipped run): widens exactly
        if arr.shape != shape or arr.dtype != dtype:
            raise ValueError(
                f"{name}/{p}: saved {arr.dtype}{list(arr.shape)} vs expected {dtype}{list(shape)}"
            )
        sharding = getattr(tmpl, "sharding", None)
        leaves.append(jax.device_put(arr, sharding) if sharding is not None else jnp.asarray(arr))
    return jax.tree_util.tree_unflatten(want_def, leaves)


def read_checkpoint_meta(path: str | os.PathLike) -> dict:
    """The metadata of a checkpoint (format version, step, config, extra) without its arrays.
    FileNotFoundError for a missing path, ValueError for a corrupt file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        with zipfile.ZipFile(path, "r") as zf:
            return _read_meta(zf)
    except (zipfile.BadZipFile, KeyError, ValueError) as e:
        raise ValueError(f"corrupt checkpoint {path}: {type(e).__name__}: {e}") from e


def _read_meta(zf: zipfile.ZipFile) -> dict:
    """The metadata member of an open checkpoint; ValueError for a format this code cannot read."""
    meta = json.loads(zf.read(META_MEMBER))
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"unsupported checkpoint format {meta.get('format_version')!r}")
    return meta


def load_checkpoint(
    path: str | os.PathLike,
    *,
    config: dict | None = None,
    params_like: PyTree = None,
    opt_state_like: PyTree = None,
    ignore: tuple[str, ...] = (),
    upgrade: Callable[[dict], dict] | None = None,
) -> Checkpoint:
    """Read a checkpoint written by `save_checkpoint`.

    - `upgrade`: maps the saved config to today's names (conav_jax.runs.upgrade_config) before
      it is compared and returned.
    - `config`: if given, the saved config must equal it, else ValueError naming the first
      differing dotted key (`task.v_max_mps: saved 1.0 vs expected 2.0`); the dotted keys in
      `ignore` may differ (or be absent on either side).
    - `params_like` / `opt_state_like`: templates (arrays or `jax.ShapeDtypeStruct`s); the saved
      tree must match in structure, shape and dtype, else ValueError naming the key path.
      Without a template the tree is rebuilt from the saved structure.
    Raises FileNotFoundError for a missing path and ValueError for a corrupt file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        with zipfile.ZipFile(path, "r") as zf:
            meta = _read_meta(zf)
            arrays = {}
            for member in zf.namelist():
                if member.endswith(".npy"):
                    with zf.open(member) as f:
                        arrays[member[: -len(".npy")]] = np.lib.format.read_array(f, allow_pickle=False)
            trees = {k: _decode(meta["structure"][k], arrays) for k in ("params", "opt_state")}
    except (zipfile.BadZipFile, KeyError, TypeError, ValueError, EOFError) as e:
        raise ValueError(f"corrupt checkpoint {path}: {type(e).__name__}: {e}") from e

    if upgrade is not None:
        meta["config"] = upgrade(meta["config"])
    if config is not None:
        # A run's provenance (the code and device that wrote it) may differ when another commit resumes it.
        mismatch = _first_config_mismatch(meta["config"], _config_dict(config), ignore=frozenset(ignore) | {PROVENANCE_KEY})
        if mismatch:
            raise ValueError(f"checkpoint {path} config mismatch at {mismatch}")

    def restore(name: str, like: PyTree) -> PyTree:
        if like is not None:
            return _restore_like(name, trees[name], like)
        return jax.tree_util.tree_map(jnp.asarray, trees[name])

    return Checkpoint(
        params=restore("params", params_like),
        opt_state=restore("opt_state", opt_state_like),
        config=meta["config"],
        step=int(meta["step"]),
        extra=meta["extra"],
    )
