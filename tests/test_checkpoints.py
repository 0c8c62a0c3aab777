"""conav_jax.checkpoints: bit-exact round trips, named errors for mismatches, and atomic saves."""

import os
import zipfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conav_jax.checkpoints import (
    checkpoint_path,
    latest_checkpoint,
    load_checkpoint,
    quantize_int8,
    save_checkpoint,
)
from conav_jax.optim import AdamState, adam

CONFIG = {"model": {"hidden": 8, "image_hw": (16, 64)}, "lr": 1e-3, "name": "tiny"}


@pytest.fixture(scope="module")
def trained():
    """Params of mixed dtypes and an optimizer state after two real updates (non-zero moments)."""
    rng = np.random.default_rng(0)
    normal = lambda *shape: rng.normal(size=shape).astype(np.float32)
    params = {
        "encoder": {"w": normal(3, 4), "b": np.zeros(4, np.float32)},
        "layers": [{"w": normal(4, 2)}, {"w": normal(2)}],
        "table": np.arange(6, dtype=np.int32).reshape(2, 3),
    }
    float_params = {k: v for k, v in params.items() if k != "table"}
    opt = adam(1e-2)
    state, update = opt.init(float_params), jax.jit(opt.update)
    for _ in range(2):
        grads = jax.tree_util.tree_map(lambda p: np.sin(np.asarray(p)) + 0.1, float_params)
        float_params, state = update(grads, state, float_params)
    return {**float_params, "table": params["table"]}, state


def _assert_trees_bit_identical(a, b):
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes()


def test_round_trip_is_bit_identical_with_and_without_templates(tmp_path, trained):
    params, state = trained
    path = save_checkpoint(tmp_path / "ckpt_00000002.npz", params=params, opt_state=state,
                           config=CONFIG, step=2, extra={"best_fasr": 0.25})
    plain = load_checkpoint(path)
    assert isinstance(plain.opt_state, AdamState)  # rebuilt from the saved structure
    state_like = jax.eval_shape(lambda: state)  # ShapeDtypeStructs are enough
    templated = load_checkpoint(path, config=CONFIG, params_like=params, opt_state_like=state_like)
    for ckpt in (plain, templated):
        _assert_trees_bit_identical(ckpt.params, params)
        _assert_trees_bit_identical(ckpt.opt_state, state)
        assert ckpt.step == 2 and ckpt.extra == {"best_fasr": 0.25}
        assert ckpt.config["model"]["image_hw"] == [16, 64]


def test_file_is_a_plain_npz_with_json_metadata(tmp_path, trained):
    params, state = trained
    path = save_checkpoint(tmp_path / "c.npz", params=params, opt_state=state, config=CONFIG, step=7)
    with np.load(path) as npz:
        np.testing.assert_array_equal(npz["params/encoder/w"], params["encoder"]["w"])
        assert "opt_state/mu/layers/1/w" in npz.files
    assert b'"step": 7' in zipfile.ZipFile(path).read("meta.json")


def test_config_mismatch_names_the_dotted_key(tmp_path, trained):
    params, state = trained
    path = save_checkpoint(tmp_path / "c.npz", params=params, opt_state=state, config=CONFIG, step=1)
    wrong = {**CONFIG, "model": {"hidden": 16, "image_hw": (16, 64)}}
    with pytest.raises(ValueError, match=r"model\.hidden: saved 8 vs expected 16"):
        load_checkpoint(path, config=wrong)
    with pytest.raises(ValueError, match=r"extra_flag"):
        load_checkpoint(path, config={**CONFIG, "extra_flag": True})


def test_ignored_config_keys_may_differ_or_be_missing_and_nothing_else(tmp_path, trained):
    params, state = trained
    path = save_checkpoint(tmp_path / "c.npz", params=params, opt_state=state, config=CONFIG, step=1)
    changed = {**CONFIG, "model": {**CONFIG["model"], "hidden": 16}}
    load_checkpoint(path, config=changed, ignore=("model.hidden",))
    load_checkpoint(path, config={**CONFIG, "model": {"image_hw": (16, 64)}}, ignore=("model.hidden",))
    with pytest.raises(ValueError, match=r"model\.hidden"):
        load_checkpoint(path, config=changed, ignore=("hidden",))  # dotted from the root
    with pytest.raises(ValueError, match=r"model\.image_hw"):
        load_checkpoint(path, config={**changed, "model": {"hidden": 16, "image_hw": (8, 8)}}, ignore=("model.hidden",))


