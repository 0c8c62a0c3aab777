"""The Agent interface every rollout runs, and what a benchmark row must say about an agent.

An `Agent` acts for ONE environment (rollouts vmap it): `init(key, episode) -> carry` and
`act(state, carry, key) -> (action (2,), carry)`, where `state` is the env's brax State. Beside
the two functions it carries what a results table reports about it: a `title`, where its
intention inputs come from (`intention_source`) and every privileged input it reads
(`privileged`, from the names below). A row never hides an oracle: `row_title` spells them out.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax

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
PRIVILEGED_INPUTS = (
    ORACLE_MAP, ORACLE_GOAL_CATEGORY, ORACLE_GOAL_POINT, CANDIDATE_GOAL_POINTS,
    GROUND_TRUTH_INTENTIONS, FUTURE_HUMAN_POSITIONS, HUMAN_PHASE, ORACLE_SEGMENTATION,
)


class Agent(NamedTuple):
    name: str
    init: Callable[[jax.Array, jax.Array], Any]  # (key, episode index) -> carry
    act: Callable[[Any, Any, jax.Array], tuple[jax.Array, Any]]  # (state, carry, key) -> (action, carry)
    title: str = ""  # the row name in reports (default: the name)
    intention_source: str = NO_INTENTIONS
    privileged: tuple[str, ...] = ()

    def check(self) -> "Agent":
        """This agent, after checking its description; ValueError naming what is wrong."""
        if self.intention_source not in INTENTION_SOURCES:
            raise ValueError(f"agent {self.name!r}: intention_source must be one of {INTENTION_SOURCES}, "
                             f"got {self.intention_source!r}")
        unknown = [p for p in self.privileged if p not in PRIVILEGED_INPUTS]
        if unknown:
            raise ValueError(f"agent {self.name!r}: unknown privileged inputs {unknown}; known: {PRIVILEGED_INPUTS}")
        if (self.intention_source == GROUND_TRUTH) != (GROUND_TRUTH_INTENTIONS in self.privileged):
            raise ValueError(f"agent {self.name!r}: ground-truth intentions must be listed as privileged exactly "
                             "when they are the intention source")
        return self


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
