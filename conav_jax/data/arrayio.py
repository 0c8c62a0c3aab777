"""Byte-deterministic, atomic file writes for array shards and JSON.

`np.savez` stamps the wall-clock time into each zip entry, so the same arrays give different
bytes on every run; here entries carry a fixed timestamp and a sorted order. Every write goes to
a temporary sibling that is fsynced and then renamed over the target, and the directory is
fsynced after the rename, so an interrupted run (or a power cut) never leaves a truncated file
under the real name, nor loses the rename of a file a later write depends on.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
import zipfile
from pathlib import Path
from typing import Mapping

import numpy as np

_FIXED_ZIP_TIME = (1980, 1, 1, 0, 0, 0)


def fsync_dir(directory: str | os.PathLike) -> None:
    """Persist the entries of `directory` (a rename into it): fsync the directory itself.
    Best effort: some platforms cannot open a directory for fsync."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write `data` to `path` so that readers see either the old file or the whole new one:
    a temporary sibling is written and fsynced, renamed over `path`, and the directory fsynced
    so the rename itself survives a crash."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    fsync_dir(path.parent)


def npz_bytes(arrays: Mapping[str, np.ndarray]) -> bytes:
    """An uncompressed .npz archive of `arrays`, identical bytes for identical arrays."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name in sorted(arrays):
            arr = np.asarray(arrays[name])
            if not arr.flags.c_contiguous:  # (np.ascontiguousarray would turn 0-d into 1-d)
                arr = arr.copy(order="C")
            if arr.dtype == object:
                raise TypeError(f"array {name!r} has dtype object; only numeric arrays are stored")
            entry = io.BytesIO()
            np.lib.format.write_array(entry, arr, allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_FIXED_ZIP_TIME)
            info.external_attr = 0o644 << 16
            zf.writestr(info, entry.getvalue())
    return buf.getvalue()


def save_npz(path: str | os.PathLike, arrays: Mapping[str, np.ndarray]) -> str:
    """Atomically write `arrays` as a deterministic .npz; returns its sha256 hex digest."""
    data = npz_bytes(arrays)
    atomic_write_bytes(path, data)
    return hashlib.sha256(data).hexdigest()


def load_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """All arrays of an .npz file, loaded eagerly (no pickles)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"array file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError) as e:
        raise ValueError(f"corrupt array file {path}: {e}") from e


def json_bytes(obj) -> bytes:
    """Canonical JSON (sorted keys, 1-space indent, trailing newline)."""
    return (json.dumps(obj, indent=1, sort_keys=True) + "\n").encode()


def save_json(path: str | os.PathLike, obj) -> str:
    """Atomically write canonical JSON; returns its sha256 hex digest."""
    data = json_bytes(obj)
    atomic_write_bytes(path, data)
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
