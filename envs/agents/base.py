"""What acts in the env: the public, observation-only `Agent`, the internal `StateAgent` of
the simulator's privileged agents, and what a benchmark row must say about either.

`Agent` (the contract a user writes, jittable, for ONE environment; rollouts vmap it):
`init(key, obs) -> carry` and `act(carry, obs, key) -> (carry, action)`, `action` = (v_lin,
v_ang) in [-1, 1]. `obs` holds exactly the observation keys the agent `reads`
(envs.observations); a privileged key reaches only an agent that lists its privileged input.

`StateAgent` (internal: the expert, the scripted baselines, the planners): `init(key, state)`
and `act(state, carry, key) -> (action, carry)` read the env's brax State (its obs holds the
keys the agent reads) and the episode bank through `env.bank_view` (looked up as it acts, so a
compiled rollout can take the bank as an argument: envs.rollout.jit_with_bank). A learned one
(`sensing_agent`: the goal-navigation baselines) is an observation-only policy given inputs
the simulator makes from the State. Every such read is named in `privileged`; an oracle mover
(`action_size` 3, a pose) lists ORACLE_MOVES, and the rollout moves it with
ConavEnv.step_to_pose. Both carry what a results table reports: a
`title`, where intention inputs come from (`intention_source`) and every privileged input; a
row never hides an oracle (`row_title`).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp

MIXED_ACTION_SIZE = 6  # switch_agent's (kind, v_lin, v_ang, x, y, yaw): kind 1 a pose

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
    """An agent that sees observations only (module docstring): a title, two jittable functions
    and its declarations. `reads`: the observation keys it gets (default: every sensor, none
    privileged); `privileged`: the privileged inputs it declares, from PRIVILEGED_INPUTS (a
    privileged key in `reads` needs its input listed: envs.observations). `name`: a short
    identifier for files and logs (default: the title)."""

    title: str
    init: Callable[[jax.Array, dict], Any]  # (key, obs) -> carry
    act: Callable[[Any, dict, jax.Array], tuple[Any, jax.Array]]  # (carry, obs, key) -> (carry, action (2,))
    reads: tuple[str, ...] | None = None  # None: the sensor keys (envs.observations.SENSOR_KEYS)
    privileged: tuple[str, ...] = ()
    name: str = ""
    intention_source: str = NO_INTENTIONS
    action_size: int = 2  # velocities only

    def check(self) -> "Agent":
        """This agent with its defaults filled in, after checking its declarations; ValueError
        naming what is wrong."""
        from conav_jax.envs.observations import SENSOR_KEYS

        source = self.intention_source
        if source == NO_INTENTIONS and GROUND_TRUTH_INTENTIONS in self.privileged:
            source = GROUND_TRUTH  # an agent declaring the ground truth reads its intentions from it
        agent = self._replace(name=self.name or self.title, title=self.title or self.name,
                              reads=SENSOR_KEYS if self.reads is None else tuple(self.reads),
                              privileged=tuple(self.privileged), intention_source=source)
        if not agent.name:
            raise ValueError("an agent needs a title")
        if not callable(agent.init) or not callable(agent.act):
            raise ValueError(f"agent {agent.name!r}: init and act must be functions")
        if ORACLE_MOVES in agent.privileged or agent.action_size != 2:
            raise ValueError(f"agent {agent.name!r}: an observation-only agent acts with velocities (v_lin, "
                             f"v_ang); {ORACLE_MOVES!r} is for the simulator's own oracle movers")
        return _check_declarations(agent)


class StateAgent(NamedTuple):
    """An internal agent reading the simulator's State (module docstring): privileged by design."""

    name: str
    init: Callable[[jax.Array, Any], Any]  # (key, state) -> carry
    act: Callable[[Any, Any, jax.Array], tuple[jax.Array, Any]]  # (state, carry, key) -> (action, carry)
    title: str = ""  # the row name in reports (default: the name)
    intention_source: str = NO_INTENTIONS
    privileged: tuple[str, ...] = ()
    reads: tuple[str, ...] = ()  # the observation keys its State's obs holds
    # 2: (v_lin, v_ang) velocity commands; 3: a pose (x, y, yaw) the env puts the robot at
    # (ConavEnv.step_to_pose), which only an oracle mover may do; MIXED_ACTION_SIZE: either, the
    # kind first (switch_agent over agents of both kinds).
    action_size: int = 2
    # A learned agent given privileged inputs (sensing_agent): the observation-only policy it
    # acts through and `sense(state) -> dict`, the inputs the simulator adds to the State's
    # observation for it; its init and act are made of them. None for the scripted agents.
    policy: Agent | None = None
    sense: Callable[[Any], dict] | None = None

    def check(self) -> "StateAgent":
        """This agent, after checking its description; ValueError naming what is wrong."""
        # MIXED_ACTION_SIZE belongs to switch_agent's groups alone, which are never rows.
        if self.action_size not in (2, 3) or (self.action_size == 3) != (ORACLE_MOVES in self.privileged):
            raise ValueError(f"agent {self.name!r}: action_size is 2 (velocities) or 3 (poses, listing "
                             f"{ORACLE_MOVES!r} as privileged), got {self.action_size}")
        return _check_declarations(self)


