"""The generic training loop: deterministic resume, non-finite loss handling, config checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conav_jax.checkpoints import checkpoint_path, latest_checkpoint, load_checkpoint
from conav_jax.runs import read_log
from conav_jax.train.loop import NonFiniteLoss, TrainConfig, train

FAST = {"xla_backend_optimization_level": 0}
CONFIG = {"kind": "linear", "model": {"inputs": 3}}


def linear_loss(params, batch, key):
    """Squared error of a linear model, plus a key-dependent jitter that pins the loss key."""
    pred = batch["x"] @ params["w"] + params["b"]
    noise = 1e-3 * jax.random.normal(key, ())
    return jnp.mean(jnp.square(pred - batch["y"])) + noise, {"bias": params["b"]}


def make_data(n=32, nan_at=None):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(n, 3)).astype(np.float32)
    y = (x @ np.array([1.0, -2.0, 0.5], np.float32) + 0.3).astype(np.float32)
    if nan_at is not None:
        x[nan_at] = np.nan
    return {"x": x, "y": y}


def init_params():
    return {"w": jnp.zeros(3), "b": jnp.zeros(())}


def cfg(**kw):
    base = dict(steps=8, batch=4, lr=0.05, warmup_steps=2, log_every=2, val_every=4, ckpt_every=4, seed=1)
    return TrainConfig(**{**base, **kw})


def train_losses(run_dir):
    return [(r["step"], r["loss"]) for r in read_log(run_dir) if r["split"] == "train"]


def test_resumed_run_matches_an_uninterrupted_one(tmp_path):
    data = make_data()
    straight = train(tmp_path / "a", linear_loss, init_params(), data, cfg(), CONFIG,
                     progress=False, compiler_options=FAST)

    def interrupt_at_8(params):
        calls.append(1)
        if len(calls) == 2:  # the second validation: step 8, before its checkpoint
            raise KeyboardInterrupt
        return {"w0": params["w"][0]}

    calls = []
    with pytest.raises(KeyboardInterrupt):
        train(tmp_path / "b", linear_loss, init_params(), data, cfg(), CONFIG, val_fn=interrupt_at_8,
              progress=False, compiler_options=FAST)
    assert latest_checkpoint(tmp_path / "b") == checkpoint_path(tmp_path / "b", 4)
    resumed = train(tmp_path / "b", linear_loss, init_params(), data, cfg(), CONFIG,
                    progress=False, compiler_options=FAST)

    assert resumed.step == straight.step == 8
    for a, b in zip(jax.tree.leaves(straight.params), jax.tree.leaves(resumed.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert train_losses(tmp_path / "a") == train_losses(tmp_path / "b")
    assert [s for s, _ in train_losses(tmp_path / "a")] == [2, 4, 6, 8]
    # and it learned something
    assert train_losses(tmp_path / "a")[-1][1] < train_losses(tmp_path / "a")[0][1]


def loop_batches(c, n):
    """Replays the loop's minibatch draw: sample indices of every update, (steps, batch)."""
    keys = [jax.random.split(jax.random.fold_in(jax.random.PRNGKey(c.seed), s))[0] for s in range(c.steps)]
    return np.stack([np.asarray(jax.random.randint(k, (c.batch,), 0, n)) for k in keys])


def test_non_finite_loss_stops_and_keeps_the_last_good_checkpoint(tmp_path):
    c = cfg(steps=40, ckpt_every=2, val_every=40)
    batches = loop_batches(c, 32)
    # The sample drawn last for the first time, so that checkpoints come before it.
    first_draw = {int(i): s for s in reversed(range(c.steps)) for i in batches[s]}
    nan_sample = max(first_draw, key=first_draw.get)
    bad_step, bad_idx = first_draw[nan_sample], batches[first_draw[nan_sample]]
    assert bad_step >= 2
    with pytest.raises(NonFiniteLoss, match=f"step {bad_step} ") as err:
        train(tmp_path, linear_loss, init_params(), make_data(nan_at=nan_sample), c, CONFIG,
              progress=False, compiler_options=FAST)
    assert err.value.step == bad_step and err.value.indices == bad_idx.tolist()
    assert str(bad_idx.tolist()) in str(err.value)
    last = latest_checkpoint(tmp_path)
    assert last == checkpoint_path(tmp_path, bad_step // 2 * 2)
    ckpt = load_checkpoint(last)
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves((ckpt.params, ckpt.opt_state)))
    assert read_log(tmp_path)[-1]["error"] == "non-finite loss"


