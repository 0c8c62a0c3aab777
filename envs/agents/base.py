"""The Agent interface every rollout runs, and what a benchmark row must say about an agent.

An `Agent` acts for ONE environment (rollouts vmap it): `init(key, episode) -> carry` and
`act(state, carry, key) -> (action (2,), carry)`, where `state` is the env's brax State. A
privileged agent reads the episode bank through `env.bank_view` (looked up as it acts), so that
a compiled rollout can take the bank as an argument (envs.rollout.jit_with_bank). Beside
the two functions it carries what a results table reports about it: a `title`, where its
intention inputs come from (`intention_source`) and every privileged input it reads
(`privileged`, from the names below). A row never hides an oracle: `row_title` spells them out.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp

MIXED_ACTION_SIZE = 6  # ConavEnv.step's (kind, v_lin, v_ang, x, y, yaw)

# Where an agent's intention inputs (activity B, object B, future trajectory) come from.
PREDICTED = "predicted"  # the intention and trajectory predictors' outputs
GROUND_TRUTH = "ground_truth"  # the env's ground truth (privileged)
NO_INTENTIONS = "none"  # the agent reads no intention input
INTENTION_SOURCES = (PREDICTED, GROUND_TRUTH, NO_INTENTIONS)

# Privileged inputs: what an agent reads that a real robot with the paper's sensors would not have.
ORACLE_MAP = "oracle map"  # the scene's geometry or geodesic fields
ORACLE_GOAL_CATEGORY = "oracle goal category"  # the episode's object-B category
ORACLE_GOAL_POINT = "oracle goal point"  # the episode's goal position itself
CANDIDATE_GOAL_POINTS = "candidate goal points"  # every object's standing point in the scene
GROUND_TRUTH_INTENTIONS = "ground-truth intentions"  # activity/object B from the episode
FUTURE_HUMAN_POSITIONS = "future human positions"  # where the human will be
HUMAN_PHASE = "human activity phase"  # whether the human is still at activity A
ORACLE_SEGMENTATION = "oracle segmentation"  # each pixel's object category, from the render
HUMAN_VIEW_GOAL_IMAGE = "goal image from the human's position"  # rendered where the human stands, each step
ORACLE_MOVES = "pose set by an oracle pathfinder"  # moved to a target at once, not driven there
PRIVILEGED_INPUTS = (
    ORACLE_MAP, ORACLE_GOAL_CATEGORY, ORACLE_GOAL_POINT, CANDIDATE_GOAL_POINTS, GROUND_TRUTH_INTENTIONS,
    FUTURE_HUMAN_POSITIONS, HUMAN_PHASE, ORACLE_SEGMENTATION, HUMAN_VIEW_GOAL_IMAGE, ORACLE_MOVES,
)


class Agent(NamedTuple):
    name: str
    init: Callable[[jax.Array, jax.Array], Any]  # (key, episode index) -> carry
    act: Callable[[Any, Any, jax.Array], tuple[jax.Array, Any]]  # (state, carry, key) -> (action, carry)
    title: str = ""  # the row name in reports (default: the name)
    intention_source: str = NO_INTENTIONS
    privileged: tuple[str, ...] = ()
    # 2: (v_lin, v_ang) velocity commands; 3: a pose (x, y, yaw) the env puts the robot at
    # (ConavEnv.step), which only an oracle mover may do; MIXED_ACTION_SIZE: either, the kind
    # first (switch_agent over agents of both kinds).
    action_size: int = 2

    def check(self) -> "Agent":
        """This agent, after checking its description; ValueError naming what is wrong."""
        if self.intention_source not in INTENTION_SOURCES:
            raise ValueError(f"agent {self.name!r}: intention_source must be one of {INTENTION_SOURCES}, "
                             f"got {self.intention_source!r}")
        unknown = [p for p in self.privileged if p not in PRIVILEGED_INPUTS]
        if unknown:
            raise ValueError(f"agent {self.name!r}: unknown privileged inputs {unknown}; known: {PRIVILEGED_INPUTS}")
        if self.action_size not in (2, 3) or (self.action_size == 3) != (ORACLE_MOVES in self.privileged):
            raise ValueError(f"agent {self.name!r}: action_size is 2 (velocities) or 3 (poses, listing "
                             f"{ORACLE_MOVES!r} as privileged), got {self.action_size}")
        if (self.intention_source == GROUND_TRUTH) != (GROUND_TRUTH_INTENTIONS in self.privileged):
            raise ValueError(f"agent {self.name!r}: ground-truth intentions must be listed as privileged exactly "
                             "when they are the intention source")
        return self


def _as_mixed_action(action: jax.Array) -> jax.Array:
    """A velocity (2,) or pose (3,) action as ConavEnv.step's (6,) = (kind, v_lin, v_ang, x, y,
    yaw), the unused part zero."""
    if action.shape[-1] == 2:
        return jnp.concatenate([jnp.zeros_like(action[..., :1]), action, jnp.zeros((*action.shape[:-1], 3), action.dtype)], -1)
    return jnp.concatenate([jnp.ones_like(action[..., :1]), jnp.zeros_like(action[..., :2]), action], -1)


def switch_agent(agents: Sequence[Agent], which: jax.Array) -> Agent:
    """One Agent acting as `agents[which]` (`which` an int32 scalar, traced or not): a rollout
    compiled once serves all of them, the agent chosen as data. Its carry holds every agent's;
    under vmap over environments `which` stays one scalar, so only the chosen agent computes.
    Agents of both action kinds (velocities and poses) together act in ConavEnv.step's mixed
    (6,) form."""
    agents = tuple(agents)
    if not agents:
        raise ValueError("switch_agent needs at least one agent")
    mixed = len({a.action_size for a in agents}) > 1

    def init(key, episode):
        return tuple(a.init(key, episode) for a in agents)

    def act(state, carry, key):
        def branch(i):
            def run(carry):
                action, own = agents[i].act(state, carry[i], key)
                return _as_mixed_action(action) if mixed else action, carry[:i] + (own,) + carry[i + 1:]
            return run

        return jax.lax.switch(which, [branch(i) for i in range(len(agents))], carry)

    return Agent("|".join(a.name for a in agents), init, act, action_size=MIXED_ACTION_SIZE if mixed else agents[0].action_size)


def row_title(agent: Agent) -> str:
    """The agent's title with where its intentions come from and every privileged input, e.g.
    "CoNav Agent (ground-truth intentions + oracle segmentation)" or "Object-goal planner
    (oracle goal category + oracle map)"."""
    parts = {PREDICTED: ["predicted intentions"], GROUND_TRUTH: [GROUND_TRUTH_INTENTIONS]}.get(agent.intention_source, [])
    parts += [p for p in agent.privileged if p not in parts]
    title = agent.title or agent.name
    return f"{title} ({' + '.join(parts)})" if parts else title


def describe(agent: Agent) -> dict:
    """What a results file records about an agent: name, row title, intention source, privileged inputs."""
    return {
        "agent": agent.name,
        "title": row_title(agent),
        "intention_source": agent.intention_source,
        "privileged": list(agent.privileged),
    }