def sensing_agent(policy: Agent, sense: Callable[[Any], dict], name: str, title: str, privileged: tuple[str, ...],
                  reads: tuple[str, ...], intention_source: str = NO_INTENTIONS) -> StateAgent:
    """A StateAgent acting as `policy`, an observation-only agent, on its State's observation
    (the keys `reads`) and the privileged inputs `sense(state)` adds to it: the learned
    goal-navigation baselines, given the episode's goal category or a goal image rendered where
    the human stands. `policy.init` sees the State's observation alone. The policy is kept apart
    from what the simulator gives it, so a rollout can take its weights as arguments
    (envs.agents.lift)."""

    def init(key, state):
        return policy.init(key, state.obs)

    def act(state, carry, key):
        carry, action = policy.act(carry, {**state.obs, **sense(state)}, key)
        return action, carry

    return StateAgent(name, init, act, title, intention_source, privileged, reads, policy=policy, sense=sense).check()


def _check_declarations(agent):
    """`agent` after checking its intention source, privileged inputs and observation keys."""
    from conav_jax.envs.observations import undeclared_privileged

    if agent.intention_source not in INTENTION_SOURCES:
        raise ValueError(f"agent {agent.name!r}: intention_source must be one of {INTENTION_SOURCES}, "
                         f"got {agent.intention_source!r}")
    unknown = [p for p in agent.privileged if p not in PRIVILEGED_INPUTS]
    if unknown:
        raise ValueError(f"agent {agent.name!r}: unknown privileged inputs {unknown}; known: {PRIVILEGED_INPUTS}")
    if (agent.intention_source == GROUND_TRUTH) != (GROUND_TRUTH_INTENTIONS in agent.privileged):
        raise ValueError(f"agent {agent.name!r}: ground-truth intentions must be listed as privileged exactly "
                         "when they are the intention source")
    hidden = undeclared_privileged(agent.reads, agent.privileged)
    if hidden:
        raise ValueError(f"agent {agent.name!r} reads privileged observations without declaring them: " +
                         ", ".join(f"{k} (privileged={p!r})" for k, p in hidden.items()))
    return agent


def as_state_agent(agent: Agent | StateAgent) -> StateAgent:
    """`agent` as the rollouts run it: an observation-only Agent acting on its State's obs (which
    holds the keys it reads, and nothing else); a StateAgent as it is."""
    if isinstance(agent, StateAgent):
        return agent
    agent = agent.check()

    def act(state, carry, key):
        carry, action = agent.act(carry, state.obs, key)
        return jnp.asarray(action), carry

    return StateAgent(agent.name, lambda key, state: agent.init(key, state.obs), act, agent.title,
                      agent.intention_source, agent.privileged, agent.reads)


