"""Intention predictor training: rendered crops show the human, the prior baseline, a short
run that checkpoints and validates on minival by route, and the per-step predictor under jit
seeing exactly the training frames."""

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conav_jax.checkpoints import latest_checkpoint, load_checkpoint, save_checkpoint
from conav_jax.geometry import to_frame
from conav_jax.models import perceiver
from conav_jax.data.categories import CATEGORIES
from conav_jax.models.perceiver import PerceiverConfig
from conav_jax.models.policy import categories_in_view
from conav_jax.nav.navigation import line_of_sight
from conav_jax.runs import read_log
from conav_jax.envs.agents.base import ORACLE_SEGMENTATION
from conav_jax.envs.agents.predictors import FrameSpec, intention_frame, load_intention_predictor, make_intention_predictor
from conav_jax.envs.humanoid import capsule_colours
from conav_jax.envs.panorama import front_view
from conav_jax.train.intention import (
    IntentionDataConfig,
    activity_a_steps,
    baseline_metrics,
    frame_spec,
    make_env,
    make_renderer,
    intention_loss,
    recolour_frames,
    make_val_fn,
    prior_scores,
    render_split,
    robot_poses,
    run_config,
    same_object_top1,
    topk_accuracy,
    train_intention,
    train_intention_from_data,
)
from conav_jax.train.loop import TrainConfig

FAST = {"xla_backend_optimization_level": 0}
# 16x16 crops of 32x128 panoramas: at this resolution a human 1.5-3 m away is 9-19 rows tall.
# Two viewpoints: each episode's start pose and one drawn around the human.
# Flat colours: the human's pixels are told by their colour.
DATA = IntentionDataConfig(resolution=(32, 128), materials="flat", frames=4, viewpoints=2)
MODEL = PerceiverConfig(image_hw=(16, 16), dim=16, num_latents=4, num_heads=2, num_blocks=0)


@pytest.fixture(scope="module")
def rendered(tiny_data):
    env = make_env(tiny_data, "train", DATA)
    return env, render_split(env, MODEL, DATA, compiler_options=FAST)


def test_activity_a_steps_spread_over_activity_a():
    steps, num = activity_a_steps(np.array([31, 2]), 4)
    np.testing.assert_array_equal(steps, [[0, 10, 20, 30], [0, 1, 1, 1]])
    np.testing.assert_array_equal(num, [4, 2])


def test_viewpoints_are_the_start_pose_then_clear_views_of_the_human(rendered):
    env, _ = rendered
    eps = env.split.episodes
    poses = robot_poses(env, 3)
    assert poses.shape == (env.num_episodes, 3, 3)
    np.testing.assert_array_equal(poses[:, 0], eps["robot_start"])
    np.testing.assert_array_equal(robot_poses(env, 3), poses)  # the same draws every time
    lo, hi = env.task.robot_start_distance_m
    for e in range(env.num_episodes):
        grid = env.split.navs[int(eps["scene_index"][e])].grid
        for v in (1, 2):
            assert not np.array_equal(poses[e, v], poses[e, 0])
            assert lo <= np.linalg.norm(poses[e, v, :2] - eps["root_xy"][e, 0]) <= hi
            assert grid.is_free(poses[e, v, :2]) and line_of_sight(grid, poses[e, v, :2], eps["root_xy"][e, 0])
            ahead = np.asarray(to_frame(eps["root_xy"][e, 0], poses[e, v, :2], poses[e, v, 2]))
            assert abs(np.arctan2(ahead[1], ahead[0])) <= 0.25 + 1e-5  # facing the human, as start poses do


def test_the_renderer_takes_the_episode_bank_as_an_argument_not_as_constants(rendered):
    import re

    env, _ = rendered
    render = make_renderer(env, MODEL, frame_spec(env, DATA), 4, FAST)
    one = jnp.zeros((1,), jnp.int32)
    text = render.lower(one, one, jnp.zeros((1, 3)), jnp.zeros((1, 2))).as_text()
    n, t = env.bank.joints_local.shape[:2]
    assert f"tensor<{n}x{t}x22x3xf16>" in text  # the humanoid's joints: an argument
    biggest = max((len(c) for c in re.findall(r'dense<"0x[0-9A-F]*">', text)), default=0)
    assert biggest < 4 * int(env.bank.fields[0, 0].size), biggest


