"""conav_jax.profiling: a compiled program's device time, attributed to its named scopes."""

import jax
import jax.numpy as jnp

from conav_jax.profiling import hlo_op_names, profile_program, scope_of

HLO = """HloModule m

%fused_add (param_0: f32[4]) -> f32[4] {
  %param_0 = f32[4]{0} parameter(0)
  ROOT %add.1 = f32[4]{0} add(%param_0, %param_0), metadata={op_name="jit(f)/update/add"}
}

ENTRY %main (p: f32[4]) -> f32[4] {
  %p = f32[4]{0} parameter(0)
  %sine.2 = f32[4]{0} sine(%p), metadata={op_name="jit(f)/rollout/observe/sin"}
  ROOT %loop_add_fusion.3 = f32[4]{0} fusion(%sine.2), kind=kLoop, calls=%fused_add
}
"""


def test_instructions_and_fusions_are_named_by_their_metadata():
    names = hlo_op_names(HLO)
    assert names["sine_2"] == "jit(f)/rollout/observe/sin"
    # The fusion carries no metadata: it takes its called computation's.
    assert names["loop_add_fusion_3"] == "jit(f)/update/add"


def test_a_scope_is_the_first_listed_one_the_op_is_traced_under():
    scopes = ("observe", "update", "rollout")
    assert scope_of("jit(f)/rollout/while/body/observe/sin", scopes) == "observe"
    assert scope_of("jit(f)/rollout/while/body/scan", scopes) == "rollout"
    assert scope_of("jit(f)/update/transpose(jvp())/while/body/dot_general", scopes) == "update (backward)"
    assert scope_of("jit(f)/while/body/vmap(observe)/min", scopes) == "observe"  # a scope under vmap
    assert scope_of("jit(f)/mul", scopes) == "other"


def test_device_time_goes_to_the_scopes_that_ran(tmp_path):
    def f(x):
        with jax.named_scope("heavy"):
            for _ in range(4):
                x = jnp.tanh(x @ x)
        with jax.named_scope("light"):
            y = x + 1.0
        return y

    x = jnp.full((192, 192), 0.01, jnp.float32)
    compiled = jax.jit(f).lower(x).compile()
    prof = profile_program(compiled, (x,), ("heavy", "light", "idle"), str(tmp_path), calls=2,
                           after=lambda out: (out,))
    by_scope = prof["by_scope_ms"]
    assert by_scope["heavy"] > by_scope.get("light", 0.0) >= 0.0
    assert "idle" not in by_scope
    assert prof["device_ms_per_call"] > 0 and prof["top_kernels_ms"]
