"""conav_jax.optim: Adam/AdamW against the update formula in numpy, global-norm clipping,
and the warm-up cosine schedule."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conav_jax.optim import adam, adamw, clip_by_global_norm, global_norm, warmup_cosine

PARAMS = {"w": np.array([[0.5, -1.0], [2.0, 0.0]], np.float32), "b": [np.array([0.1, -0.2, 0.3], np.float32)]}
GRADS = [
    {"w": np.array([[0.1, 0.2], [-0.3, 0.0]], np.float32), "b": [np.array([1.0, -1.0, 0.5], np.float32)]},
    {"w": np.array([[-0.2, 0.1], [0.3, 0.4]], np.float32), "b": [np.array([0.5, 0.0, -2.0], np.float32)]},
    {"w": np.array([[0.0, -0.5], [0.1, 0.2]], np.float32), "b": [np.array([-1.0, 0.3, 0.2], np.float32)]},
]


def _numpy_adam(lrs, b1, b2, eps, wd):
    """The textbook update, leaf by leaf, in float64."""
    params = jax.tree_util.tree_map(lambda p: p.astype(np.float64), PARAMS)
    mu = jax.tree_util.tree_map(np.zeros_like, params)
    nu = jax.tree_util.tree_map(np.zeros_like, params)
    history = []
    for t, (g, lr) in enumerate(zip(GRADS, lrs), start=1):
        mu = jax.tree_util.tree_map(lambda m, g: b1 * m + (1 - b1) * g, mu, g)
        nu = jax.tree_util.tree_map(lambda v, g: b2 * v + (1 - b2) * g * g, nu, g)
        params = jax.tree_util.tree_map(
            lambda p, m, v: p - lr * ((m / (1 - b1**t)) / (np.sqrt(v / (1 - b2**t)) + eps) + wd * p),
            params, mu, nu,
        )
        history.append(params)
    return history


@pytest.mark.parametrize("weight_decay", [0.0, 0.1])
def test_adam_matches_the_update_formula_for_three_steps(weight_decay):
    lrs = [0.01, 0.02, 0.005]
    schedule = lambda step: jnp.asarray(lrs)[step]  # a schedule, read at the pre-update step
    opt = adam(schedule, b1=0.8, b2=0.9, eps=1e-6, weight_decay=weight_decay)
    update = jax.jit(opt.update)
    params, state = PARAMS, opt.init(PARAMS)
    for t, (grads, expected) in enumerate(zip(GRADS, _numpy_adam(lrs, 0.8, 0.9, 1e-6, weight_decay)), 1):
        params, state = update(grads, state, params)
        assert int(state.step) == t
        for got, want in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(expected)):
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-7)


def test_adamw_decays_weights_even_with_zero_gradient():
    opt = adamw(0.1, weight_decay=0.5)
    params = {"w": np.ones(3, np.float32)}
    new, _ = opt.update({"w": np.zeros(3, np.float32)}, opt.init(params), params)
    np.testing.assert_allclose(new["w"], 1 - 0.1 * 0.5, rtol=1e-6)  # decoupled: lr * wd * p only


def test_adam_first_step_moves_each_weight_by_the_learning_rate():
    # Bias correction makes step 1 exactly lr * sign(g) (up to eps), whatever the scale of g.
    opt = adam(1e-3)
    params = {"w": np.zeros(3, np.float32)}
    new, _ = opt.update({"w": np.array([1e-4, -50.0, 3.0], np.float32)}, opt.init(params), params)
    np.testing.assert_allclose(new["w"], [-1e-3, 1e-3, -1e-3], rtol=1e-3)


def test_clip_by_global_norm_scales_to_the_limit_and_keeps_direction():
    grads = {"a": np.array([3.0, 0.0], np.float32), "b": [np.array([[4.0]], np.float32)]}  # norm 5
    clipped, norm = clip_by_global_norm(grads, 1.0)
    assert float(norm) == pytest.approx(5.0)
    assert float(global_norm(clipped)) == pytest.approx(1.0)
    np.testing.assert_allclose(clipped["a"], [0.6, 0.0], rtol=1e-6)
    np.testing.assert_allclose(clipped["b"][0], [[0.8]], rtol=1e-6)


def test_clip_by_global_norm_leaves_small_and_zero_gradients_alone():
    grads = {"a": np.array([0.3, 0.4], np.float32)}
    clipped, norm = clip_by_global_norm(grads, 1.0)
    np.testing.assert_array_equal(clipped["a"], grads["a"])
    zero, norm = clip_by_global_norm({"a": np.zeros(2, np.float32)}, 1.0)
    assert float(norm) == 0.0 and np.isfinite(zero["a"]).all()


def test_warmup_cosine_values_at_known_steps():
    lr = jax.jit(warmup_cosine(peak_lr=1.0, warmup_steps=10, total_steps=110, final_lr=0.1))
    expected = {0: 0.0, 5: 0.5, 10: 1.0, 60: 0.55, 110: 0.1, 500: 0.1}  # 60: half-way down
    for step, value in expected.items():
        assert float(lr(step)) == pytest.approx(value, abs=1e-6), step
    assert float(lr(35)) == pytest.approx(0.1 + 0.9 * (1 + np.cos(np.pi / 4)) / 2, abs=1e-6)


def test_warmup_cosine_without_warmup_starts_at_peak():
    lr = warmup_cosine(peak_lr=2e-3, warmup_steps=0, total_steps=100)
    assert float(lr(0)) == pytest.approx(2e-3)
    assert float(lr(100)) == pytest.approx(0.0, abs=1e-9)
