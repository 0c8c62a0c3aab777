"""Layers of conav_jax.nn: gradients against central finite differences (float64), attention
masking, the LSTM scan against a Python loop, and shapes of the rest."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conav_jax import nn

# Tiny shapes on a 2-core CPU: LLVM's optimisation passes cost far more compile time than
# they save at run time (3x faster compiles), so the tests' jits skip them.
jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})

# Inputs come from numpy (each new shape drawn with jax.random costs a compile) and params are
# drawn once, under one jit, and shared.
RNG = np.random.default_rng(0)
KEY = jax.random.PRNGKey(0)


def _normal(*shape):
    return RNG.normal(size=shape).astype(np.float32)


def _to64(tree):
    return jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), tree)


def _assert_grad_matches_finite_differences(loss, args, seed=0, eps=1e-6, directions=3):
    """Directional derivatives of `loss(*args)` along random directions: autodiff vs central
    differences `(f(x + eps v) - f(x - eps v)) / 2 eps`, all args differentiated at once."""
    # Jitted: one compile per loss instead of one per eager op.
    grads = jit(jax.grad(loss, argnums=tuple(range(len(args)))))(*args)
    loss = jit(loss)
    assert loss(*args).dtype == jnp.float64  # float32 rounding would swamp the differences
    rng = np.random.default_rng(seed)
    for _ in range(directions):
        v = jax.tree_util.tree_map(lambda x: rng.normal(size=np.shape(x)), args)
        shift = lambda s: jax.tree_util.tree_map(lambda x, d: x + s * d, args, v)
        numeric = (loss(*shift(eps)) - loss(*shift(-eps))) / (2 * eps)
        analytic = sum(
            jnp.vdot(g, d) for g, d in zip(jax.tree_util.tree_leaves(grads), jax.tree_util.tree_leaves(v))
        )
        np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-8)


def _weighted_sum(y, seed=1):
    # A fixed random weighting, so every output element matters to the scalar loss.
    w = np.random.default_rng(seed).normal(size=y.shape)
    return jnp.sum(jnp.sin(y) * w)


@pytest.fixture(scope="module")
def layers():
    """One set of float32 layer params shared by every test."""
    init = lambda key: {
        "linear": nn.linear.init(key, 3, 4, scheme="glorot"),
        "conv": nn.conv.init(key, 2, 3, 3),
        "attention": nn.attention.init(key, 8, 6, num_heads=2, head_dim=4),
        "lstm": nn.lstm.init(key, 3, 5),
        "mlp": nn.mlp.init(key, (3, 16, 2)),
        "embedding": nn.embedding.init(key, 10, 6),
    }
    return jit(init)(KEY)


def test_linear_gradient_matches_finite_differences(layers):
    with jax.enable_x64(True):
        loss = lambda p, x: _weighted_sum(nn.linear.apply(p, x))
        _assert_grad_matches_finite_differences(loss, _to64((layers["linear"], _normal(2, 5, 3))))


@pytest.mark.parametrize("stride,padding", [(1, "SAME"), (2, "VALID")])
def test_conv2d_gradient_matches_finite_differences(layers, stride, padding):
    with jax.enable_x64(True):
        loss = lambda p, x: _weighted_sum(nn.conv.apply(p, x, stride=stride, padding=padding))
        _assert_grad_matches_finite_differences(loss, _to64((layers["conv"], _normal(2, 5, 6, 2))))


def test_layer_norm_gradient_matches_finite_differences():
    with jax.enable_x64(True):
        params = {"scale": _normal(4), "bias": _normal(4)}
        loss = lambda p, x: _weighted_sum(nn.norm.apply(p, x))
        _assert_grad_matches_finite_differences(loss, _to64((params, _normal(3, 4))))


def test_attention_gradient_matches_finite_differences_with_a_mask(layers):
    mask = np.array([[True, True, False, True, False], [False] * 5])  # 2nd row fully masked
    with jax.enable_x64(True):
        loss = lambda p, q, kv: _weighted_sum(nn.attention.apply(p, q, kv, mask))
        args = _to64((layers["attention"], _normal(2, 3, 8), _normal(2, 5, 6)))
        _assert_grad_matches_finite_differences(loss, args)


def test_lstm_scan_gradient_matches_finite_differences(layers):
    resets = np.zeros((4, 2), bool)
    resets[2, 0] = True

    def loss(p, carry, xs):
        final, hs = nn.lstm.lstm_scan(p, carry, xs, resets)
        return _weighted_sum(hs) + jnp.sum(final.c)

    with jax.enable_x64(True):
        carry = nn.lstm.LSTMState(_normal(2, 5), _normal(2, 5))
        _assert_grad_matches_finite_differences(loss, _to64((layers["lstm"], carry, _normal(4, 2, 3))))


def test_conv2d_matches_explicit_sum(layers):
    params = layers["conv"]
    x = _normal(1, 4, 5, 2)
    y = nn.conv.apply(params, x, stride=1, padding="VALID")
    w, xn = np.asarray(params["w"]), x[0]
    expected = np.zeros((2, 3, 3))
    for i in range(2):
        for j in range(3):
            expected[i, j] = np.einsum("hwc,hwco->o", xn[i : i + 3, j : j + 3], w)
    np.testing.assert_allclose(y[0], expected + np.asarray(params["b"]), rtol=1e-5, atol=1e-5)


def _bf16(a):
    return jnp.asarray(a).astype(jnp.bfloat16).astype(jnp.float32)


def test_conv2d_in_bfloat16_rounds_its_operands_and_returns_bfloat16(layers):
    params, x = layers["conv"], _normal(2, 5, 6, 2)
    exact = nn.conv.apply(params, x, stride=2)
    y = nn.conv.apply(params, x, stride=2, compute_dtype=jnp.bfloat16)
    assert y.dtype == jnp.bfloat16
    assert not np.array_equal(y.astype(jnp.float32), exact)  # the operands were rounded
    # Measured on the CPU over five seeds: at most 1.0e-2 from the float32 conv (outputs up to ~3.2).
    np.testing.assert_allclose(y.astype(jnp.float32), exact, rtol=0, atol=3e-2)
    # The float32 conv of the rounded operands: products of bf16 operands are exact in float32
    # and the sum is accumulated in float32, so only two roundings to bf16 (the conv's output,
    # then its sum with the bias; 2^-9 relative each) separate them: 3.7e-3 at most, measured
    # over five seeds.
    rounded = nn.conv.apply({"w": _bf16(params["w"]), "b": _bf16(params["b"])}, _bf16(x), stride=2)
    np.testing.assert_allclose(y.astype(jnp.float32), rounded, rtol=2.0**-8, atol=1e-3)


@pytest.mark.parametrize("kernel, hw", [(5, (8, 12)), (3, (6, 10)), (1, (4, 6)), (4, (8, 8))])
def test_space_to_depth_gives_the_stride2_same_conv(kernel, hw):
    """Over 2x2 blocks with the kernel rearranged, any kernel size, five input channels (padded
    to eight inside)."""
    k1, k2, k3 = jax.random.split(KEY, 3)
    params = {**nn.conv.init(k1, 5, 7, kernel), "b": jax.random.normal(k2, (7,))}
    x = jax.random.normal(k3, (2, 3, *hw, 5))
    exact = nn.conv.apply(params, x, stride=2)
    blocks = nn.conv.apply(params, x, stride=2, space_to_depth=True)
    assert blocks.shape == exact.shape
    np.testing.assert_allclose(blocks, exact, rtol=1e-5, atol=1e-5)
    for bad in ({"stride": 1}, {"stride": 2, "padding": "VALID"}):
        with pytest.raises(ValueError, match="space_to_depth needs a stride-2 SAME"):
            nn.conv.apply(params, x, space_to_depth=True, **bad)
    with pytest.raises(ValueError, match="even height and width"):
        nn.conv.apply(params, x[..., 1:, :, :], stride=2, space_to_depth=True)


def _conv_operand_dtypes(closed_jaxpr) -> list[tuple[str, ...]]:
    """Operand dtypes of every convolution in a traced program, nested programs included."""
    found = []

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "conv_general_dilated":
                found.append(tuple(str(v.aval.dtype) for v in eqn.invars))
            for value in eqn.params.values():
                for sub in value if isinstance(value, (tuple, list)) else (value,):
                    inner = getattr(sub, "jaxpr", sub)
                    if hasattr(inner, "eqns"):
                        walk(inner)

    walk(closed_jaxpr.jaxpr)
    return found


@pytest.mark.parametrize("kernel, hw", [(4, (8, 12)), (2, (6, 10)), ((2, 4), (4, 8))])
def test_a_kernel_equal_to_its_stride_runs_as_one_product_per_patch(kernel, hw):
    """The convolution's outputs, with no convolution primitive in the program; an image the
    patches do not tile convolves as before."""
    k1, k2, k3 = jax.random.split(KEY, 3)
    params = {**nn.conv.init(k1, 5, 7, kernel), "b": jax.random.normal(k2, (7,))}
    stride = kernel
    for padding in ("SAME", "VALID"):
        for x in (jax.random.normal(k3, (2, 3, *hw, 5)), jax.random.normal(k3, (2, 3, hw[0] + 1, hw[1], 5))):
            exact = jax.vmap(lambda im: nn.conv._conv(im, params["w"], nn.conv._pair(stride), padding))(x) + params["b"]
            y = nn.conv.apply(params, x, stride=stride, padding=padding)
            np.testing.assert_allclose(y, exact, rtol=1e-5, atol=1e-5)
            convs = _conv_operand_dtypes(jax.make_jaxpr(lambda x: nn.conv.apply(params, x, stride=stride, padding=padding))(x))
            assert len(convs) == (0 if x.shape[-3] == hw[0] else 1)


def test_conv2d_in_bfloat16_runs_its_gradient_in_bfloat16_and_returns_float32_gradients(layers):
    params, x = layers["conv"], _normal(2, 6, 8, 2)

    def loss(p, x, dtype, blocks):
        y = nn.conv.apply(p, x, stride=2, compute_dtype=dtype, space_to_depth=blocks)
        return _weighted_sum(y.astype(jnp.float32))

    grad = jax.grad(loss, argnums=(0, 1))
    exact = jit(grad, static_argnums=(2, 3))(params, x, None, False)
    for blocks in (False, True):
        # Forward and both transposes take bf16 operands.
        dtypes = _conv_operand_dtypes(jax.make_jaxpr(grad, static_argnums=(2, 3))(params, x, jnp.bfloat16, blocks))
        assert len(dtypes) >= 3 and set(dtypes) == {("bfloat16", "bfloat16")}, dtypes
        mixed = jit(grad, static_argnums=(2, 3))(params, x, jnp.bfloat16, blocks)
        for a, b in zip(jax.tree.leaves(exact), jax.tree.leaves(mixed)):
            assert b.dtype == jnp.float32 and np.isfinite(b).all()
            # Measured on the CPU over five seeds: at most 0.52% of the largest gradient entry.
            np.testing.assert_allclose(b, a, rtol=0, atol=0.02 * np.abs(a).max())


def _compiled_convolutions(fn, *args) -> list[str]:
    text = jax.jit(fn).lower(*args).compile().as_text()
    return [line for line in text.splitlines() if " convolution(" in line]


@pytest.mark.parametrize("blocks", [False, True])
def test_kernels_vmapped_over_runs_run_as_one_ungrouped_convolution_per_run(blocks):
    """Runs trained together (vmap over their own kernels): each run's output and gradients are
    its own, and no convolution of the program is grouped, forward or backward (JAX's batching
    would make one grouped convolution, whose gradients GPU kernels run far slower). A batched
    image under one kernel (the lanes of one run) gives each image's own gradient too."""
    runs = 2
    keys = jax.random.split(KEY, runs + 1)
    params = [{**nn.conv.init(k, 5, 7, 3), "b": jnp.full((7,), 0.1 * i)} for i, k in enumerate(keys[:runs])]
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *params)
    images = _normal(runs, 3, 8, 12, 5)

    def loss(p, x):
        return _weighted_sum(nn.conv.apply(p, x, stride=2, space_to_depth=blocks))

    grad = jax.grad(loss, argnums=(0, 1))
    for in_axes, image_of in (((0, 0), lambda i: images[i]), ((0, None), lambda i: images[0])):
        together = jax.vmap(grad, in_axes=in_axes)
        got = jit(together)(stacked, images if in_axes[1] == 0 else images[0])
        for i in range(runs):
            own = jit(grad)(params[i], image_of(i))
            for a, b in zip(jax.tree.leaves(own), jax.tree.leaves(jax.tree.map(lambda g: g[i], got))):
                np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-5)
        convs = _compiled_convolutions(together, stacked, images if in_axes[1] == 0 else images[0])
        assert convs and not [c for c in convs if "group_count" in c], convs
        assert len(convs) == runs * len(_compiled_convolutions(grad, params[0], images[0]))
    per_image = jit(jax.vmap(grad, in_axes=(None, 0)))(params[0], images)
    for i in range(runs):
        for a, b in zip(jax.tree.leaves(jit(grad)(params[0], images[i])), jax.tree.leaves(per_image)):
            np.testing.assert_allclose(b[i], a, rtol=1e-5, atol=1e-5)


