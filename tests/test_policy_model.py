"""conav_jax.models.policy: a sequence rollout equals stepping, resets start from a zero carry,
the Table 3 ablations neither read nor hold weights for the inputs they switch off, and the
object saliency channel finds each category by its rendered colour and nothing else."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conav_jax.data.categories import CATEGORIES
from conav_jax.models import policy
from conav_jax.models.policy import PolicyConfig, ablation_config, encoder_config

# Tiny shapes on a 2-core CPU: LLVM's optimisation passes cost far more compile time than
# they save at run time (3x faster compiles), so the tests' jits skip them.
jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})

CONFIG = PolicyConfig(
    resolution=(16, 64), conv_channels=(8, 8), conv_kernels=(3, 3),
    visual_dim=32, state_dim=8, intention_dim=8, hidden=32,
)
STEP = jit(policy.apply, static_argnums=1)
SEQUENCE = jit(policy.apply_sequence, static_argnums=1)
INTENTION_KEYS = {"activity_probs", "object_probs", "future_traj"}
B, T = 2, 4


def _obs(lead, seed=0):
    rng = np.random.default_rng(seed)
    f = lambda *shape: rng.uniform(size=(*lead, *shape)).astype(np.float32)
    rgbd = f(16, 64, 4) * np.array([1, 1, 1, 8], np.float32)
    # Objects of a few categories in the segmentation, so the saliency channel sees some.
    segmentation = np.full((*lead, 16, 64), -1, np.int32)
    for k, col in enumerate((3, 20, 41)):
        segmentation[..., 4:12, col : col + 3] = 7 * k + 1
    return {
        "rgbd": rgbd,
        "segmentation": segmentation,
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


@pytest.mark.parametrize("remat", [False, True])
def test_time_major_sequence_equals_batch_major(params, remat):
    obs_seq, carry = _obs((B, T)), _random_carry()
    resets = np.zeros((B, T), bool)
    resets[1, 3] = True
    actions, values, final = policy.apply_sequence(params, CONFIG, obs_seq, carry, resets, remat=remat)
    swap = lambda x: jnp.swapaxes(x, 0, 1)
    t_actions, t_values, t_final = policy.apply_sequence(params, CONFIG, jax.tree.map(swap, obs_seq), carry,
                                                         swap(resets), remat=remat, time_major=True)
    np.testing.assert_allclose(swap(t_actions), actions, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(swap(t_values), values, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(t_final.h, final.h, rtol=1e-5, atol=1e-6)


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
    saliency = "object_probs" in used
    assert ("saliency" in shapes) == saliency and shapes["convs"][0]["w"].shape[-2] == 4 + saliency
    # visual + state + intentions (+ the object's saliency bearing)
    assert shapes["lstm"]["wi"].shape[0] == 32 + 8 + 8 * (len(used) + saliency)
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
    obs["segmentation"] = jax.ShapeDtypeStruct((3, 112, 448), jnp.int32)
    action, value, _ = jax.eval_shape(
        lambda p, o, c: policy.apply(p, config, o, c), shapes, obs, policy.initial_carry(config, 3)
    )
    assert action.shape == (3, 2) and value.shape == (3,)


def _trained_policy_model(flag, monkeypatch, tmp_path):
    """(PolicyConfig, ImitationConfig) that `conav train policy ... --ablation object FLAG`
    hands to train.policy.train_policy_from_data (replaced by a recorder)."""
    from conav_jax.eval.cli import build_parser
    from conav_jax.train import policy as train_policy_mod

    seen = {}

    def fake_train_policy(data, out, cfg, model, imitation, **kw):
        seen.update(model=model, imitation=imitation)
        return train_policy_mod.PolicyResult({}, {"FASR": 0, "RASR": 0, "CR": 0, "AS": 0}, {"FASR": 0, "RASR": 0, "CR": 0, "AS": 0}, tmp_path)

    monkeypatch.setattr(train_policy_mod, "train_policy_from_data", fake_train_policy)
    args = build_parser().parse_args(["train", "policy", "--data", str(tmp_path), "--out", str(tmp_path / "run"),
                                      "--resolution", "16x64", "--ablation", "object", *flag])
    assert args.func(args) == 0
    return seen["model"], seen["imitation"]


# -- panorama encoders -------------------------------------------------------------------------


def _conv_eqns(jaxpr) -> list:
    """Every convolution of a traced program in program order, nested programs included (a
    layer's convolution sits inside its vmap rule and gradient)."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "conv_general_dilated":
            found.append(eqn)
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    found += _conv_eqns(inner)
    return found


def _convolutions(config, params, obs):
    return _conv_eqns(jax.make_jaxpr(policy.encode, static_argnums=1)(params, config, obs).jaxpr)


def test_the_patch_encoder_reaches_the_conv_encoders_grid_with_a_patch_product_first():
    conv, patch = (encoder_config(PolicyConfig(), name) for name in ("conv", "patch"))
    shapes = {c: jax.eval_shape(lambda k, c=c: policy.init(k, c), jax.random.PRNGKey(0)) for c in (conv, patch)}
    # 112x448 -> a 7x28 grid of 64 channels either way: the same projection to visual_dim.
    assert shapes[patch]["visual"]["w"].shape == shapes[conv]["visual"]["w"].shape == (7 * 28 * 64, 256)
    assert [c["w"].shape for c in shapes[patch]["convs"]] == [(4, 4, 5, 32), (3, 3, 32, 32), (3, 3, 32, 64)]
    assert policy.encoder_name(conv) == "conv" and policy.encoder_name(patch) == "patch"
    assert policy.encoder_name(CONFIG) == "custom" and conv == PolicyConfig()
    # On a small panorama: the first layer runs as one product per 4x4 block, the rest convolve.
    small = {c: dataclasses.replace(c, resolution=(16, 64)) for c in (conv, patch)}
    for c, expected in ((small[conv], 4), (small[patch], 2)):
        params = jit(policy.init, static_argnums=1)(jax.random.PRNGKey(0), c)
        assert len(_convolutions(c, params, _obs((B,)))) == expected
        assert np.isfinite(jit(policy.encode, static_argnums=1)(params, c, _obs((B,)))).all()
    with pytest.raises(ValueError, match="unknown encoder 'resnet'"):
        encoder_config(PolicyConfig(), "resnet")
    with pytest.raises(ValueError, match="one entry per conv layer"):
        PolicyConfig(conv_strides=(4, 2))


@pytest.mark.parametrize("encoder, dtype", [("patch", "bfloat16"), ("patch", "float32"), ("conv", "bfloat16")])
def test_a_prepared_panorama_gives_the_step_and_gradient_of_the_raw_observation(encoder, dtype):
    """What train.live stores of a step (policy.prepare_panorama) is read by `encode` in place
    of the panorama and segmentation: the same actions and the same gradient."""
    config = dataclasses.replace(encoder_config(CONFIG, encoder), resolution=(16, 64), conv_dtype=dtype)
    params = jit(policy.init, static_argnums=1)(jax.random.PRNGKey(0), config)
    obs = _obs((B, T))
    prepared = jit(policy.prepare_panorama, static_argnums=0)(config, obs)
    assert set(prepared) == {policy.PANORAMA_IMAGE, policy.PANORAMA_BEARING}
    image = prepared[policy.PANORAMA_IMAGE]
    assert str(image.dtype) == dtype
    # The patch encoder's image is laid out as its first layer's 4x4 patches of 5 channels.
    assert image.shape == ((B, T, 4, 16, 80) if encoder == "patch" else (B, T, 16, 64, 5))
    stored = {**{k: v for k, v in obs.items() if k not in ("rgbd", "segmentation")}, **prepared}
    resets = np.zeros((B, T), bool)

    def loss(p, o):
        actions, values, _ = policy.apply_sequence(p, config, o, policy.initial_carry(config, B), resets)
        return jnp.sum(actions ** 2) + jnp.sum(values), actions

    grad = jit(jax.grad(loss, has_aux=True))
    (g_raw, a_raw), (g_prep, a_prep) = grad(params, obs), grad(params, stored)
    np.testing.assert_allclose(a_prep, a_raw, rtol=1e-6, atol=1e-6)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6), g_prep, g_raw)


