"""train.policy's runs on the tiny preset: what a recording call holds, the expert's cache
shared between runs (a seed's, Table 3's rows', a broken entry's way out) and DAgger rounds
recording subsets. Kept apart from tests/test_imitation.py, whose hall fixtures they do not use,
so the two files' compiles run in parallel under `pytest -n 2 --dist loadfile`."""

import dataclasses
import functools
import json
import shutil

import jax
import numpy as np
import pytest
from test_imitation import BURN_IN, FAKE_TRAJECTORY, PCFG, SEQ, _fake_intention

from conav_jax.models import policy
from conav_jax.nav.expert import ExpertConfig
from conav_jax.train import imitation as im
from conav_jax.train.loop import TrainConfig
from conav_jax.train.policy import ImitationConfig, imitation_envs, train_policy, train_policy_from_data

# Compile time dominates these runs on a CPU: without LLVM optimisation and XLA's fusion
# emitters the env's rollouts compile much faster (slower to run; nothing here depends on their
# float rounding).
FAST = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}
RUN = {"scan_updates": False, "compiler_options": FAST}  # every train_policy(_from_data) call here


def _hand_weights_back(monkeypatch) -> None:
    """Each round of train_policy "trains" by handing its weights back, with a validation of zeros
    (no update or validation compiled, for tests of what a run records)."""
    from conav_jax.train import loop

    monkeypatch.setattr(loop, "train", lambda run_dir, loss, params, data, cfg, *a, **k: loop.TrainResult(
        params, None, cfg.steps, {m: 0.0 for m in ("FASR", "RASR", "CR", "AS")}, run_dir))


def test_shared_recordings_are_linked_into_place_leaving_no_temp_files(tmp_path):
    from conav_jax.train.policy import _link_or_copy

    (tmp_path / "entry.npz").write_bytes(b"windows")
    (tmp_path / "run").mkdir()
    for _ in range(2):  # again onto the same file: nothing changes
        _link_or_copy(tmp_path / "entry.npz", tmp_path / "run" / "round_0.npz")
    (tmp_path / "other.npz").write_bytes(b"other")
    _link_or_copy(tmp_path / "other.npz", tmp_path / "run" / "round_0.npz")  # replaces
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["round_0.npz"]
    assert (tmp_path / "run" / "round_0.npz").read_bytes() == b"other"
    assert (tmp_path / "entry.npz").read_bytes() == b"windows"


def test_a_broken_expert_cache_entry_is_named_with_the_way_out(tiny_data, tmp_path):
    from conav_jax.data.episodes import read_manifest
    from conav_jax.train import policy as tp

    data = tmp_path / "data"
    shutil.copytree(tiny_data, data, ignore=shutil.ignore_patterns(tp.EXPERT_CACHE_DIR))
    imitation = ImitationConfig(episodes=3, val_episodes=2, seq_len=SEQ, burn_in=BURN_IN)
    ceiling, round0 = tp.expert_cache_entries(data / tp.EXPERT_CACHE_DIR, read_manifest(data)["content_hash"], PCFG,
                                              imitation, ExpertConfig(), False, None, None, record_batch=1, devices=1)
    ceiling.parent.mkdir()
    ceiling.write_text('{"FASR": 1')  # cut short
    with pytest.raises(ValueError, match=r"expert cache entry .*ceiling_.*unreadable.*share_expert=False"):
        train_policy_from_data(data, tmp_path / "run", TrainConfig(steps=2, batch=2, warmup_steps=0), PCFG, imitation,
                               **RUN)
    (round0.with_suffix(".json")).write_text("{}")
    round0.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"expert cache entry .*round0_.*\.npz is unreadable"):
        tp.read_shared(round0)


def test_envs_other_than_the_imitation_config_names_are_refused_before_anything_is_written(tiny_data, tmp_path):
    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig

    imitation = ImitationConfig(episodes=3, val_episodes=2, seq_len=SEQ, burn_in=BURN_IN)
    train_env, val_env = imitation_envs(tiny_data, PCFG, imitation)
    cfg, run = TrainConfig(steps=2, batch=2, warmup_steps=0), tmp_path / "run"
    refused = {
        r"train_env holds the 'minival' split; expected 'train'": (val_env, val_env, PCFG, imitation),
        r"val_env holds the 'train' split; expected 'minival' \(ImitationConfig.val_split\)":
            (train_env, train_env, PCFG, imitation),
        r"PolicyConfig.resolution is \(16, 64\) but train_env renders \(8, 32\)":
            (train_env, val_env, dataclasses.replace(PCFG, resolution=(16, 64)), imitation),
        r"ImitationConfig.episodes is 2 but train_env holds 3":
            (train_env, val_env, PCFG, dataclasses.replace(imitation, episodes=2)),
        r"val_env must end its episodes at the first reach":
            (train_env, ConavEnv(episodes=val_env.split, config=EnvConfig(sensor=SensorConfig(resolution=(8, 32)))),
             PCFG, imitation),
    }
    for message, (train, val, model, imitation_) in refused.items():
        with pytest.raises(ValueError, match=message):
            train_policy(train, val, run, cfg, model, imitation_, **RUN)
    assert not run.exists()


