"""conav_jax.models.perceiver: masked frames change nothing, uint8 frames read as what they
encode, a tiny batch can be memorised, the graph route and the direct heads are reported apart,
and the lowest-entropy averaging picks, averages and falls back as the paper describes."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conav_jax.models import perceiver
from conav_jax.models.perceiver import PerceiverConfig
from conav_jax.optim import adam

# Tiny shapes on a 2-core CPU: LLVM's optimisation passes cost far more compile time than
# they save at run time (3x faster compiles), so the tests' jits skip them.
jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})

CONFIG = PerceiverConfig(image_hw=(16, 16), patch_size=8, dim=32, num_latents=8, num_heads=2, num_blocks=1)
APPLY = jit(perceiver.apply, static_argnums=1)
LOWEST_ENTROPY_AVERAGE = jit(perceiver.lowest_entropy_average, static_argnames="k")
B, N = 4, 3


@pytest.fixture(scope="module")
def params():
    return jit(perceiver.init, static_argnums=1)(jax.random.PRNGKey(0), CONFIG)


@pytest.fixture(scope="module")
def batch():
    rng = np.random.default_rng(0)
    frames = rng.uniform(size=(B, N, 16, 16, 4)).astype(np.float32)
    frames[..., 3] *= 8.0  # depth in metres
    mask = np.array([[1, 1, 1], [1, 1, 0], [1, 0, 0], [0, 1, 1]], bool)
    return frames, mask


def test_outputs_have_one_logit_per_activity_and_object(params, batch):
    out = APPLY(params, CONFIG, *batch)
    assert out.activity.shape == (B, 107) and out.object.shape == (B, 51)


def test_padded_frames_change_nothing_even_if_they_hold_nan(params, batch):
    frames, mask = batch
    out = APPLY(params, CONFIG, frames, mask)
    scrambled = np.where(mask[..., None, None, None], frames, np.float32(np.nan))
    scrambled[2, 1] = 123.0  # and a masked frame with large finite values
    again = APPLY(params, CONFIG, scrambled, mask)
    np.testing.assert_array_equal(out.activity, again.activity)
    np.testing.assert_array_equal(out.object, again.object)


def test_sample_without_valid_frames_gives_finite_prior_logits(params, batch):
    frames, _ = batch
    out = APPLY(params, CONFIG, frames, np.zeros((B, N), bool))
    assert np.isfinite(out.activity).all()
    np.testing.assert_allclose(out.activity[0], out.activity[3], rtol=1e-6)  # same for every sample


def test_uint8_frames_read_as_the_float_frames_they_encode(params, batch):
    frames, mask = batch
    stored = perceiver.encode_frames(jnp.asarray(frames), CONFIG.max_depth_m)
    assert stored.dtype == jnp.uint8 and stored.shape == frames.shape
    # RGB of 8-bit colours comes back exactly; depth to half a step of max_depth / 255.
    decoded = np.asarray(stored, np.float32) / 255.0
    decoded[..., 3] *= CONFIG.max_depth_m
    colours = np.concatenate([np.round(frames[..., :3] * 255.0) / 255.0, frames[..., 3:]], axis=-1).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(perceiver.encode_frames(colours, 10.0))[..., :3] / np.float32(255.0),
                                  colours[..., :3])
    np.testing.assert_allclose(decoded[..., 3], frames[..., 3], atol=CONFIG.max_depth_m / 510 + 1e-6)
    out_u8, out_float = APPLY(params, CONFIG, stored, mask), APPLY(params, CONFIG, decoded, mask)
    np.testing.assert_allclose(out_u8.activity, out_float.activity, atol=1e-4)
    np.testing.assert_allclose(out_u8.activity_a, out_float.activity_a, atol=1e-4)


def test_frames_of_another_size_are_refused(params, batch):
    frames, mask = batch
    with pytest.raises(ValueError, match=r"frames must be \(B, N, 16, 16, 4\)"):
        perceiver.apply(params, CONFIG, frames[:, :, :8], mask)


def test_overfits_a_tiny_batch(params, batch):
    frames, mask = batch
    act = jnp.array([3, 50, 106, 7])
    obj = jnp.array([0, 50, 20, 20])
    opt = adam(3e-3)

    def loss_fn(p):
        out = perceiver.apply(p, CONFIG, frames, mask)
        ce = lambda logits, y: -jnp.mean(jnp.take_along_axis(jax.nn.log_softmax(logits), y[:, None], 1))
        return ce(out.activity, act) + ce(out.object, obj)

    @jit
    def train(p):
        def step(carry, _):
            p, s = carry
            loss, g = jax.value_and_grad(loss_fn)(p)
            p, s = opt.update(g, s, p)
            return (p, s), loss

        (p, _), losses = jax.lax.scan(step, (p, opt.init(p)), None, length=200)
        return losses, loss_fn(p)

    losses, final = train(params)
    assert losses[0] > 5.0  # ~ log(107) + log(51) at init
    assert final < 0.05


def test_lowest_entropy_average_takes_the_k_most_confident_valid_predictions():
    sharp = lambda i: np.eye(4)[i] * 0.97 + 0.01
    flat = np.full(4, 0.25)
    history = np.stack([flat, sharp(0), sharp(1), flat, sharp(2), sharp(3), sharp(0)])[None]
    valid = np.array([[True, True, True, True, True, False, True]])
    out = LOWEST_ENTROPY_AVERAGE(history.astype(np.float32), valid, k=4)
    # The 4 sharp valid ones (steps 1, 2, 4, 6); the invalid sharp step 5 is ignored.
    np.testing.assert_allclose(out[0], np.mean([sharp(0), sharp(1), sharp(2), sharp(0)], 0), rtol=1e-6)


def test_lowest_entropy_average_with_few_or_no_valid_steps():
    history = np.stack([np.eye(3)[0] * 0.9 + 0.05, np.eye(3)[1] * 0.6 + 0.2, np.full(3, 1 / 3)])
    history = np.stack([history, history])  # (2, 3, 3)
    valid = np.array([[True, True, False], [False, False, False]])
    out = LOWEST_ENTROPY_AVERAGE(history.astype(np.float32), valid, k=5)
    np.testing.assert_allclose(out[0], history[0, :2].mean(0), rtol=1e-6)  # fewer than k: those
    np.testing.assert_allclose(out[1], np.full(3, 1 / 3), rtol=1e-6)  # none: uniform


def test_graph_route_maps_a_certain_activity_a_to_its_graph_successors():
    from conav_jax.data.activities import load_activity_graph

    graph = load_activity_graph()
    transition, objects = perceiver.graph_tables(CONFIG)
    np.testing.assert_allclose(transition.sum(1), 1.0, rtol=1e-6)
    np.testing.assert_array_equal(objects.sum(1), 1.0)
    a = next(i for i in range(len(graph.activities)) if graph.successors(i))
    successors = {link.b for link in graph.successors(a)}
    assert set(np.flatnonzero(transition[a])) == successors
    # Certain of A, indifferent heads: p(B) = mix * P(B | A) + (1 - mix) * uniform.
    n, m = CONFIG.num_activities, CONFIG.num_objects
    logits = perceiver.IntentionLogits(jnp.zeros(n), jnp.zeros(m), jnp.full(n, -1e9).at[a].set(0.0))
    act, obj = perceiver.intention_probs(CONFIG, logits)
    w = CONFIG.graph_mix
    np.testing.assert_allclose(act, w * transition[a] + (1 - w) / n, atol=1e-6)
    np.testing.assert_allclose(obj, w * transition[a] @ objects + (1 - w) / m, atol=1e-6)
    assert abs(float(act.sum()) - 1.0) < 1e-5 and abs(float(obj.sum()) - 1.0) < 1e-5
    # Each route apart: the graph prior alone, the direct heads alone, and their mix.
    routes = perceiver.intention_routes(CONFIG, logits)
    np.testing.assert_allclose(routes.graph_prior[0], transition[a], atol=1e-6)
    np.testing.assert_allclose(routes.direct[1], 1.0 / m, rtol=1e-6)
    np.testing.assert_array_equal(routes.mixed[0], act)
    # Without the A head the direct heads alone; a graph route needs the graph's class counts.
    assert perceiver.intention_routes(CONFIG, logits._replace(activity_a=None)).graph_prior is None
    plain = perceiver.intention_probs(CONFIG, logits._replace(activity_a=None))
    np.testing.assert_allclose(plain[0], 1.0 / n, rtol=1e-6)
    with pytest.raises(ValueError, match="activity_a_head=False"):
        perceiver.init(jax.random.PRNGKey(0), PerceiverConfig(num_activities=4, num_objects=6))
    with pytest.raises(ValueError, match="graph_mix"):
        PerceiverConfig(graph_mix=1.5)


def test_seen_objects_keep_only_the_activities_of_objects_the_robot_has_seen():
    transition, objects = perceiver.graph_tables(CONFIG)
    object_of = np.argmax(objects, axis=1)
    n, m = CONFIG.num_activities, CONFIG.num_objects
    # Certain of an A with successors of several objects; the robot has seen A's object and one
    # successor's object, besides one more category.
    a = next(i for i in range(n) if len(set(object_of[np.flatnonzero(transition[i])])) >= 3)
    successor_objects = sorted(set(object_of[np.flatnonzero(transition[a])]))
    seen = np.zeros(m, bool)
    seen[[object_of[a], successor_objects[0], 7]] = True
    rng = np.random.default_rng(0)
    logits = perceiver.IntentionLogits(jnp.asarray(rng.normal(size=n), jnp.float32),
                                       jnp.asarray(rng.normal(size=m), jnp.float32),
                                       jnp.full(n, -1e9).at[a].set(0.0))
    routes = perceiver.intention_routes(CONFIG, logits, objects_seen=jnp.asarray(seen))
    plain = perceiver.intention_routes(CONFIG, logits)
    seen_activity = seen[object_of]
    for name in ("direct", "graph_prior", "mixed"):
        act, obj = (np.asarray(x) for x in getattr(routes, name))
        assert act[~seen_activity].max() == 0.0 and obj[~seen].max() == 0.0, name
        assert act.sum() == pytest.approx(1.0, abs=1e-5) and obj.sum() == pytest.approx(1.0, abs=1e-5), name
    # The graph route: A's row of P(B | A) over the seen Bs, renormalised; the direct heads:
    # their softmax over the seen classes, renormalised.
    row = np.where(seen_activity, transition[a], 0.0)
    np.testing.assert_allclose(routes.graph_prior[0], row / row.sum(), atol=1e-6)
    direct = np.where(seen_activity, np.asarray(plain.direct[0]), 0.0)
    np.testing.assert_allclose(routes.direct[0], direct / direct.sum(), atol=1e-6)
    # An A the robot has not seen the object of gives way to a less likely one it has.
    a2, b2 = next((i, j) for i in range(n) for j in np.flatnonzero(transition[i])
                  if object_of[a] not in (object_of[i], object_of[j]))
    seen2 = np.zeros(m, bool)
    seen2[[object_of[a2], object_of[b2]]] = True
    unseen_a = logits._replace(activity_a=jnp.full(n, -1e9).at[a].set(0.0).at[a2].set(-1.0))
    got = perceiver.intention_routes(CONFIG, unseen_a, objects_seen=jnp.asarray(seen2))
    row = np.where(seen2[object_of], transition[a2], 0.0)
    np.testing.assert_allclose(got.graph_prior[0], row / row.sum(), atol=1e-6)
    # Everything seen, or nothing yet: as without the restriction. A batch restricts each row
    # by its own set.
    for everything_or_nothing in (np.ones(m, bool), np.zeros(m, bool)):
        same = perceiver.intention_routes(CONFIG, logits, objects_seen=jnp.asarray(everything_or_nothing))
        for x, y in zip(jax.tree.leaves(same), jax.tree.leaves(plain)):
            np.testing.assert_allclose(x, y, atol=1e-6)
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), logits)
    both = perceiver.intention_probs(CONFIG, batch, objects_seen=jnp.asarray(np.stack([seen, np.ones(m, bool)])))
    np.testing.assert_allclose(both[0][0], routes.mixed[0], atol=1e-6)
    np.testing.assert_allclose(both[0][1], plain.mixed[0], atol=1e-6)
    with pytest.raises(ValueError, match="objects_seen"):
        perceiver.intention_routes(CONFIG, logits, objects_seen=jnp.ones(m + 1, bool))
    # Weighed, not dropped: the unseen keep their share times the weight.
    weights = {"activity_a": 0.5, "activity_b": 0.25}
    soft = perceiver.intention_routes(CONFIG, logits, objects_seen=jnp.asarray(seen), unseen_weights=weights)
    row = transition[a] * np.where(seen_activity, 1.0, 0.25)
    np.testing.assert_allclose(soft.graph_prior[0], row / row.sum(), atol=1e-6)
    direct = np.asarray(plain.direct[1]) * np.where(seen, 1.0, 0.25)
    np.testing.assert_allclose(soft.direct[1], direct / direct.sum(), atol=1e-6)


def test_seen_object_weights_are_the_odds_ratio_of_not_seeing_the_true_object():
    # Three samples, four categories. Object B 2 is seen in 2 of 3 samples (odds of not seeing
    # it (1 + 1) / (2 + 1)); the other categories in 3 of 9 (odds (6 + 1) / (3 + 1)).
    seen = np.array([[1, 0, 1, 0], [0, 1, 1, 0], [1, 0, 0, 0]], bool)
    w = perceiver.seen_object_weights(seen, object_a=np.array([0, 1, 0]), object_b=np.array([2, 2, 2]))
    assert w["activity_b"] == pytest.approx((2 / 3) / (7 / 4))
    # Object A (0, 1, 0) is seen in all three: odds (0 + 1) / (3 + 1); others: 2 of 9 seen.
    assert w["activity_a"] == pytest.approx((1 / 4) / (8 / 3))
    with pytest.raises(ValueError, match="objects_seen must be"):
        perceiver.seen_object_weights(seen[0], np.zeros(3, int), np.zeros(3, int))
    assert perceiver.check_unseen_weights(w) == w
    with pytest.raises(ValueError, match="finite"):
        perceiver.check_unseen_weights({"activity_a": float("nan"), "activity_b": 0.2})


def test_counted_transition_replaces_the_uniform_graph_rows_it_has_data_for():
    a, b = np.array([3, 3, 3, 7]), np.array([5, 5, 9, 2])
    triples = perceiver.count_transitions(a, b)
    assert triples == [[3, 5, 2], [3, 9, 1], [7, 2, 1]]
    t = perceiver.transition_from_counts(CONFIG, triples)
    uniform, _ = perceiver.graph_tables(CONFIG)
    np.testing.assert_allclose(t[3, [5, 9]], [2 / 3, 1 / 3], rtol=1e-6)
    assert t[3].sum() == pytest.approx(1.0) and t[7, 2] == 1.0
    np.testing.assert_array_equal(t[0], uniform[0])  # no episode starts with A = 0: the graph's row
    # The graph route steps through the table it is given.
    n, m = CONFIG.num_activities, CONFIG.num_objects
    logits = perceiver.IntentionLogits(jnp.zeros(n), jnp.zeros(m), jnp.full(n, -1e9).at[3].set(0.0))
    routes = perceiver.intention_routes(CONFIG, logits, t)
    np.testing.assert_allclose(routes.graph_prior[0], t[3], atol=1e-6)
    with pytest.raises(ValueError, match="transition must have shape"):
        perceiver.intention_routes(CONFIG, logits, t[:5])
    with pytest.raises(ValueError, match="activities in"):
        perceiver.transition_from_counts(CONFIG, [[3, n, 1]])
    with pytest.raises(ValueError, match="1-D of one length"):
        perceiver.count_transitions(a, b[:2])