def test_conv2d_output_sizes_and_leading_dims(layers):
    params = layers["conv"]
    x = np.zeros((2, 3, 16, 64, 2), np.float32)

    def shape(padding):
        return jax.eval_shape(lambda p, x: nn.conv.apply(p, x, stride=2, padding=padding), params, x).shape

    assert shape("SAME") == (2, 3, 8, 32, 3)
    assert shape("VALID") == (2, 3, 7, 31, 3)


def test_layer_norm_gives_zero_mean_unit_variance():
    x = _normal(3, 16) * 5 + 2
    y = jit(nn.norm.apply)(nn.norm.init(None, 16), x)
    np.testing.assert_allclose(y.mean(-1), 0, atol=1e-5)
    np.testing.assert_allclose(y.var(-1), 1, atol=1e-3)


ATTEND = jit(nn.attention.apply)


@pytest.fixture(scope="module")
def attention_case(layers):
    params = layers["attention"]
    q, kv = _normal(2, 3, 8), _normal(2, 5, 6)
    mask = np.array([[True, False, True, True, False], [True, True, False, False, False]])
    return params, q, kv, mask


def test_attention_ignores_masked_keys_exactly(attention_case):
    params, q, kv, mask = attention_case
    garbage = np.where(mask[..., None], kv, 1e3 * _normal(*kv.shape))
    out = ATTEND(params, q, kv, mask)
    np.testing.assert_array_equal(out, ATTEND(params, q, garbage, mask))
    # ...and equals attending to the valid keys alone.
    alone = nn.attention.apply(params, q[1:], kv[1:, :2])
    np.testing.assert_allclose(out[1:], alone, rtol=1e-5, atol=1e-6)


