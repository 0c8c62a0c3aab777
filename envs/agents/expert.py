"""The imitation teacher in the simulator: conav_jax.nav.expert acting on one env's brax State.

The expert is privileged by design: it reads the episode's geodesic fields (its goal and the
human's start), the wall clearance of the scene, the human's upcoming positions and whether the
human is still at activity A. train.imitation records it; `conav eval --agent expert` reports
it as the ceiling a learned policy is measured against.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from conav_jax.motion.phases import PHASE_ACTIVITY_A
from conav_jax.nav.expert import (
    ExpertCarry,
    ExpertConfig,
    ExpertMaps,
    expert_action,
    initial_carry,
)
from conav_jax.envs.agents.base import (
    FUTURE_HUMAN_POSITIONS,
    HUMAN_PHASE,
    ORACLE_GOAL_POINT,
    ORACLE_MAP,
    StateAgent,
)
from conav_jax.envs.mjcf import UD


# Jitted on its own (the configs static): every program that runs the expert on episodes of
# one shape reuses its traced jaxpr. XLA inlines it.
_expert_action = jax.jit(expert_action, static_argnums=(0, 2))


def make_expert_step(env, cfg: ExpertConfig = ExpertConfig()) -> Callable:
    """`(state, carry) -> (action (2,), carry)`: conav_jax.nav.expert acting on one env's brax State.
    Privileged: it reads the episode's fields, the human's upcoming positions and phase."""
    b = env.bank_view
    look = jnp.asarray(cfg.human_lookahead_steps, jnp.int32)

    def step(state, carry: ExpertCarry):
        ep = state.info["episode"]
        s = b.scene_index[ep]
        t = state.pipeline_state.userdata[UD["t"]].astype(jnp.int32)
        ts = jnp.clip(t + look, 0, b.max_steps - 1)
        maps = ExpertMaps(b.fields[s, b.field_b[ep]], b.fields[s, b.field_a[ep]], b.clearance[s], b.field_origin[s])
        at_a = b.phase[ep, ts[0]] == PHASE_ACTIVITY_A
        return _expert_action(cfg, maps, b.cell_m, state.pipeline_state.qpos, b.root_xy[ep, ts], at_a, carry)

    return step


def expert_agent(env, cfg: ExpertConfig = ExpertConfig()) -> StateAgent:
    """The expert as a StateAgent named "expert": the imitation teacher, and the ceiling a learned
    policy is measured against."""
    step = make_expert_step(env, cfg)
    return StateAgent("expert", lambda key, state: initial_carry(), lambda state, carry, key: step(state, carry),
                 title="Imitation expert",
                      privileged=(ORACLE_GOAL_POINT, ORACLE_MAP, FUTURE_HUMAN_POSITIONS, HUMAN_PHASE))
