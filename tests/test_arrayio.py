"""Atomic, deterministic file writes: what is fsynced, in which order, and byte-stable npz."""

import os

import numpy as np
import pytest

from conav_jax.data import arrayio


def _record_syncs(monkeypatch):
    """Record ("fsync", path) and ("replace", src, dst) events in the order they happen."""
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.path.realpath(f"/proc/self/fd/{fd}")))
        return real_fsync(fd)

    def replace(src, dst):
        events.append(("replace", os.path.realpath(src), os.path.realpath(dst)))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    return events


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc to name file descriptors")
def test_atomic_write_fsyncs_file_before_rename_and_directory_after(tmp_path, monkeypatch):
    events = _record_syncs(monkeypatch)
    target = tmp_path / "sub" / "a.bin"
    arrayio.atomic_write_bytes(target, b"hello")
    assert target.read_bytes() == b"hello"
    kinds = [e[0] for e in events]
    assert kinds == ["fsync", "replace", "fsync"], events
    tmp = events[1][1]
    assert events[0] == ("fsync", tmp)  # the data reached the disk under the temporary name
    assert events[1][2] == os.path.realpath(target)
    assert events[2] == ("fsync", os.path.realpath(target.parent))  # and so did the rename


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc to name file descriptors")
def test_save_npz_and_save_json_sync_their_directory(tmp_path, monkeypatch):
    events = _record_syncs(monkeypatch)
    arrayio.save_npz(tmp_path / "x.npz", {"a": np.arange(3)})
    arrayio.save_json(tmp_path / "x.json", {"a": 1})
    synced_dirs = [e[1] for e in events if e[0] == "fsync" and os.path.isdir(e[1])]
    assert synced_dirs == [os.path.realpath(tmp_path)] * 2


def test_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    target = tmp_path / "a.bin"
    target.write_bytes(b"old")

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        arrayio.atomic_write_bytes(target, b"new")
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


def test_npz_bytes_are_identical_for_identical_arrays():
    a = {"b": np.ones((2, 3), np.float16), "a": np.int32(7)}
    assert arrayio.npz_bytes(a) == arrayio.npz_bytes(dict(reversed(list(a.items()))))