@pytest.mark.parametrize(
    "change, key",
    [({"cfg": {"lr": 0.1}}, "train.lr"), ({"config": {"model": {"inputs": 4}}}, "model.inputs")],
)
def test_resume_with_a_different_config_names_the_key(tmp_path, change, key):
    data = make_data()
    train(tmp_path, linear_loss, init_params(), data, cfg(steps=2), CONFIG, progress=False, compiler_options=FAST)
    with pytest.raises(ValueError, match=key):
        train(tmp_path, linear_loss, init_params(), data, cfg(steps=2, **change.get("cfg", {})),
              {**CONFIG, **change.get("config", {})}, progress=False, compiler_options=FAST)


def test_bad_inputs_are_refused(tmp_path):
    with pytest.raises(ValueError, match="steps"):
        TrainConfig(steps=0)
    with pytest.raises(ValueError, match="leading size"):
        train(tmp_path, linear_loss, init_params(), {"x": np.zeros((3, 3)), "y": np.zeros(4)}, cfg(), CONFIG)
    with pytest.raises(ValueError, match="kind"):
        train(tmp_path, linear_loss, init_params(), make_data(), cfg(), {"model": {}})


def test_resume_accepts_changes_to_the_keys_it_is_told_to_ignore_and_no_others(tmp_path):
    """What `conav train policy` relies on to resume a finished BC run with another DAgger
    round length (train.policy.RESUME_CHANGEABLE)."""
    from conav_jax.checkpoints import save_checkpoint
    from conav_jax.runs import resume
    from conav_jax.train.policy import RESUME_CHANGEABLE

    params = init_params()
    opt_state = {"m": jnp.zeros(3)}
    saved = {"kind": "policy", "imitation": {"dagger_steps": 1000, "seq_len": 32}}
    save_checkpoint(checkpoint_path(tmp_path, 5), params=params, opt_state=opt_state, config=saved, step=5)
    longer = {"kind": "policy", "imitation": {"dagger_steps": 4000, "seq_len": 32}}
    assert resume(tmp_path, longer, params, opt_state, ignore=RESUME_CHANGEABLE).step == 5
    with pytest.raises(ValueError, match="imitation.dagger_steps"):
        resume(tmp_path, longer, params, opt_state)
    with pytest.raises(ValueError, match="imitation.seq_len"):
        resume(tmp_path, {"kind": "policy", "imitation": {"dagger_steps": 4000, "seq_len": 16}}, params, opt_state,
               ignore=RESUME_CHANGEABLE)
    # A run saved before the expert's share existed continues as DAgger with one.
    mixed = {"kind": "policy", "imitation": {"dagger_steps": 1000, "dagger_beta": 0.5, "seq_len": 32}}
    assert resume(tmp_path, mixed, params, opt_state, ignore=RESUME_CHANGEABLE).step == 5
    with pytest.raises(ValueError, match="imitation.dagger_beta"):
        resume(tmp_path, mixed, params, opt_state, ignore=("imitation.dagger_steps",))


def test_single_updates_on_a_mesh_compile_once(tmp_path):
    """Updates one call at a time (the CPU path) on a device mesh: the first call's guard and
    sums are placed as the update returns them, so later calls reuse its program."""
    from conav_jax.parallel import make_mesh
    from conav_jax.train.loop import _jitted

    c = cfg(log_every=2)
    train(tmp_path / "run", linear_loss, init_params(), make_data(), c, CONFIG, compiler_options=FAST,
          mesh=make_mesh(1), scan_updates=False)
    cadence_free = TrainConfig(**{**c.__dict__, "log_every": 1, "val_every": 1, "ckpt_every": 1})
    compiled, _ = _jitted(linear_loss, cadence_free, 32, tuple(sorted(FAST.items())), make_mesh(1), False)
    assert compiled._cache_size() == 1