def test_recording_lanes_fill_the_memory_budget_and_validation_runs_in_its_own_batches(tiny_data, tmp_path, monkeypatch):
    from conav_jax.checkpoints import latest_checkpoint, load_checkpoint
    from conav_jax.data.episodes import read_manifest
    from conav_jax.train import policy as tp

    # A lane holds a 32-step chunk, 16 steps of burn-in and twice the chunk's window (48 steps):
    # 144 steps of 112x448 records, 43.4 MB (uint8 RGB + float16 depth + int8 segmentation), 65.0 MB
    # with a goal image.
    assert tp.recording_lanes(32, 32, 16, (112, 448), budget_bytes=2**34) == 2**34 // (144 * 50176 * 6) == 396
    assert tp.recording_lanes(32, 32, 16, (112, 448), goal_image=True, budget_bytes=2**34) == 264
    assert tp.recording_lanes(32, 32, 16, (8, 32)) == tp.MAX_ROLLOUT_LANES
    assert tp.recording_lanes(10**6, 32, 16, (112, 448)) == 1
    if jax.default_backend() == "cpu":  # the host holds every recorded window too: a smaller budget
        assert tp.recording_lanes(32, 32, 16, (112, 448)) == tp.RECORD_BUDGET_BYTES_CPU // (144 * 50176 * 6) == 49
    with pytest.raises(ValueError, match="rollout_batch must be >= 1"):
        ImitationConfig(rollout_batch=0)

    data = tmp_path / "data"  # an expert cache of its own
    shutil.copytree(tiny_data, data, ignore=shutil.ignore_patterns(tp.EXPERT_CACHE_DIR))
    calls = []  # the lanes of every rollout call: validations, recordings
    real_run, real_record = im.run_batched, im.record_windows
    monkeypatch.setattr(im, "run_batched", lambda *a, **k: calls.append(a[5]) or real_run(*a, **k))
    recordings = []  # what each real recording returned

    def record(*a, **k):
        calls.append(a[7])
        recordings.append(real_record(*a, **k))
        return recordings[-1]

    monkeypatch.setattr(im, "record_windows", record)
    cfg, imitation = TrainConfig(steps=2, batch=2, warmup_steps=0), ImitationConfig(episodes=3, val_episodes=2, seq_len=SEQ,
                                                                                      burn_in=BURN_IN, val_batch=5)
    # Trained on env objects: the expert's cache lies beside the data the train env was loaded from.
    train_policy(*imitation_envs(data, PCFG, imitation), tmp_path / "run", cfg, PCFG, imitation, **RUN)
    config = load_checkpoint(latest_checkpoint(tmp_path / "run")).config
    assert config["data_hash"] == read_manifest(data)["content_hash"]  # the train env's dataset
    # The expert's ceiling, round 0's recording (every lane at once), the final validation.
    assert calls == [5, tp.MAX_ROLLOUT_LANES, 5]
    # The ceiling, round 0's windows and log line, and the lock files of the two entries.
    cached = sorted(p.suffix for p in (data / tp.EXPERT_CACHE_DIR).iterdir())
    assert cached == [".json", ".json", ".lock", ".lock", ".npz"]
    # A finished run resumed (from the data directory: the same config) records nothing again and
    # keeps its validation.
    (tmp_path / "run" / "data" / "round_0.npz").unlink()
    calls.clear()
    assert train_policy_from_data(data, tmp_path / "run", cfg, PCFG, imitation, **RUN).val and calls == []
    # Another seed shares the expert's ceiling and round 0 (the expert ignores the seed:
    # test_expert_round_data_...): it runs neither again (its updates are not under test here:
    # they hand the weights back), and it trains on the same windows and log lines.
    _hand_weights_back(monkeypatch)
    train_policy_from_data(data, tmp_path / "s1", dataclasses.replace(cfg, seed=1), PCFG, imitation, **RUN)
    assert calls == []
    [entry] = (data / tp.EXPERT_CACHE_DIR).glob("round0_*.npz")  # the first run's recording (its own file is gone)
    recorded, shared = im.load_sequences(entry), im.load_sequences(tmp_path / "s1" / "data" / "round_0.npz")
    for a, b in zip(jax.tree.leaves(recorded), jax.tree.leaves(shared)):
        assert a.tobytes() == b.tobytes()
    log_lines = [[json.loads(x) for x in (tmp_path / r / "log.jsonl").read_text().splitlines()[:2]] for r in ("run", "s1")]
    assert log_lines[0] == log_lines[1] and log_lines[0][1]["round"] == 0
    # Continued with a DAgger round on 2 of the 3 train episodes, the round records its own subset
    # (its rollout stands in: round 0's windows again).
    seen = []
    monkeypatch.setattr(im, "record_windows", lambda *a, **k: seen.append(np.asarray(a[5])) or recordings[0])
    dagger = dataclasses.replace(imitation, dagger_rounds=1, dagger_episodes=2)
    train_policy_from_data(data, tmp_path / "s1", dataclasses.replace(cfg, seed=1), PCFG, dagger, **RUN)
    [episodes] = seen
    assert len(episodes) == 2 and (episodes == tp.round_episodes(np.arange(3), 1, dagger, seed=1)).all()
    assert json.loads((tmp_path / "s1" / "log.jsonl").read_text().splitlines()[-1])["episodes"] == 2
    # Other train episodes: a recording of their own (the same ceiling); another batching: both.
    entries = functools.partial(tp.expert_cache_entries, data, "h", PCFG, expert=ExpertConfig(), predicted=False,
                                intention_run=None, trajectory_run=None, devices=1)
    base = entries(imitation, record_batch=64)
    fewer = entries(dataclasses.replace(imitation, episodes=2), record_batch=64)
    assert base[0] == fewer[0] and base[1] != fewer[1]
    other_batches = entries(dataclasses.replace(imitation, val_batch=7), record_batch=32)
    assert base[0] != other_batches[0] and base[1] != other_batches[1]