def test_rendered_crops_show_the_human(rendered):
    env, d = rendered
    n = 2 * env.num_episodes  # two viewpoints per episode, next to each other
    assert d["frames"].shape == (n, 4, 16, 16, 4) and d["frames"].dtype == jnp.uint8
    assert d["num_frames"].shape == (n,) and d["human_pos"].shape == (n, 4, 2)
    np.testing.assert_array_equal(d["activity"], np.repeat(env.split.episodes["activity_b"], 2))
    # The robot starts near the human: every frame's crop shows it, and most of it (16 rows of
    # a 32-row panorama leave the feet of the closest humans out)...
    seen, total = np.asarray(d["human_pixels"]), np.asarray(d["human_pixels_sensor"])
    assert (seen > 0).all() and seen.sum() > 0.85 * total.sum()
    # ...its pixels carry the capsules' colours (uint8: within half a step, 2e-3)...
    rgb = np.asarray(d["frames"][..., :3], np.float32).reshape(n, 4, -1, 1, 3) / 255.0
    is_human = np.any(np.all(np.abs(rgb - capsule_colours()[None, None, None]) < 2e-3, axis=-1), axis=-1)
    np.testing.assert_array_equal(is_human.sum(-1), seen)
    # ...and it is 1.5-3 m away, where the robot starts, at any bearing from the other viewpoint.
    dist = np.linalg.norm(np.asarray(d["human_pos"]), axis=-1)
    assert dist.min() > 1.3 and dist.max() < 3.3


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
def intention_run(rendered, tiny_data, tmp_path_factory):
    """A run trained on env objects: the train env above, minival's as `make_env` builds it."""
    run_dir = tmp_path_factory.mktemp("intention_run")
    cfg = TrainConfig(steps=40, batch=8, lr=3e-3, warmup_steps=0, log_every=10, val_every=40, ckpt_every=40)
    result = train_intention(rendered[0], make_env(tiny_data, "minival", DATA), run_dir, cfg, MODEL, DATA,
                             progress=False, compiler_options=FAST)
    return run_dir, result


def test_a_short_run_checkpoints_and_validates_on_minival(intention_run):
    run_dir, result = intention_run
    assert result.step == 40 and latest_checkpoint(run_dir).name == "ckpt_00000040.npz"
    log = read_log(run_dir)
    train_log = [r for r in log if r["split"] == "train"]
    assert all(r["val_split"] == "minival" for r in log) and "ce_activity_a" in train_log[0]
    assert train_log[-1]["loss"] < train_log[0]["loss"]  # it learns (the tiny train split)
    # Each route reported: the predictor's output, the direct heads without the generator's
    # graph, and the graph prior alone; the watched activity A; the data's sanity checks.
    for key in ("activity_top1", "object_top5_direct", "activity_top1_generator_graph_prior", "activity_a_top5",
                "prior_activity_top1", "val_frames_with_human", "val_human_pixels_in_view"):
        assert key in result.val, key
    assert result.val["val_frames_with_human"] == 1.0


def test_a_run_on_env_objects_records_their_dataset_and_refuses_envs_its_config_does_not_name(
        intention_run, rendered, tiny_data, tmp_path):
    from worlds import make_split

    from conav_jax.data.episodes import read_manifest
    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig

    run_dir, _ = intention_run
    config = load_checkpoint(latest_checkpoint(run_dir)).config
    assert config["data"]["content_hash"] == read_manifest(tiny_data)["content_hash"]  # the env's dataset
    train_env = rendered[0]
    minival = make_env(tiny_data, "minival", DATA)
    cfg = TrainConfig(steps=1, batch=4, warmup_steps=0)
    hand_made = ConavEnv(episodes=dataclasses.replace(make_split([(5.0, 2.0, 0.0)]), name="minival"),
                         config=EnvConfig(sensor=SensorConfig(resolution=DATA.resolution, materials=DATA.materials)))
    refused = {
        "train_env holds the 'minival' split; expected 'train'": (minival, minival, DATA),
        r"IntentionDataConfig.resolution is \(16, 64\) but train_env renders \(32, 128\)":
            (train_env, minival, dataclasses.replace(DATA, resolution=(16, 64))),
        "IntentionDataConfig.materials is 'instance' but train_env renders 'flat'":
            (train_env, minival, dataclasses.replace(DATA, materials="instance")),
        "train_env and val_env come from different datasets": (train_env, hand_made, DATA),
    }
    for message, (train, val, data) in refused.items():
        with pytest.raises(ValueError, match=message):
            train_intention(train, val, tmp_path / "run", cfg, MODEL, data, progress=False, compiler_options=FAST)
    assert not (tmp_path / "run").exists()