def test_runs_store_the_strides_only_for_the_patch_encoder_and_read_them_back():
    import json

    from conav_jax.envs.agents.policy import policy_config_from_dict

    assert "conv_strides" not in policy.config_dict(PolicyConfig())  # runs before the field resume
    patch = encoder_config(PolicyConfig(), "patch")
    stored = json.loads(json.dumps(policy.config_dict(patch)))
    assert stored["conv_strides"] == [4, 2, 2] and policy_config_from_dict(stored) == patch


@pytest.mark.parametrize("flag, encoder", [([], "conv"), (["--encoder", "patch"], "patch")])
def test_train_policy_flag_sets_the_encoder_of_the_runs_model(flag, encoder, monkeypatch, tmp_path):
    model, _ = _trained_policy_model(flag, monkeypatch, tmp_path)
    assert policy.encoder_name(model) == encoder and model.use_object and not model.use_activity


# -- the object saliency channel ---------------------------------------------------------------


def test_categories_in_view_are_those_with_a_pixel_in_the_segmentation():
    seg = np.full((4, 6), -1, np.int32)  # no object anywhere
    seg[0, 0], seg[3, 5] = 3, 40
    seen = np.asarray(policy.categories_in_view(jnp.asarray(seg)))
    assert seen.shape == (len(CATEGORIES),) and seen.dtype == bool
    assert np.flatnonzero(seen).tolist() == [3, 40]
    assert not np.asarray(policy.categories_in_view(jnp.full((4, 6), -1))).any()
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        policy.categories_in_view(jnp.zeros((2, 4, 6), jnp.int32))