def _another_run_recording(cache, aside):
    """As if another run had begun recording the round-0 entry in `cache`: the entry moved to
    `aside` and its lock held until the returned event is set (a run waiting for it says so);
    then the entry is back and the lock let go. Returns (the thread, the event)."""
    import threading

    from conav_jax.train import policy as tp

    (entry,) = cache.glob("round0_*.npz")
    aside.mkdir()
    for p in (entry, entry.with_suffix(".json")):
        p.rename(aside / p.name)
    locked, waited_on = threading.Event(), threading.Event()

    def other_run():
        with tp.entry_lock(entry):
            locked.set()
            waited_on.wait(timeout=120)
            for p in (entry, entry.with_suffix(".json")):
                (aside / p.name).rename(p)

    thread = threading.Thread(target=other_run)
    thread.start()
    locked.wait()
    return thread, waited_on


def test_table3_rows_share_one_round0_recording_holding_every_prediction(tiny_data, tmp_path, monkeypatch):
    from conav_jax.train import policy as tp

    data = tmp_path / "data"  # an expert cache of its own
    shutil.copytree(tiny_data, data, ignore=shutil.ignore_patterns(tp.EXPERT_CACHE_DIR))
    fakes = (_fake_intention(9, 11), FAKE_TRAJECTORY)
    monkeypatch.setattr(tp, "load_predictors", lambda i, t: fakes if (i, t) == ("I", "T") else (None, None))
    monkeypatch.setattr(tp, "predictor_digest", lambda run: run)
    recorded = []
    real_record = im.record_windows
    monkeypatch.setattr(im, "record_windows", lambda *a, **k: recorded.append(a[0]) or real_record(*a, **k))
    _hand_weights_back(monkeypatch)  # what is recorded is under test, not the updates
    cfg = TrainConfig(steps=2, batch=2, warmup_steps=0)
    imitation = ImitationConfig(episodes=3, val_episodes=2, seq_len=SEQ, burn_in=BURN_IN, train_intentions="predicted")
    logs, other = [], None

    def log(line):
        logs.append(line)
        if line.startswith("waiting for another run recording") and other is not None:
            other[1].set()  # the other run finishes its recording

    for name in ("none", "object"):  # the first reads no intention input, the second the object's alone
        if name == "object":
            other = _another_run_recording(data / tp.EXPERT_CACHE_DIR, tmp_path / "aside")
        train_policy_from_data(data, tmp_path / name, cfg, policy.ablation_config(PCFG, name), imitation,
                               intention_run="I", trajectory_run="T", **RUN, log=log)
    other[0].join()
    assert len(recorded) == 1  # the second row reads the first's recording
    # It started while another run was recording that entry (`conav reproduce --gpus`): it waited.
    assert any(line.startswith("waiting for another run recording") for line in logs)
    # Continued where the same predictors lie elsewhere (a pack unpacked in another directory):
    # it resumes, its predictors checked by content; other predictors are refused.
    monkeypatch.setattr(tp, "load_predictors", lambda i, t: fakes)
    monkeypatch.setattr(tp, "predictor_digest", lambda run: {"there/I": "I", "there/T": "T"}.get(run, run))
    logs.clear()
    train_policy_from_data(data, tmp_path / "object", cfg, policy.ablation_config(PCFG, "object"), imitation,
                           intention_run="there/I", trajectory_run="there/T", **RUN, log=log)
    assert any(line.startswith(f"resuming {tmp_path / 'object'}") for line in logs)
    with pytest.raises(ValueError, match=r"cannot resume .*predictor_digests\.intention: saved 'I' vs expected 'X'"):
        train_policy_from_data(data, tmp_path / "object", cfg, policy.ablation_config(PCFG, "object"), imitation,
                               intention_run="X", trajectory_run="there/T", **RUN)
    # A run saved before runs recorded their predictors' digests is still checked by their paths.
    from conav_jax.checkpoints import save_checkpoint

    older = tmp_path / "older.npz"
    save_checkpoint(older, params={"w": np.zeros(1)}, opt_state=None, config={"intention_run": "I"}, step=0, extra={})
    assert tp.predictor_resume_ignore(older) == ("predictor_digests",)
    assert tp.predictor_resume_ignore(tmp_path / "object" / "ckpt_00000002.npz") == tp.PREDICTOR_PATHS
    none, obj = (im.load_sequences(tmp_path / n / "data" / "round_0.npz") for n in ("none", "object"))
    for a, b in zip(jax.tree.leaves(none), jax.tree.leaves(obj)):
        assert a.tobytes() == b.tobytes()
    # It holds every prediction, the trajectory's too (no row above reads it: all of Table 3 shares it).
    steps = obj["mask"] > 0
    assert (obj["obs"]["object_probs"].argmax(-1)[steps] == 11).all()
    np.testing.assert_array_equal(obj["obs"]["future_traj"][steps], 7.0)
    # Unshared, or without predictors, a run records what it reads and the truth for the rest.
    none_cfg, all_cfg = policy.ablation_config(PCFG, "none"), policy.ablation_config(PCFG, "all")
    assert tp.round0_configs(none_cfg, imitation, *fakes, shared=False) == (none_cfg, none_cfg)
    assert tp.round0_configs(none_cfg, imitation, shared=True) == (none_cfg, none_cfg)
    assert tp.round0_configs(none_cfg, imitation, fakes[0], None, shared=True)[0] == policy.ablation_config(
        PCFG, "activity_object")
    # On ground truth every row records the same (the truth of every input): one entry's name.
    truth = ImitationConfig()
    assert tp.round0_configs(none_cfg, truth, shared=True) == (none_cfg, all_cfg)
    assert tp.round0_configs(policy.ablation_config(PCFG, "object"), truth, shared=True)[1] == all_cfg


