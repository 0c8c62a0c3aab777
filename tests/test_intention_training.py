"""Intention predictor training: rendered frames show the human, the prior baseline, a short
run that checkpoints, and the per-step predictor under jit."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conav_jax.checkpoints import latest_checkpoint
from conav_jax.models import perceiver
from conav_jax.models.perceiver import PerceiverConfig
from conav_jax.runs import read_log
from envs.agents.predictors import load_intention_predictor
from envs.humanoid import capsule_colours
from train.intention import (
    IntentionDataConfig,
    activity_a_steps,
    baseline_metrics,
    intention_loss,
    make_env,
    make_val_fn,
    prior_scores,
    render_split,
    run_config,
    topk_accuracy,
)
from train.loop import TrainConfig, train

FAST = {"xla_backend_optimization_level": 0}
DATA = IntentionDataConfig(sensor_hw=(16, 64), frames=4)
MODEL = PerceiverConfig(image_hw=(16, 16), dim=16, num_latents=4, num_heads=2, num_blocks=0)


@pytest.fixture(scope="module")
def rendered(tiny_data):
    env = make_env(tiny_data, "train", DATA)
    return env, render_split(env, MODEL, DATA, compiler_options=FAST)


def test_activity_a_steps_spread_over_activity_a():
    steps, num = activity_a_steps(np.array([31, 2]), 4)
    np.testing.assert_array_equal(steps, [[0, 10, 20, 30], [0, 1, 1, 1]])
    np.testing.assert_array_equal(num, [4, 2])


def test_rendered_frames_show_the_human(rendered):
    env, d = rendered
    n = env.num_episodes
    assert d["frames"].shape == (n, 4, 16, 16, 4) and d["num_frames"].shape == (n,)
    np.testing.assert_array_equal(d["activity"], env.split.episodes["activity_b"])
    # The robot starts facing the human: every episode shows it in most of its frames...
    seen = np.asarray(d["human_pixels"]) > 0
    assert seen.mean() > 0.8 and seen.any(axis=1).all()
    # ...and the human's pixels carry the capsules' colours (float16 storage: ~1e-3).
    rgb = np.asarray(d["frames"][..., :3], np.float32).reshape(n, 4, -1, 1, 3)
    is_human = np.any(np.all(np.abs(rgb - capsule_colours()[None, None, None]) < 2e-3, axis=-1), axis=-1)
    np.testing.assert_array_equal(is_human.sum(-1), d["human_pixels"])


def test_prior_is_the_most_frequent_b_given_a():
    # A=0 -> B: 3, 3, 4; A=1 -> B: 4, 5 (a tie, broken by B's overall frequency: 4 twice);
    # A=2 never seen -> the overall most frequent B (4: three times; 3: twice).
    a = np.array([0, 0, 0, 1, 1, 3])
    b = np.array([3, 3, 4, 4, 5, 4])
    scores = prior_scores(a, b, num_a=4, num_b=6)
    assert scores.argmax(1).tolist() == [3, 4, 4, 4]
    assert np.argsort(-scores[0])[:3].tolist() == [3, 4, 5]
    assert topk_accuracy(scores[[0, 1, 2]], np.array([3, 5, 4]), 1) == pytest.approx(2 / 3)
    assert topk_accuracy(scores[[0, 1, 2]], np.array([3, 5, 4]), 2) == 1.0
    model = PerceiverConfig(num_activities=4, num_objects=6, activity_a_head=False)
    labels = {"activity_a": a, "activity": b % 4, "object": b}
    m = baseline_metrics(labels, labels, model)
    assert m["prior_object_top1"] == pytest.approx(4 / 6)  # A=0's B=4 and A=1's B=5 are missed
    assert m["chance_object_top5"] == pytest.approx(5 / 6) and m["chance_activity_top5"] == 1.0


@pytest.fixture(scope="module")
def intention_run(rendered, tmp_path_factory):
    env, d = rendered
    run_dir = tmp_path_factory.mktemp("intention_run")
    samples = {k: d[k] for k in ("frames", "num_frames", "activity", "object", "activity_a")}
    result = train(
        run_dir,
        lambda p, b, k: intention_loss(p, MODEL, b, k),
        perceiver.init(jax.random.PRNGKey(0), MODEL),
        samples,
        TrainConfig(steps=3, batch=4, warmup_steps=0, log_every=3, val_every=3, ckpt_every=3),
        run_config(MODEL, DATA, None, spacing=2.0),
        val_fn=make_val_fn(MODEL, d, baseline_metrics(d, d, MODEL), compiler_options=FAST),
        progress=False,
        compiler_options=FAST,
    )
    return run_dir, result


def test_a_few_training_steps_run_and_checkpoint(intention_run, rendered):
    run_dir, result = intention_run
    assert result.step == 3 and latest_checkpoint(run_dir).name == "ckpt_00000003.npz"
    log = read_log(run_dir)
    assert log[0]["split"] == "train" and np.isfinite(log[0]["loss"]) and "ce_object" in log[0]
    # Validation reports the predictor's top-5 over every episode, all frames seen: recomputed here.
    d = rendered[1]
    mask = np.arange(4)[None, :] < np.asarray(d["num_frames"])[:, None]
    out = perceiver.apply(result.params, MODEL, jnp.asarray(d["frames"], jnp.float32), jnp.asarray(mask))
    act, obj = (np.asarray(p) for p in perceiver.intention_probs(MODEL, out))
    for name, probs, labels in (("activity", act, d["activity"]), ("object", obj, d["object"])):
        top5 = np.mean([y in np.argsort(-p)[:5] for p, y in zip(probs, np.asarray(labels))])
        assert result.val[f"{name}_top5"] == pytest.approx(top5), name
    assert "prior_activity_top1" in result.val


def test_predictor_steps_under_jit(intention_run, rendered):
    run_dir, _ = intention_run
    predictor = load_intention_predictor(run_dir)
    assert predictor.frame_stride == 2 and predictor.config == MODEL
    # The env's front view at another resolution (resized inside): 32x32 from the 16x16 frames.
    fronts = jax.image.resize(rendered[1]["frames"][0].astype(jnp.float32), (4, 32, 32, 4), "nearest")
    fronts = jnp.concatenate([fronts, fronts[:1]])  # 5 steps

    @jax.jit
    def run(fronts):
        def body(carry, front):
            act, obj, carry = predictor.step(carry, front)
            return carry, (act, obj)

        return jax.lax.scan(body, predictor.init(), fronts)

    carry, (act, obj) = run(fronts)
    assert act.shape == (5, 107) and obj.shape == (5, 51)
    np.testing.assert_allclose(act.sum(-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(obj.sum(-1), 1.0, atol=1e-5)
    # Stride 2: frames recorded at steps 0, 2, 4; as many predictions in the history.
    assert int(carry.num_frames) == 3 and int(carry.num_predictions) == 3 and int(carry.t) == 5
