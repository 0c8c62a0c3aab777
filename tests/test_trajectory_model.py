"""conav_jax.models.trajectory: starts as constant velocity, is frame-equivariant, memorises
a tiny batch; the constant-velocity baseline and ADE/FDE on hand-made cases."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conav_jax.models import trajectory
from conav_jax.models.trajectory import TrajectoryConfig
from conav_jax.optim import adam

# Tiny shapes on a 2-core CPU: LLVM's optimisation passes cost far more compile time than
# they save at run time (3x faster compiles), so the tests' jits skip them.
jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})

CONFIG = TrajectoryConfig(history=8, horizon=5, hidden=32)
APPLY = jit(trajectory.apply, static_argnums=1)


def _arcs(n=6, k=8, horizon=5, seed=0):
    """Walks along circular arcs at ~1.1 m/s (0.1 s steps): `(n, k + horizon, 2)` metres."""
    rng = np.random.default_rng(seed)
    t = np.arange(k + horizon)
    speed, turn = rng.uniform(0.1, 0.13, n), rng.uniform(-0.15, 0.15, n)
    heading = rng.uniform(-np.pi, np.pi, n)[:, None] + turn[:, None] * t
    steps = speed[:, None, None] * np.stack([np.cos(heading), np.sin(heading)], -1)
    return (rng.uniform(-5, 5, (n, 1, 2)) + np.cumsum(steps, 1)).astype(np.float32)


@pytest.fixture(scope="module")
def params():
    return jit(trajectory.init, static_argnums=1)(jax.random.PRNGKey(0), CONFIG)


def test_untrained_model_is_constant_velocity(params):
    history = _arcs()[:, :8]
    expected = trajectory.constant_velocity(history)
    np.testing.assert_allclose(APPLY(params, CONFIG, history), expected, atol=1e-5)


def test_prediction_moves_and_turns_with_the_input_frame(params):
    # Make the correction head non-zero so the check is not trivially constant velocity.
    rng = np.random.default_rng(1)
    params = jax.tree_util.tree_map(lambda x: x + 0.3 * rng.normal(size=x.shape).astype(np.float32), params)
    history = _arcs()[:, :8]
    angle, shift = 0.7, np.array([3.0, -2.0], np.float32)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]], np.float32)
    moved = history @ rot.T + shift
    pred, pred_moved = APPLY(params, CONFIG, history), APPLY(params, CONFIG, moved)
    assert not np.allclose(pred, trajectory.constant_velocity(history), atol=1e-3)
    np.testing.assert_allclose(pred_moved, np.asarray(pred) @ rot.T + shift, atol=1e-4)


def test_standing_human_is_predicted_to_stay(params):
    history = np.tile(np.array([[1.0, 2.0]], np.float32), (1, 8, 1))
    np.testing.assert_allclose(APPLY(params, CONFIG, history), np.tile(history[:, :1], (1, 5, 1)), atol=1e-6)


def test_overfits_a_tiny_batch(params):
    walks = _arcs(n=8, seed=2)
    history, future = walks[:, :8], walks[:, 8:]
    opt = adam(3e-3)
    loss_fn = lambda p: jnp.mean(jnp.sum(jnp.square(trajectory.apply(p, CONFIG, history) - future), -1))

    @jit
    def train(p):
        def step(carry, _):
            p, s = carry
            g = jax.grad(loss_fn)(p)
            return opt.update(g, s, p), None

        (p, _), _ = jax.lax.scan(step, (p, opt.init(p)), None, length=300)
        return loss_fn(params), loss_fn(p)

    initial, final = train(params)
    assert final < 1e-5 and final < initial / 50  # squared metres


def test_constant_velocity_repeats_the_last_step():
    history = np.array([[[0.0, 0.0], [1.0, 0.0], [1.5, 0.5]]], np.float32)
    expected = [[[2.0, 1.0], [2.5, 1.5], [3.0, 2.0]]]
    np.testing.assert_allclose(trajectory.constant_velocity(history, horizon=3), expected)


def test_ade_fde_on_a_known_offset():
    target = np.zeros((2, 5, 2), np.float32)
    pred = target.copy()
    pred[0, :, 0] = [0, 0, 0, 0, 1.0]  # only the last point is off by 1 m
    pred[1] = 3.0 / np.sqrt(2)  # every point off by 3 m
    ade, fde = trajectory.ade_fde(pred, target)
    np.testing.assert_allclose(ade, [0.2, 3.0], rtol=1e-6)
    np.testing.assert_allclose(fde, [1.0, 3.0], rtol=1e-6)