def test_object_saliency_weights_pixels_by_their_category_probability():
    seg = np.full((2, 3), -1, np.int32)
    seg[0, 0], seg[0, 1] = 4, 9
    seg[1, 0] = seg[1, 1] = 30
    probs = np.zeros(51, np.float32)
    probs[4], probs[9], probs[30] = 0.4, 0.1, 0.0
    probs[0] = 0.5  # the most likely category is not in view: saliencies are relative to it
    sal = np.asarray(policy.object_saliency(seg, probs))
    np.testing.assert_allclose(sal, [[0.8, 0.2, 0.0], [0.0, 0.0, 0.0]], atol=1e-6)


def test_saliency_bearing_finds_the_sector_and_depth_of_the_salient_pixels():
    config = PolicyConfig(resolution=(4, 32), saliency_sectors=8)
    sal = np.zeros((4, 32), np.float32)
    depth = np.full((4, 32), 9.0, np.float32)
    sal[1:3, 13] = 1.0  # sector 3 (columns 12-15)
    depth[1, 13], depth[2, 13] = 2.5, 3.0
    sal[0, 29], depth[0, 29] = 0.4, 1.0  # sector 7: weaker, nearer
    feat = np.asarray(policy.saliency_bearing(config, sal, depth))
    peak, near = feat[:8], feat[8:]
    np.testing.assert_allclose(peak, [0, 0, 0, 1.0, 0, 0, 0, 0.4], atol=1e-6)
    np.testing.assert_allclose(near, [1, 1, 1, 0.25, 1, 1, 1, 0.1], atol=1e-6)


