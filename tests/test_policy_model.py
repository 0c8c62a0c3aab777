"""conav_jax.models.policy: a sequence rollout equals stepping, resets start from a zero carry,
and the Table 3 ablations neither read nor hold weights for the inputs they switch off."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conav_jax.models import policy
from conav_jax.models.policy import PolicyConfig, ablation_config

# Tiny shapes on a 2-core CPU: LLVM's optimisation passes cost far more compile time than
# they save at run time (3x faster compiles), so the tests' jits skip them.
jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})

CONFIG = PolicyConfig(
    image_hw=(16, 64), conv_channels=(8, 8), conv_kernels=(3, 3),
    visual_dim=32, state_dim=8, intention_dim=8, hidden=32,
)
STEP = jit(policy.apply, static_argnums=1)
SEQUENCE = jit(policy.apply_sequence, static_argnums=1)
INTENTION_KEYS = {"activity_probs", "object_probs", "future_traj"}
B, T = 2, 4


def _obs(lead, seed=0):
    rng = np.random.default_rng(seed)
    f = lambda *shape: rng.uniform(size=(*lead, *shape)).astype(np.float32)
    return {
        "rgbd": f(16, 64, 4) * np.array([1, 1, 1, 8], np.float32),
        "gps_compass": (f(3) - 0.5) * np.array([10, 10, 6.28], np.float32),
        "human_pos": f(2) * 3,
        "activity_probs": f(107) / 53.5,
        "object_probs": f(51) / 25.5,
        "future_traj": f(5, 2) * 2,
    }


@pytest.fixture(scope="module")
def params():
    return jit(policy.init, static_argnums=1)(jax.random.PRNGKey(0), CONFIG)


def _random_carry(seed=1):
    rng = np.random.default_rng(seed)
    return policy.initial_carry(CONFIG, B)._replace(
        h=rng.normal(size=(B, 32)).astype(np.float32), c=rng.normal(size=(B, 32)).astype(np.float32)
    )


def test_step_outputs_bounded_actions_and_a_value_per_sample(params):
    action, value, carry = STEP(params, CONFIG, _obs((B,)), policy.initial_carry(CONFIG, B))
    assert action.shape == (B, 2) and value.shape == (B,) and carry.h.shape == (B, 32)
    assert np.all(np.abs(action) <= 1.0)
    assert params["log_std"].shape == (2,)
    np.testing.assert_allclose(params["log_std"], CONFIG.init_log_std)


def test_apply_sequence_equals_stepping_apply_in_a_loop(params):
    obs_seq = _obs((B, T))
    resets = np.zeros((B, T), bool)
    resets[0, 2] = True  # sample 0 starts a new episode at step 2
    carry = _random_carry()
    actions, values, final = SEQUENCE(params, CONFIG, obs_seq, carry, resets)
    step_carry = carry
    for t in range(T):
        obs_t = {k: v[:, t] for k, v in obs_seq.items()}
        action, value, step_carry = STEP(params, CONFIG, obs_t, step_carry, resets[:, t])
        np.testing.assert_allclose(actions[:, t], action, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(values[:, t], value, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(final.h, step_carry.h, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(final.c, step_carry.c, rtol=1e-5, atol=1e-6)


def test_rematerialised_sequence_gives_the_same_outputs_and_gradients(params):
    obs_seq, carry = _obs((B, T)), _random_carry()

    def loss(p, remat):
        actions, values, final = policy.apply_sequence(p, CONFIG, obs_seq, carry, remat=remat)
        return jnp.sum(actions**2) + jnp.sum(values) + jnp.sum(final.h)

    grad = jit(jax.value_and_grad(loss), static_argnums=1)
    (plain, g_plain), (remat, g_remat) = grad(params, False), grad(params, True)
    np.testing.assert_allclose(remat, plain, rtol=1e-5)
    for a, b in zip(jax.tree.leaves(g_remat), jax.tree.leaves(g_plain)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)


def test_reset_starts_the_step_from_a_zero_carry(params):
    obs = _obs((B,))
    fresh = STEP(params, CONFIG, obs, policy.initial_carry(CONFIG, B), np.zeros(B, bool))
    reset = STEP(params, CONFIG, obs, _random_carry(), np.ones(B, bool))
    kept = STEP(params, CONFIG, obs, _random_carry(), np.zeros(B, bool))
    np.testing.assert_array_equal(fresh[0], reset[0])
    assert not np.allclose(fresh[0], kept[0], atol=1e-7)


@pytest.mark.parametrize(
    "name,used",
    [
        ("none", set()),
        ("activity", {"activity_probs"}),
        ("object", {"object_probs"}),
        ("activity_object", {"activity_probs", "object_probs"}),
        ("all", INTENTION_KEYS),
    ],
)
def test_ablation_has_no_params_for_disabled_inputs_and_never_reads_them(name, used):
    config = ablation_config(CONFIG, name)
    shapes = jax.eval_shape(lambda k: policy.init(k, config), jax.random.PRNGKey(0))
    assert set(shapes["intentions"]) == used
    assert shapes["lstm"]["wi"].shape[0] == 32 + 8 + 8 * len(used)  # visual + state + intentions
    obs = {k: v for k, v in _obs((B,)).items() if k not in INTENTION_KEYS - used}
    action, _, _ = jax.eval_shape(
        lambda p, o, c: policy.apply(p, config, o, c), shapes, obs, policy.initial_carry(config, B)
    )  # a KeyError here would mean a disabled input is read
    assert action.shape == (B, 2)


def test_unknown_ablation_name_is_rejected():
    with pytest.raises(ValueError, match="trajectory_only"):
        ablation_config(CONFIG, "trajectory_only")


def test_default_config_builds_for_the_112x448_panorama():
    config = PolicyConfig()
    shapes = jax.eval_shape(lambda k: policy.init(k, config), jax.random.PRNGKey(0))
    obs = {k: jax.ShapeDtypeStruct((3, *v.shape[1:]), jnp.float32) for k, v in _obs((1,)).items()}
    obs["rgbd"] = jax.ShapeDtypeStruct((3, 112, 448, 4), jnp.float32)
    action, value, _ = jax.eval_shape(
        lambda p, o, c: policy.apply(p, config, o, c), shapes, obs, policy.initial_carry(config, 3)
    )
    assert action.shape == (3, 2) and value.shape == (3,)