def test_a_run_weighing_seen_objects_records_its_weights_and_validates_with_them(rendered, tiny_data, tmp_path,
                                                                                   monkeypatch):
    from conav_jax.train import intention

    _, d = rendered
    asked = []
    real = intention.make_val_fn
    monkeypatch.setattr(intention, "make_val_fn", lambda *a, **k: asked.append(k) or real(*a, **k))
    losses, real_loss = [], intention.intention_loss
    monkeypatch.setattr(intention, "intention_loss", lambda *a, **k: losses.append(k) or real_loss(*a, **k))
    model = dataclasses.replace(MODEL, seen_objects=True)
    cfg = TrainConfig(steps=2, batch=4, warmup_steps=0, log_every=1, val_every=2, ckpt_every=2)
    # (The same run checks that the data options it records are those it trains with.)
    data = dataclasses.replace(DATA, recolour=True)
    train_intention_from_data(tiny_data, tmp_path / "run", cfg, model, data, progress=False, compiler_options=FAST)
    config = load_checkpoint(latest_checkpoint(tmp_path / "run")).config
    assert config["data"]["recolour"] is True and losses and all(k["recolour"] is True for k in losses)
    weights = intention.start_pose_weights(model, d, DATA.viewpoints)
    assert config["data"]["seen_object_weights"] == weights and config["model"]["seen_objects"] is True
    assert 0.0 < weights["activity_b"] < 1.0
    assert asked[0]["seen_objects"] is True and asked[0]["unseen_weights"] == weights
    assert load_intention_predictor(tmp_path / "run").privileged == (ORACLE_SEGMENTATION,)
    # Runs without it keep the config they had: no seen_objects key, no weights.
    plain = run_config(MODEL, DATA, None, 1.0, 1.25)
    assert "seen_objects" not in plain["model"] and "seen_object_weights" not in plain["data"]


def test_validation_reports_each_route_over_every_episode(rendered):
    # Recomputed here, all frames seen: the predictor's top-5 and the direct heads' top-1.
    d = rendered[1]
    params = perceiver.init(jax.random.PRNGKey(1), MODEL)
    val = make_val_fn(MODEL, d, {}, batch=5, compiler_options=FAST)(params)
    mask = np.arange(4)[None, :] < np.asarray(d["num_frames"])[:, None]
    routes = perceiver.intention_routes(MODEL, perceiver.apply(params, MODEL, d["frames"], jnp.asarray(mask)))
    for name, k, (act, obj), suffix in (("top5", 5, routes.mixed, ""), ("top1", 1, routes.direct, "_direct")):
        for head, probs in (("activity", act), ("object", obj)):
            hits = np.mean([y in np.argsort(-p)[:k] for p, y in zip(np.asarray(probs), np.asarray(d[head]))])
            assert val[f"{head}_{name}{suffix}"] == pytest.approx(hits), (head, name, suffix)
    watched = np.asarray(perceiver.apply(params, MODEL, d["frames"], jnp.asarray(mask)).activity_a)
    assert val["activity_a_object_top1"] == same_object_top1(MODEL, watched, np.asarray(d["activity_a"]))


def _mirror_by_hand(frames, key):
    flip = np.asarray(jax.random.bernoulli(key, 0.5, (frames.shape[0],)))
    assert 0 < flip.sum() < frames.shape[0]  # the draw mirrors some samples and not others
    return jnp.asarray(np.where(flip[:, None, None, None, None], np.asarray(frames)[:, :, :, ::-1], frames))