def test_dagger_rounds_record_a_subset_of_their_own_and_older_runs_keep_their_config():
    from conav_jax.train import policy as tp

    eps = np.arange(10, 30)
    subset = ImitationConfig(dagger_episodes=5)
    assert (tp.round_episodes(eps, 0, subset, seed=0) == eps).all()  # behaviour cloning records them all
    first, second = (tp.round_episodes(eps, r, subset, seed=0) for r in (1, 2))
    assert len(first) == 5 and len(set(first)) == 5 and set(first) <= set(eps) and (np.diff(first) > 0).all()
    assert not (first == second).all()  # each round its own
    assert (tp.round_episodes(eps, 1, subset, seed=0) == first).all()  # a resumed run records the same
    assert not (tp.round_episodes(eps, 1, subset, seed=1) == first).all()
    assert (tp.round_episodes(eps, 1, ImitationConfig(), seed=0) == eps).all()
    assert (tp.round_episodes(eps, 1, ImitationConfig(dagger_episodes=50), seed=0) == eps).all()
    with pytest.raises(ValueError, match="dagger_episodes must be >= 1"):
        ImitationConfig(dagger_episodes=0)
    # Unset, a run's config holds no such key (runs made before it resume); set, it is recorded.
    assert "dagger_episodes" not in tp.imitation_record(ImitationConfig())
    assert tp.imitation_record(subset)["dagger_episodes"] == 5
    assert "imitation.dagger_episodes" in tp.RESUME_CHANGEABLE  # a BC run goes on with DAgger on a subset