def test_attention_without_mask_equals_all_true_mask(attention_case):
    params, q, kv, _ = attention_case
    np.testing.assert_allclose(
        nn.attention.apply(params, q, kv), ATTEND(params, q, kv, np.ones(kv.shape[:2], bool)), rtol=1e-5
    )


def test_fully_masked_attention_row_gives_finite_zeros_and_gradients(attention_case):
    params, q, kv, _ = attention_case
    mask = np.zeros(kv.shape[:2], bool)
    out = ATTEND(params, q, kv, mask)
    np.testing.assert_array_equal(out, np.zeros_like(out))
    grads = jit(jax.grad(lambda p: jnp.sum(nn.attention.apply(p, q, kv, mask))))(params)
    assert all(np.isfinite(g).all() for g in jax.tree_util.tree_leaves(grads))


def test_self_attention_keeps_shape():
    params = jax.eval_shape(lambda: nn.attention.init(KEY, 8, 8, num_heads=4, head_dim=2))
    x = jax.ShapeDtypeStruct((2, 7, 8), jnp.float32)
    assert jax.eval_shape(lambda p, x: nn.attention.apply(p, x, x), params, x).shape == (2, 7, 8)


SCAN = jit(nn.lstm.lstm_scan)


@pytest.fixture(scope="module")
def lstm_case(layers):
    params = layers["lstm"]
    carry = nn.lstm.LSTMState(_normal(2, 5), _normal(2, 5))
    return params, _normal(6, 2, 3), carry