@pytest.mark.parametrize("option, by_hand", [("mirror", _mirror_by_hand), ("recolour", lambda f, k: recolour_frames(f, k))])
def test_an_augmenting_loss_reads_its_transformed_frames_and_only_its_runs_say_so(rendered, option, by_hand):
    d = rendered[1]
    params = perceiver.init(jax.random.PRNGKey(1), MODEL)
    batch = {k: jnp.asarray(d[k][:6]) for k in ("frames", "num_frames", "activity", "object", "activity_a")}
    key = jax.random.PRNGKey(3)
    augmented, _ = jax.jit(lambda b: intention_loss(params, MODEL, b, key, **{option: True}))(batch)
    # The loss's draw, and the key left for the rest of the loss.
    k_rest, k_option = jax.random.split(key)
    expected, _ = intention_loss(params, MODEL, {**batch, "frames": by_hand(batch["frames"], k_option)}, k_rest)
    plain, _ = intention_loss(params, MODEL, batch, k_rest)
    assert augmented == pytest.approx(float(expected), rel=1e-5) and augmented != pytest.approx(float(plain), rel=1e-5)
    # A run's config names the option only where it is on (runs from before it resume).
    assert option not in run_config(MODEL, DATA, None, 1.0, 1.25)["data"]
    assert run_config(MODEL, dataclasses.replace(DATA, **{option: True}), None, 1.0, 1.25)["data"][option] is True


def test_recoloured_samples_keep_their_depth_and_share_one_colour_map_over_their_frames():
    key = jax.random.PRNGKey(5)
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (8, 3, 5, 6, 4), dtype=np.uint8)
    out = np.asarray(recolour_frames(jnp.asarray(frames), key))
    assert out.dtype == np.uint8 and out.shape == frames.shape
    np.testing.assert_array_equal(out[..., 3], frames[..., 3])  # depth untouched
    # Each sample's map is a channel order and gains, the same for every frame and pixel:
    # recovered from the draw, it reproduces the output to within uint8 rounding.
    k_perm, k_gain = jax.random.split(key)
    order = np.asarray(jax.vmap(lambda k: jax.random.permutation(k, 3))(jax.random.split(k_perm, 8)))
    gain = np.asarray(jax.random.uniform(k_gain, (8, 3), minval=0.6, maxval=1.4))
    by_hand = np.clip(np.take_along_axis(frames[..., :3] / 255.0, order[:, None, None, None, :], -1)
                      * gain[:, None, None, None, :], 0.0, 1.0)
    np.testing.assert_allclose(out[..., :3] / 255.0, by_hand, atol=0.51 / 255.0)
    assert len({tuple(o) for o in order}) > 1 and not np.allclose(out[..., :3], frames[..., :3], atol=2)
    # Float frames (depth in metres) keep their depth and dtype too.
    as_float = np.concatenate([frames[..., :3] / 255.0, frames[..., 3:] / 10.0], -1).astype(np.float32)
    out_f = np.asarray(recolour_frames(jnp.asarray(as_float), key))
    assert out_f.dtype == np.float32 and np.array_equal(out_f[..., 3], as_float[..., 3])
    np.testing.assert_allclose(out_f[..., :3], by_hand, atol=1e-6)


def test_an_activity_of_the_true_activitys_object_counts_as_the_same_object():
    object_of = perceiver.activity_objects(MODEL)
    a, sibling = next((a, b) for a in range(len(object_of)) for b in range(a + 1, len(object_of))
                      if object_of[b] == object_of[a])
    other = next(b for b in range(len(object_of)) if object_of[b] != object_of[a])
    scores = np.eye(len(object_of))[[a, sibling, other]]  # top-1: the true A, another of its object, neither
    assert same_object_top1(MODEL, scores, np.array([a, a, a])) == pytest.approx(2 / 3)


def _panoramas(env, d, episode):
    """The env's observations `rgbd (F, H, W, 4)`, `segmentation (F, H, W)`, `human_pos (F, 2)`
    of `episode`'s training frames from its start pose (its first viewpoint)."""
    steps, _ = activity_a_steps(env.split.episodes["t_walk_start"], DATA.frames)

    def one(t):
        rgbd, ids = env.render_at(episode, env.bank.robot_start[episode], t)
        return rgbd, env.segmentation(ids, episode)

    rgbd, segmentation = jax.jit(jax.vmap(one))(steps[episode])
    return {"rgbd": rgbd, "segmentation": segmentation, "human_pos": d["human_pos"][2 * episode]}


def _run_predictor(predictor, obs):
    @jax.jit
    def run(obs):
        def body(carry, o):
            act, obj, carry = predictor.step(carry, o)
            return carry, (act, obj)

        return jax.lax.scan(body, predictor.init(), obs)

    return run(obs)