def test_shape_and_structure_mismatches_name_the_key_path(tmp_path, trained):
    params, state = trained
    path = save_checkpoint(tmp_path / "c.npz", params=params, opt_state=state, config=CONFIG, step=1)
    bigger = {**params, "encoder": {**params["encoder"], "w": np.zeros((3, 5), np.float32)}}
    with pytest.raises(ValueError, match=r"params/encoder/w: saved float32\[3, 4\] vs expected float32\[3, 5"):
        load_checkpoint(path, params_like=bigger)
    with pytest.raises(ValueError, match=r"params/table: saved int32.* vs expected float32"):
        load_checkpoint(path, params_like={**params, "table": params["table"].astype(np.float32)})
    with pytest.raises(ValueError, match=r"params/head/w: expected by the template, missing"):
        load_checkpoint(path, params_like={**params, "head": {"w": np.zeros(2, np.float32)}})


def test_interrupted_save_leaves_the_previous_checkpoint_loadable(tmp_path, trained, monkeypatch):
    params, state = trained
    path = checkpoint_path(tmp_path, 5)
    save_checkpoint(path, params=params, opt_state=state, config=CONFIG, step=5)

    def crash(src, dst):
        raise OSError("simulated crash before the rename")

    monkeypatch.setattr(os, "replace", crash)
    zeros = jax.tree_util.tree_map(np.zeros_like, params)
    with pytest.raises(OSError, match="simulated crash"):
        save_checkpoint(path, params=zeros, opt_state=state, config=CONFIG, step=6)
    monkeypatch.undo()

    assert os.listdir(tmp_path) == [path.name]  # the temp file is gone too
    ckpt = load_checkpoint(path, config=CONFIG)
    assert ckpt.step == 5
    _assert_trees_bit_identical(ckpt.params, params)