def test_the_policy_reads_where_the_predicted_object_is(params):
    """One panorama with categories 1 and 8 in different columns; only `object_probs`
    changes, from category 1 to category 8. With the object vector's own weights zeroed, the
    saliency channel alone can tell the two apart, and the action changes; with the saliency
    channel's weights zeroed too, it cannot (so the difference is the channel's)."""
    obs = _obs((1,))
    one_hot = np.eye(51, dtype=np.float32)
    carry = policy.initial_carry(CONFIG, 1)

    def zero(tree):
        return jax.tree.map(jnp.zeros_like, tree)

    blind = {**params, "intentions": {**params["intentions"], "object_probs": zero(params["intentions"]["object_probs"])}}
    a, _, _ = STEP(blind, CONFIG, {**obs, "object_probs": one_hot[None, 1]}, carry)
    b, _, _ = STEP(blind, CONFIG, {**obs, "object_probs": one_hot[None, 8]}, carry)
    assert not np.allclose(a, b, atol=1e-6)
    first = dict(params["convs"][0], w=params["convs"][0]["w"].at[:, :, 4, :].set(0.0))  # the saliency channel's kernel
    no_channel = {**blind, "convs": [first, *params["convs"][1:]], "saliency": zero(params["saliency"])}
    a, _, _ = STEP(no_channel, CONFIG, {**obs, "object_probs": one_hot[None, 1]}, carry)
    b, _, _ = STEP(no_channel, CONFIG, {**obs, "object_probs": one_hot[None, 8]}, carry)
    np.testing.assert_allclose(a, b, atol=1e-7)


def test_saliency_sectors_must_divide_the_width():
    with pytest.raises(ValueError, match="saliency_sectors"):
        policy.init(jax.random.PRNGKey(0), PolicyConfig(resolution=(16, 64), conv_channels=(4,), conv_kernels=(3,), saliency_sectors=12))


def test_checkpoint_configs_from_before_the_saliency_channel_load_without_it():
    from conav_jax.envs.agents.policy import policy_config_from_dict

    old = {k: v for k, v in dataclasses.asdict(CONFIG).items() if k != "object_saliency"}
    assert policy_config_from_dict(old).object_saliency is False
    assert policy_config_from_dict(dataclasses.asdict(CONFIG)).object_saliency is True


@pytest.mark.parametrize("flag, saliency", [([], True), (["--no-object-saliency"], False)])
def test_train_policy_flag_switches_the_saliency_channel_in_the_runs_model(flag, saliency, monkeypatch, tmp_path):
    from conav_jax.nav.expert import ExpertConfig
    from conav_jax.train.policy import run_config

    model, imitation = _trained_policy_model(flag, monkeypatch, tmp_path)
    assert model.resolution == (16, 64) and model.object_saliency is saliency
    assert (model.use_activity, model.use_object, model.use_trajectory) == (False, True, False)
    config = run_config(model, imitation, ExpertConfig(), "hash", None, None)
    assert config["model"]["object_saliency"] is saliency and "object_saliency" not in config["imitation"]
    shapes = jax.eval_shape(lambda k: policy.init(k, model), jax.random.PRNGKey(0))
    assert ("saliency" in shapes) is saliency


GOAL = dataclasses.replace(CONFIG, goal_image=True, goal_conv_channels=(4, 4), goal_conv_kernels=(3, 3), goal_dim=8,
                           use_human_pos=False)


def test_the_goal_image_is_read_and_the_human_position_can_be_switched_off(params):
    # Off by default: no goal encoder, and the state layer reads the human's position.
    assert not {"goal", "goal_convs"} & set(params) and params["state"]["w"].shape[0] == 6
    goal_params = jit(policy.init, static_argnums=1)(jax.random.PRNGKey(0), GOAL)
    assert goal_params["state"]["w"].shape[0] == 4
    # The goal encoder draws its own keys: the rest of the network is initialised as without it.
    for name in ("convs", "visual", "intentions", "action_head"):
        for a, b in zip(jax.tree.leaves(goal_params[name]), jax.tree.leaves(params[name])):
            np.testing.assert_array_equal(a, b)
    obs, carry = _obs((B,)), policy.initial_carry(GOAL, B)
    goal = np.random.default_rng(3).uniform(size=(B, *GOAL.goal_image_hw, 3)).astype(np.float32)
    assert GOAL.goal_image_hw == (16, 16)
    a, _, _ = STEP(goal_params, GOAL, {**obs, "goal_image": goal}, carry)
    b, _, _ = STEP(goal_params, GOAL, {**obs, "goal_image": 1.0 - goal}, carry)
    c, _, _ = STEP(goal_params, GOAL, {**obs, "goal_image": goal, "human_pos": obs["human_pos"] + 5.0}, carry)
    assert not np.allclose(a, b, atol=1e-6)
    np.testing.assert_array_equal(a, c)