def _as_mixed_action(action: jax.Array, action_size: int) -> jax.Array:
    """A velocity (2,) or pose (3,) action, as its agent's `action_size` declares it, as (6,) =
    (kind, v_lin, v_ang, x, y, yaw), the unused part zero (envs.rollout's `agent_step` steps it
    with ConavEnv.step_to_pose)."""
    if action_size == 2:
        return jnp.concatenate([jnp.zeros_like(action[..., :1]), action, jnp.zeros((*action.shape[:-1], 3), action.dtype)], -1)
    return jnp.concatenate([jnp.ones_like(action[..., :1]), jnp.zeros_like(action[..., :2]), action], -1)


def switch_agent(agents: Sequence[Agent | StateAgent], which: jax.Array) -> StateAgent:
    """One StateAgent acting as `agents[which]` (`which` an int32 scalar, traced or not): a
    rollout compiled once serves all of them, the agent chosen as data. Its carry holds every
    agent's; under vmap over environments `which` stays one scalar, so only the chosen agent
    computes. It observes what any of them reads, each seeing its own keys only. Agents of both
    action kinds (velocities and poses) together act in the mixed (6,) form."""
    agents = tuple(as_state_agent(a) for a in agents)
    if not agents:
        raise ValueError("switch_agent needs at least one agent")
    mixed = len({a.action_size for a in agents}) > 1
    reads = tuple(dict.fromkeys(k for a in agents for k in a.reads))

    def own(state, agent):
        return state.replace(obs={k: state.obs[k] for k in agent.reads})

    def init(key, state):
        return tuple(a.init(key, own(state, a)) for a in agents)

    def act(state, carry, key):
        def branch(i):
            def run(carry):
                action, mine = agents[i].act(own(state, agents[i]), carry[i], key)
                action = jnp.asarray(action)
                # What an agent declares, not the shape it returns, says what its action is: only
                # a declared oracle mover's three numbers are a pose.
                if action.shape[-1:] != (agents[i].action_size,):
                    raise ValueError(f"agent {agents[i].name!r} declares actions of size {agents[i].action_size} "
                                     f"({'a pose' if agents[i].action_size == 3 else '(v_lin, v_ang)'}), "
                                     f"returned shape {action.shape}")
                return (_as_mixed_action(action, agents[i].action_size) if mixed else action,
                        carry[:i] + (mine,) + carry[i + 1:])
            return run

        return jax.lax.switch(which, [branch(i) for i in range(len(agents))], carry)

    privileged = tuple(dict.fromkeys(p for a in agents for p in a.privileged if p != ORACLE_MOVES))
    return StateAgent("|".join(a.name for a in agents), init, act, reads=reads, privileged=privileged,
                      action_size=MIXED_ACTION_SIZE if mixed else agents[0].action_size)


def row_title(agent: Agent | StateAgent) -> str:
    """The agent's title with where its intentions come from and every privileged input, e.g.
    "CoNav Agent (ground-truth intentions + oracle segmentation)" or "Object-goal planner
    (oracle goal category + oracle map)"."""
    parts = {PREDICTED: ["predicted intentions"], GROUND_TRUTH: [GROUND_TRUTH_INTENTIONS]}.get(agent.intention_source, [])
    parts += [p for p in agent.privileged if p not in parts]
    title = agent.title or agent.name
    return f"{title} ({' + '.join(parts)})" if parts else title


def describe(agent: Agent | StateAgent) -> dict:
    """What a results file records about a checked agent (Agent.check fills in its defaults):
    name, row title, intention source, privileged inputs, the observation keys it reads (an
    Agent's declared `reads`, the keys a StateAgent's State holds) and whether it reads the
    simulator's state (a StateAgent: the scripted and goal-navigation agents, whose privileged
    inputs say what of it they use), so a row says what it was given as well as how it did."""
    return {
        "agent": agent.name,
        "title": row_title(agent),
        "intention_source": agent.intention_source,
        "privileged": list(agent.privileged),
        "reads": list(agent.reads),
        "reads_state": isinstance(agent, StateAgent),
    }