def test_missing_file_raises_file_not_found_with_the_path(tmp_path):
    missing = tmp_path / "nope" / "ckpt_00000001.npz"
    with pytest.raises(FileNotFoundError, match="nope"):
        load_checkpoint(missing)


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_corrupt_file_raises_value_error(tmp_path, trained, damage):
    params, state = trained
    path = save_checkpoint(tmp_path / "c.npz", params=params, opt_state=state, config=CONFIG, step=1)
    data = path.read_bytes()
    path.write_bytes(b"not a checkpoint" if damage == "garbage" else data[: len(data) // 2])
    with pytest.raises(ValueError, match="corrupt checkpoint"):
        load_checkpoint(path)


def test_latest_checkpoint_picks_the_highest_step(tmp_path, trained):
    params, state = trained
    assert latest_checkpoint(tmp_path) is None
    assert latest_checkpoint(tmp_path / "missing") is None
    for step in (3, 12, 7):
        path = checkpoint_path(tmp_path, step)
        save_checkpoint(path, params=params, opt_state=state, config=CONFIG, step=step)
    (tmp_path / ".ckpt_00000099.npz.tmp-1-abcd").write_bytes(b"half")  # an interrupted save
    (tmp_path / "notes.txt").write_text("hi")
    assert latest_checkpoint(tmp_path) == tmp_path / "ckpt_00000012.npz"
    assert load_checkpoint(latest_checkpoint(tmp_path)).step == 12


def test_runs_written_under_old_key_names_load_and_resume_under_todays(tmp_path, trained):
    """The panorama size was `model.image_hw` (policy runs; a live run's env repeated it as
    `env.sensor_hw`) and `data.sensor_hw` (intention runs); a run written then reads as
    `resolution` and resumes against today's config. An intention run's `model.image_hw` is
    the Perceiver's crop, another fact, and stays."""
    from conav_jax import runs

    params, state = trained
    old = {"kind": "policy", "model": {"hidden": 8, "image_hw": [16, 64]}, "env": {"split": "train", "sensor_hw": [16, 64]}}
    save_checkpoint(checkpoint_path(tmp_path / "policy", 5), params=params, opt_state=state, config=old, step=5)
    today = {"kind": "policy", "model": {"hidden": 8, "resolution": [16, 64]}, "env": {"split": "train"}}
    assert runs.run_config(tmp_path / "policy", runs.POLICY) == today
    assert runs.load_run(tmp_path / "policy", runs.POLICY).config == today
    assert runs.resume(tmp_path / "policy", today, params, state).step == 5
    with pytest.raises(ValueError, match=r"model\.resolution"):
        runs.resume(tmp_path / "policy", {**today, "model": {"hidden": 8, "resolution": [8, 32]}}, params, state)

    crop = {"kind": "intention", "model": {"image_hw": [16, 16]}, "data": {"sensor_hw": [16, 64]}}
    save_checkpoint(checkpoint_path(tmp_path / "intention", 1), params=params, opt_state=None, config=crop, step=1)
    assert runs.run_config(tmp_path / "intention", runs.INTENTION) == {
        "kind": "intention", "model": {"image_hw": [16, 16]}, "data": {"resolution": [16, 64]}}
    assert old["model"] == {"hidden": 8, "image_hw": [16, 64]}  # the caller's dict untouched
    with pytest.raises(ValueError, match="both model.image_hw and model.resolution"):
        runs.upgrade_config({"kind": "ppo", "model": {"image_hw": [1, 2], "resolution": [1, 2]}})


def test_int8_quantisation_keeps_each_entry_within_half_a_step_of_its_slice():
    rng = np.random.default_rng(0)
    w = rng.normal(size=(6, 5, 4)).astype(np.float32) * np.array([1e-3, 1.0, 30.0, 0.0], np.float32)
    q = quantize_int8(w)
    assert q.values.dtype == np.int8 and q.values.shape == w.shape and q.scale.shape == (4,)
    peak = np.abs(w).reshape(-1, 4).max(axis=0)
    np.testing.assert_allclose(q.scale[:3], peak[:3] / 127, rtol=1e-6)
    assert q.scale[3] == 1.0 and not q.values[..., 3].any()  # a slice of zeros stays zeros
    err = np.abs(q.dequantized() - w).reshape(-1, 4).max(axis=0)
    assert np.all(err[:3] <= peak[:3] / 254 * (1 + 1e-5)) and err[3] == 0
    # Each slice reaches its extremes exactly: the scale is set by the largest entry.
    assert np.abs(q.values).reshape(-1, 4).max(axis=0)[:3].tolist() == [127] * 3
    with pytest.raises(ValueError, match="NaN or inf"):
        quantize_int8(np.array([[1.0, np.nan]], np.float32))
    with pytest.raises(ValueError, match="scalar"):
        quantize_int8(np.float32(2.0))


def test_an_int8_leaf_is_stored_small_and_loads_as_the_float32_it_stands_for(tmp_path):
    rng = np.random.default_rng(1)
    w = rng.normal(size=(256, 64)).astype(np.float32)
    q = quantize_int8(w)
    full = save_checkpoint(tmp_path / "f.npz", params={"w": w}, opt_state=None, config={}, step=0)
    small = save_checkpoint(tmp_path / "q.npz", params={"w": q, "b": np.ones(3, np.float32)}, opt_state=None,
                            config={}, step=0)
    assert small.stat().st_size < 0.3 * full.stat().st_size
    like = {"w": jax.ShapeDtypeStruct(w.shape, jnp.float32), "b": jax.ShapeDtypeStruct((3,), jnp.float32)}
    for loaded in (load_checkpoint(small).params, load_checkpoint(small, params_like=like).params):
        assert loaded["w"].dtype == jnp.float32
        np.testing.assert_array_equal(np.asarray(loaded["w"]), q.values.astype(np.float32) * q.scale)
    with pytest.raises(TypeError, match="Int8Array at params/w"):
        save_checkpoint(tmp_path / "bad.npz", params={"w": q._replace(scale=q.scale[:3])}, opt_state=None,
                        config={}, step=0)


def test_an_int8_leaf_whose_scale_does_not_match_its_values_is_refused_as_corrupt(tmp_path):
    q = quantize_int8(np.random.default_rng(3).normal(size=(8, 4)).astype(np.float32))
    good = save_checkpoint(tmp_path / "q.npz", params={"w": q}, opt_state=None, config={}, step=0)
    bad = tmp_path / "bad.npz"  # the same file with a one-entry scale, which would broadcast
    with zipfile.ZipFile(good) as src, zipfile.ZipFile(bad, "w") as dst:
        for member in src.namelist():
            data = src.read(member)
            if member == "params/w/int8_scale.npy":
                with dst.open(member, "w") as f:
                    np.lib.format.write_array(f, q.scale[:1])
            else:
                dst.writestr(member, data)
    with pytest.raises(ValueError, match=r"corrupt checkpoint .*int8 leaf params/w: .*scale float32\[1\]"):
        load_checkpoint(bad)