def test_runs_store_the_config_as_before_the_goal_inputs_and_read_both_back():
    import json

    from conav_jax.envs.agents.policy import policy_config_from_dict

    old = {k: v for k, v in dataclasses.asdict(CONFIG).items() if k not in policy.LATER_FIELDS}
    assert policy.config_dict(CONFIG) == old  # what a run stores: so runs written before resume
    assert policy_config_from_dict(json.loads(json.dumps(old))) == CONFIG
    stored = json.loads(json.dumps(policy.config_dict(GOAL)))
    assert stored["goal_image"] is True and stored["use_human_pos"] is False and stored["goal_dim"] == 8
    assert policy_config_from_dict(stored) == GOAL


# -- bfloat16 convolutions --------------------------------------------------------------------


def test_conv_dtype_must_be_float32_or_bfloat16():
    with pytest.raises(ValueError, match="conv_dtype 'float16'"):
        PolicyConfig(conv_dtype="float16")


def test_bfloat16_reaches_every_convolution_the_policy_runs():
    params = jit(policy.init, static_argnums=1)(jax.random.PRNGKey(0), GOAL)
    obs = {**_obs((B,)), "goal_image": np.random.default_rng(3).uniform(size=(B, *GOAL.goal_image_hw, 3)).astype(np.float32)}
    encode = jit(policy.encode, static_argnums=1)
    exact = encode(params, GOAL, obs)
    mixed = encode(params, dataclasses.replace(GOAL, conv_dtype="bfloat16"), obs)
    assert mixed.dtype == jnp.float32
    # Features: the panorama CNN's first (visual_dim), the goal CNN's last (goal_dim); between
    # them the state, intention and saliency-bearing embeddings, which no convolution computes.
    # Measured on the CPU over four seeds: at most 0.58% of the largest feature.
    cnn = {"panorama CNN": slice(0, GOAL.visual_dim), "goal CNN": slice(-GOAL.goal_dim, None)}
    for name, part in cnn.items():
        assert not np.array_equal(mixed[:, part], exact[:, part]), f"the {name} did not run in bfloat16"
        np.testing.assert_allclose(mixed[:, part], exact[:, part], rtol=0, atol=0.02 * np.abs(exact[:, part]).max())
    middle = slice(GOAL.visual_dim, -GOAL.goal_dim)
    np.testing.assert_array_equal(mixed[:, middle], exact[:, middle])


def test_in_bfloat16_the_first_convolution_runs_over_pixel_blocks():
    """Its 5 input channels (RGB, depth, saliency), padded to 8, times the 2x2 block: a stride-1
    convolution over 32 channels; the float32 path keeps the plain stride-2 one."""
    params = jit(policy.init, static_argnums=1)(jax.random.PRNGKey(0), CONFIG)

    def first_conv(config):
        jaxpr = jax.make_jaxpr(policy.encode, static_argnums=1)(params, config, _obs((B,)))
        eqn = _conv_eqns(jaxpr.jaxpr)[0]
        return eqn.params["window_strides"], eqn.invars[1].aval.shape[2], str(eqn.invars[0].aval.dtype)

    assert first_conv(dataclasses.replace(CONFIG, conv_dtype="bfloat16")) == ((1, 1), 32, "bfloat16")
    assert first_conv(CONFIG) == ((2, 2), 5, "float32")


@pytest.mark.parametrize("flag, dtype", [([], "float32"), (["--conv-dtype", "bfloat16"], "bfloat16")])
def test_train_policy_flag_sets_the_conv_dtype_of_the_runs_model(flag, dtype, monkeypatch, tmp_path):
    model, _ = _trained_policy_model(flag, monkeypatch, tmp_path)
    assert model.conv_dtype == dtype and model.use_object and not model.use_activity