def test_lstm_scan_equals_python_loop_over_the_cell(lstm_case):
    params, xs, carry = lstm_case
    final, hs = SCAN(params, carry, xs)
    cell = jit(nn.lstm.apply)
    c, loop_hs = carry, []
    for x in xs:
        c, h = cell(params, c, x)
        loop_hs.append(h)
    np.testing.assert_allclose(hs, np.stack(loop_hs), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(final.c, c.c, rtol=1e-5, atol=1e-6)


def test_lstm_scan_reset_zeroes_the_carry_before_that_step(lstm_case):
    params, xs, carry = lstm_case
    resets = np.zeros((6, 2), bool)
    resets[3, 0] = True
    _, hs = SCAN(params, carry, xs, resets)
    _, untouched = SCAN(params, carry, xs, np.zeros_like(resets))
    # Sample 0 from step 3 on is a fresh sequence from a zero carry; the rest is untouched.
    zero = nn.lstm.LSTMState(np.zeros((2, 5), np.float32), np.zeros((2, 5), np.float32))
    _, fresh = SCAN(params, zero, np.concatenate([xs[3:], xs[:3]]), np.zeros_like(resets))
    np.testing.assert_allclose(hs[3:, 0], fresh[:3, 0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(hs[:, 1], untouched[:, 1], rtol=1e-6)
    np.testing.assert_allclose(hs[:3], untouched[:3], rtol=1e-6)


def test_mlp_maps_sizes_and_stays_linear_at_the_output(layers):
    params = layers["mlp"]
    x = np.ones((4, 5, 3), np.float32)
    out = jit(nn.mlp.apply)(params, np.concatenate([x, -100 * x]))
    assert out.shape == (8, 5, 2)
    assert out.min() < 0  # no activation after the last layer


def test_embedding_looks_up_rows_and_sinusoidal_is_bounded(layers):
    params = layers["embedding"]
    ids = np.array([[0, 9], [3, 3]])
    np.testing.assert_array_equal(nn.embedding.apply(params, ids), np.asarray(params["table"])[ids])
    pe = np.asarray(jit(nn.embedding.sinusoidal, static_argnums=1)(np.arange(50), 16))
    assert pe.shape == (50, 16) and np.abs(pe).max() <= 1.0
    np.testing.assert_allclose(pe[0], np.r_[np.zeros(8), np.ones(8)])
    assert len({tuple(np.round(r, 4)) for r in pe}) == 50  # positions distinguishable


def test_float64_checks_do_not_leak_x64_into_other_tests():
    # Runs after the float64 gradient tests above in this file.
    assert jnp.zeros(1).dtype == jnp.float32
    assert jnp.asarray(1.0).dtype == jnp.float32
    assert jax.eval_shape(lambda: nn.linear.init(KEY, 3, 4))["w"].dtype == jnp.float32