def test_the_predictor_sees_exactly_the_training_frames(intention_run, rendered, tiny_data):
    from conav_jax import runs
    from conav_jax.envs.conav_env import ConavEnv

    run_dir, result = intention_run
    env, d = rendered
    predictor = load_intention_predictor(run_dir, frame_stride=1)
    assert predictor.config == MODEL and predictor.spec == FrameSpec("human", (32, 128), 1.25)
    obs = _panoramas(env, d, 0)
    carry, (act, obj) = _run_predictor(predictor, obs)
    np.testing.assert_array_equal(carry.frames, d["frames"][0])  # crops from the observations
    assert act.shape == (4, 107) and obj.shape == (4, 51)
    # Its graph route steps through P(B | A) counted on the train split, recorded in the run:
    # the first output (one frame, one prediction) is the Perceiver's through the counts.
    train_eps = ConavEnv(tiny_data, "train").split.episodes
    counts = runs.run_config(run_dir, runs.INTENTION)["data"]["transition_counts"]
    assert counts == perceiver.count_transitions(train_eps["activity_a"], train_eps["activity_b"])
    logits = perceiver.apply(result.params, MODEL, d["frames"][:1, :1], jnp.ones((1, 1), bool))
    want = perceiver.intention_probs(MODEL, logits, perceiver.transition_from_counts(MODEL, counts))
    np.testing.assert_allclose(act[0], want[0][0], atol=1e-5)
    np.testing.assert_allclose(obj[0], want[1][0], atol=1e-5)
    assert not np.allclose(act[0], perceiver.intention_probs(MODEL, logits)[0][0], atol=1e-4)  # not the uniform links
    np.testing.assert_allclose(act.sum(-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(obj.sum(-1), 1.0, atol=1e-5)
    # The default stride: the training frames' spacing; a frame every `stride` steps.
    strided = load_intention_predictor(run_dir)
    assert strided.frame_stride > 1
    carry, _ = _run_predictor(strided, jax.tree.map(lambda x: jnp.concatenate([x, x[:1]]), obs))
    expected = -(-5 // strided.frame_stride)
    assert int(carry.num_frames) == expected == int(carry.num_predictions) and int(carry.t) == 5


@pytest.mark.parametrize("seen_objects", [False, True])
def test_under_vmap_each_lane_gets_what_it_gets_alone(seen_objects):
    """A batch of envs at different steps, whose recording lanes the batched predictor gathers
    in chunks (two passes when most lanes record at once): every lane's outputs and carry are
    those of the same predictor stepped alone (with the objects each lane's panoramas show)."""
    model = PerceiverConfig(image_hw=(16, 16), dim=16, num_latents=4, num_heads=2, num_blocks=1,
                            seen_objects=seen_objects)
    predictor = make_intention_predictor(perceiver.init(jax.random.key(0), model), model, 4,
                                         FrameSpec("front", (16, 64)), frame_stride=3, history=4, top_k=2)
    lanes, steps = 9, 7
    rgbd = jax.random.uniform(jax.random.key(1), (lanes, steps, 16, 64, 4), maxval=4.0)
    # A few object categories in each panorama, different in each lane and step.
    drawn = jax.random.randint(jax.random.key(2), (lanes, steps, 16, 1), 0, len(CATEGORIES))
    obs = {"rgbd": rgbd, "segmentation": jnp.broadcast_to(drawn, (lanes, steps, 16, 64)),
           "human_pos": jnp.ones((lanes, steps, 2))}
    # Seven lanes record on the first step (two passes of chunks of six), the others later.
    starts = jnp.array([0] * 7 + [1, 2], jnp.int32)

    def run(start, obs):
        def body(carry, o):
            act, obj, carry = predictor.step(carry, o)
            return carry, (act, obj)
        return jax.lax.scan(body, predictor.init()._replace(t=start), obs)

    batched = jax.jit(jax.vmap(run))(starts, obs)
    for lane in range(lanes):
        alone = jax.jit(run)(starts[lane], jax.tree.map(lambda x: x[lane], obs))
        for got, want in zip(jax.tree.leaves(batched), jax.tree.leaves(alone)):
            np.testing.assert_allclose(got[lane], want, atol=1e-6, err_msg=f"lane {lane}")
    carry, (act, _) = batched
    assert np.asarray(carry.num_predictions).tolist() == [3] * 7 + [2, 2]
    assert len({tuple(np.round(a, 4)) for a in np.asarray(act[:, -1])}) == lanes  # lanes saw different frames
    assert np.asarray(carry.objects_seen).any() == seen_objects  # kept only where it is on


def test_with_seen_objects_the_predictor_names_only_activities_of_objects_its_panoramas_showed(intention_run, rendered,
                                                                                              tmp_path):
    run_dir, result = intention_run
    env, d = rendered
    obs = _panoramas(env, d, 0)
    # What the whole panoramas show, as the training samples record it.
    in_view = np.asarray(jax.vmap(categories_in_view)(obs["segmentation"]))
    np.testing.assert_array_equal(d["objects_seen"][0], in_view)
    assert in_view.any(axis=1).all()  # every frame shows some object
    config = dataclasses.replace(MODEL, seen_objects=True)
    predictor = make_intention_predictor(result.params, config, DATA.frames, FrameSpec("human", (32, 128), 1.25))
    assert predictor.privileged == (ORACLE_SEGMENTATION,)
    assert load_intention_predictor(run_dir).privileged == ()
    # A run weighing seen objects records its weights (train_intention does); without them it
    # does not load.
    seen_run = tmp_path / "seen"
    ckpt = load_checkpoint(latest_checkpoint(run_dir))
    config = {**ckpt.config, "model": {**ckpt.config["model"], "seen_objects": True}}
    save_checkpoint(seen_run / "ckpt_00000001.npz", params=result.params, opt_state=None, config=config, step=1)
    with pytest.raises(ValueError, match="records no seen_object_weights"):
        load_intention_predictor(seen_run)
    config["data"] = {**config["data"], "seen_object_weights": {"activity_a": 0.1, "activity_b": 0.3}}
    save_checkpoint(seen_run / "ckpt_00000002.npz", params=result.params, opt_state=None, config=config, step=2)
    assert load_intention_predictor(seen_run).privileged == (ORACLE_SEGMENTATION,)
    # Malformed weights are refused by name, not read as zeros.
    for bad, why in (({"activity_b": 0.3}, "keys"), ({"activity_a": 0.1, "activity_b": -1.0}, ">= 0"),
                     ({"activity_a": 0.1, "activity_b": "x"}, "a number")):
        config["data"] = {**config["data"], "seen_object_weights": bad}
        save_checkpoint(seen_run / "ckpt_00000003.npz", params=result.params, opt_state=None, config=config, step=3)
        with pytest.raises(ValueError, match=f"seen_object_weights: .*{re.escape(why)}"):
            load_intention_predictor(seen_run)
    carry, (act, obj) = _run_predictor(predictor, obs)
    np.testing.assert_array_equal(carry.objects_seen, in_view.any(axis=0))
    # The first output: the Perceiver on one frame, restricted to what that frame showed.
    logits = perceiver.apply(result.params, MODEL, d["frames"][:1, :1], jnp.ones((1, 1), bool))
    want = perceiver.intention_probs(MODEL, logits, objects_seen=jnp.asarray(in_view[:1]))
    np.testing.assert_allclose(act[0], want[0][0], atol=1e-5)
    np.testing.assert_allclose(obj[0], want[1][0], atol=1e-5)
    assert np.asarray(obj)[:, ~in_view.any(axis=0)].max() == 0.0
    # Validation scores the restricted routes when asked, over what each sample's frames showed.
    params = perceiver.init(jax.random.PRNGKey(1), MODEL)
    val = make_val_fn(MODEL, d, {}, batch=5, compiler_options=FAST, seen_objects=True)(params)
    mask = np.arange(4)[None, :] < np.asarray(d["num_frames"])[:, None]
    seen = jnp.asarray((np.asarray(d["objects_seen"]) & mask[..., None]).any(axis=1))
    routes = perceiver.intention_routes(MODEL, perceiver.apply(params, MODEL, d["frames"], jnp.asarray(mask)),
                                        objects_seen=seen)
    plain = make_val_fn(MODEL, d, {}, batch=5, compiler_options=FAST)(params)
    for head, probs in (("activity", routes.mixed[0]), ("object", routes.mixed[1])):
        for k in (1, 5):
            hits = np.mean([y in np.argsort(-p)[:k] for p, y in zip(np.asarray(probs), np.asarray(d[head]))])
            assert val[f"{head}_top{k}"] == pytest.approx(hits), (head, k)
    assert any(val[key] != plain[key] for key in ("activity_top1", "activity_top5", "object_top1", "object_top5"))


def test_the_predictor_refuses_bad_observations(intention_run, rendered):
    run_dir, _ = intention_run
    env, d = rendered
    predictor = load_intention_predictor(run_dir, frame_stride=1)
    obs = _panoramas(env, d, 0)
    # A NaN human position cannot raise under jit: from that step on every output is NaN.
    nan_obs = {**obs, "human_pos": obs["human_pos"].at[2].set(jnp.nan)}
    _, (act, obj) = _run_predictor(predictor, nan_obs)
    assert np.isfinite(act[:2]).all() and np.isnan(act[2:]).all() and np.isnan(obj[3]).all()
    one = jax.tree.map(lambda x: x[0], obs)
    with pytest.raises(ValueError, match="finite"):
        predictor.step(predictor.init(), {**one, "human_pos": jnp.array([np.nan, 1.0])})
    with pytest.raises(ValueError, match=r"render the env with SensorConfig\(resolution=\(32, 128\)\)"):
        predictor.step(predictor.init(), {**one, "rgbd": jnp.zeros((16, 64, 4))})
    with pytest.raises(ValueError, match="mapping with 'rgbd'"):
        predictor.step(predictor.init(), one["rgbd"])
    with pytest.raises(ValueError, match="does not fit"):
        intention_frame(FrameSpec("human", (8, 32)), MODEL, jnp.zeros((8, 32, 4)), jnp.array([2.0, 0.0]))


def test_runs_from_before_the_crop_load_and_read_the_front_view(intention_run, rendered, tmp_path):
    run_dir, result = intention_run
    env, d = rendered
    ckpt = latest_checkpoint(run_dir)
    old_config = {k: v for k, v in load_checkpoint(ckpt).config.items() if k != "train"}
    old_config["data"] = {"sensor_hw": [16, 64], "frames": 4, "content_hash": None, "frame_spacing_steps": 2.0}
    save_checkpoint(tmp_path / "ckpt_00000001.npz", params=result.params, opt_state=None, config=old_config, step=1)
    predictor = load_intention_predictor(tmp_path)
    assert predictor.spec == FrameSpec("front", (16, 64), 1.25) and predictor.frame_stride == 2
    # Front views at any resolution, resized to the frame, as before the crop.
    obs = _panoramas(env, d, 0)
    carry, (act, _) = _run_predictor(predictor, obs)
    expected = jax.image.resize(front_view(obs["rgbd"][0]), (16, 16, 4), "linear")
    np.testing.assert_array_equal(carry.frames[0], perceiver.encode_frames(expected, MODEL.max_depth_m))
    assert np.isfinite(act).all()



def test_bench_intention_scores_a_run_by_route_as_its_own_validation(intention_run, tiny_data, capsys, monkeypatch):
    import json

    from conav_jax import runs
    from conav_jax.eval import cli
    from conav_jax.train import intention

    run_dir, result = intention_run
    tables, seen = [], []  # the P(B | A) each route is scored with (tiny minival's scores coincide)
    real = intention.make_val_fn
    monkeypatch.setattr(intention, "make_val_fn", lambda *a, transition=None, seen_objects=False, **k:
                        tables.append(transition) or seen.append(seen_objects)
                        or real(*a, transition=transition, seen_objects=seen_objects, **k))
    assert cli.main(["bench", "intention", "--run", str(run_dir), "--data", str(tiny_data), "--split", "minival",
                     "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    counts = runs.run_config(run_dir, runs.INTENTION)["data"]["transition_counts"]
    np.testing.assert_array_equal(tables[0], perceiver.transition_from_counts(MODEL, counts))
    assert tables[1] is None and set(res) == {"run", "split", "counted", "graph", "counted_seen_objects"}
    # The third route: the counted P(B | A), restricted to the objects the panoramas showed.
    np.testing.assert_array_equal(tables[2], tables[0])
    assert seen == [False, False, True]
    # The run records no weights (trained without --seen-objects): those of the train split's
    # start poses, rendered for the score.
    assert 0.0 < res["counted_seen_objects"]["unseen_weight_activity_b"] < 1.0
    assert "unseen_weight_activity_b" not in res["counted"]
    # The counted route is what the run validated with.
    for key in ("activity_top5", "object_top5", "activity_a_top1", "activity_top1_direct"):
        assert res["counted"][key] == pytest.approx(result.val[key]), key
    assert set(res["counted"]) == set(res["graph"])