def test_runs_store_conv_dtype_only_where_it_is_bfloat16_and_resume_only_with_the_same(tmp_path):
    import json

    from conav_jax.checkpoints import load_checkpoint, save_checkpoint
    from conav_jax.envs.agents.policy import policy_config_from_dict

    # A float32 run's model is stored as before the field existed, so runs written before it
    # resume, and a stored model without it loads as float32.
    old = json.loads(json.dumps(policy.config_dict(CONFIG)))
    assert "conv_dtype" not in old
    assert policy_config_from_dict(old) == CONFIG and CONFIG.conv_dtype == "float32"
    bf16 = dataclasses.replace(CONFIG, conv_dtype="bfloat16")
    stored = json.loads(json.dumps(policy.config_dict(bf16)))
    assert stored["conv_dtype"] == "bfloat16" and policy_config_from_dict(stored) == bf16
    # A run resumed with another conv_dtype fails, naming the field.
    path = save_checkpoint(tmp_path / "ckpt_1.npz", params={"w": np.zeros(2)}, opt_state=None,
                           config={"model": old}, step=1)
    load_checkpoint(path, config={"model": policy.config_dict(CONFIG)})
    with pytest.raises(ValueError, match="model.conv_dtype"):
        load_checkpoint(path, config={"model": policy.config_dict(bf16)})


# -- the visual embedding's normalisation ------------------------------------------------------


def test_visual_norm_keeps_the_embedding_bounded_when_its_weights_grow(params):
    """The live trainer's failure: Adam grew the flatten layer's weights until the LSTM saturated
    and the action stopped depending on the panorama. Normalised, the embedding's scale is the
    norm's, whatever the weights' (the same grown weights without it: 1000 times larger)."""
    normed = dataclasses.replace(CONFIG, visual_norm=True)
    p = jit(policy.init, static_argnums=1)(jax.random.PRNGKey(0), normed)
    assert set(p) - set(params) == {"visual_norm"} and p["visual_norm"]["scale"].shape == (CONFIG.visual_dim,)
    obs = _obs((B,))
    grown = {**p, "visual": jax.tree.map(lambda w: 1000.0 * w, p["visual"])}
    for cfg, weights, bound in ((normed, p, 16.0), (normed, grown, 16.0), (CONFIG, grown, None)):
        visual = np.asarray(policy.encode(weights, cfg, obs))[:, :CONFIG.visual_dim]
        if bound is None:
            assert np.abs(visual).max() > 100.0
        else:  # ReLU of a unit-variance vector of visual_dim entries
            assert 0.0 < np.abs(visual).max() < bound and np.isfinite(visual).all()
    # Every other parameter is drawn as without the norm: a run without it is unchanged.
    jax.tree.map(np.testing.assert_array_equal, {k: v for k, v in p.items() if k != "visual_norm"}, params)


def test_runs_store_visual_norm_only_where_it_is_on_and_live_runs_default_to_it():
    import json

    from conav_jax.envs.agents.policy import policy_config_from_dict
    from conav_jax.eval.cli import build_parser, network_base

    old = json.loads(json.dumps(policy.config_dict(CONFIG)))
    assert "visual_norm" not in old and not policy_config_from_dict(old).visual_norm  # runs before the field
    normed = dataclasses.replace(CONFIG, visual_norm=True)
    assert policy_config_from_dict(json.loads(json.dumps(policy.config_dict(normed)))) == normed
    common = ["--data", "D", "--out", "O"]
    live = build_parser().parse_args(["train", "live", *common, "--ground-truth-intentions"])
    offline = build_parser().parse_args(["train", "policy", *common])
    off = build_parser().parse_args(["train", "live", *common, "--ground-truth-intentions", "--no-visual-norm"])
    assert [network_base(a, (16, 64)).visual_norm for a in (live, offline, off)] == [True, False, False]
