"""Episode dataset: determinism, split disjointness, atomic writes, episode consistency."""

import json
import math

import numpy as np
import pytest

from conav_jax import episodes as episodes_lib
from conav_jax.episodes import DatasetError, generate_dataset, load_split, read_manifest
from conav_jax.presets import preset


def test_same_seed_gives_identical_bytes_and_another_seed_differs(tmp_path, tiny_data):
    again = tmp_path / "again"
    generate_dataset(preset("tiny"), again, workers=2)  # worker count must not matter
    a, b = read_manifest(tiny_data), read_manifest(again)
    assert a["content_hash"] == b["content_hash"]
    for sh in a["splits"]["train"]["shards"]:
        assert (tiny_data / sh["file"]).read_bytes() == (again / sh["file"]).read_bytes()
    other = generate_dataset(preset("tiny", seed=1), tmp_path / "other")
    assert other["content_hash"] != a["content_hash"]


def test_train_and_val_scenes_are_disjoint(tiny_data):
    m = read_manifest(tiny_data)
    train, val = set(m["splits"]["train"]["scenes"]), set(m["splits"]["val"]["scenes"])
    assert train and val and not (train & val)
    names = [s["name"] for s in m["scenes"]]
    for split, allowed in (("train", train), ("val", val)):
        sp = load_split(tiny_data, split)
        assert {names[i] for i in sp.episodes["scene_index"]} <= allowed


def test_episodes_are_consistent(tiny_data):
    sp = load_split(tiny_data, "train")
    e = sp.episodes
    task = sp.config.task
    for i in range(sp.num_episodes):
        t_walk, t_arr, t_end = int(e["t_walk_start"][i]), int(e["t_arrive"][i]), int(e["t_end"][i])
        assert 0 < t_walk < t_arr < t_end < sp.max_steps
        phase = e["phase"][i]
        assert (phase[:t_walk] == 0).all() and (phase[t_walk:t_arr] == 1).all()
        assert (phase[t_arr : t_end + 1] == 2).all() and (phase[t_end + 1 :] == 3).all()
        # the human is at the goal when it arrives
        assert np.linalg.norm(e["root_xy"][i, t_arr] - e["goal_xy"][i]) < 0.05
        # the robot starts near the human, in free space, facing it, with the goal reachable
        start = e["robot_start"][i]
        human = e["root_xy"][i, 0]
        dist = np.linalg.norm(start[:2] - human)
        lo, hi = task.robot_start_distance_m
        assert lo - 0.3 <= dist <= hi + 0.3  # the pelvis sways around the standing point
        nav = sp.navs[int(e["scene_index"][i])]
        assert nav.grid.is_free(start[:2])
        bearing = math.atan2(human[1] - start[1], human[0] - start[0])
        assert abs(math.remainder(bearing - float(start[2]), 2 * math.pi)) < 0.5
        assert np.isfinite(e["geodesic_start_goal_m"][i]) and e["geodesic_start_goal_m"][i] > task.success_radius_m
        joints = sp.joints(i)
        assert np.isfinite(joints).all() and joints.shape[1:] == (22, 3)


def test_walking_speed_along_the_path_is_in_the_configured_range(tiny_data):
    sp = load_split(tiny_data, "train")
    e = sp.episodes
    lo, hi = sp.config.motion.walk_speed_mps
    dt = sp.config.motion.control_dt_s
    for i in range(sp.num_episodes):
        w0, w1 = int(e["t_walk_start"][i]), int(e["t_arrive"][i])
        xy = e["root_xy"][i, w0 : w1 + 1]
        speed = np.linalg.norm(np.diff(xy, axis=0), axis=-1) / dt
        cruise = speed[len(speed) // 4 : -len(speed) // 4]  # away from the ease in and out
        assert lo * 0.85 <= np.median(cruise) <= hi * 1.15


def test_interrupted_generation_leaves_no_valid_dataset(tmp_path, monkeypatch):
    calls = {"n": 0}
    real = episodes_lib.save_npz

    def failing(path, arrays):
        calls["n"] += 1
        if "shard" in str(path):
            raise KeyboardInterrupt("simulated interruption")
        return real(path, arrays)

    monkeypatch.setattr(episodes_lib, "save_npz", failing)
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(preset("tiny"), tmp_path / "broken")
    with pytest.raises(DatasetError, match="no manifest.json"):
        load_split(tmp_path / "broken", "train")
    assert not list((tmp_path / "broken").rglob("*.tmp"))  # no temporary leftovers


def test_modified_or_missing_files_are_detected(tmp_path, tiny_data):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(tiny_data, copy)
    m = json.loads((copy / "manifest.json").read_text())
    shard = copy / m["splits"]["val"]["shards"][0]["file"]
    data = bytearray(shard.read_bytes())
    data[-1] ^= 0xFF
    shard.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match="does not match the manifest"):
        load_split(copy, "val")
    shard.unlink()
    with pytest.raises(DatasetError, match="is missing"):
        load_split(copy, "val")
    with pytest.raises(DatasetError, match="no split 'test'"):
        load_split(tiny_data, "test")
    with pytest.raises(DatasetError, match="not found"):
        load_split(tmp_path / "nowhere", "val")


def test_unknown_preset_is_rejected():
    with pytest.raises(ValueError, match="unknown preset 'huge'"):
        preset("huge")
