"""Agents by name: what `conav eval`, `conav view` and `conav bench eval` build.

name -> AgentSpec (does it load a trained run? does it read intention inputs?) -> `check_agent`
(cheap: no env, no compile, run directories checked) -> `make_agent(name, env, ...)` -> Agent.
Besides the names below, `"package.module:factory"` names a user's agent: the factory, imported
from that module, returns an observation-only Agent (envs.agents.base), and its row says what
the agent declares.
Agents that read intention inputs (conav, ppo) take predictor runs, or `ground_truth=True` for
the env's ground truth; they refuse to run with neither (envs.agents.policy). The learned
object-goal agent's predicted variant takes an intention predictor run and nothing else
(envs.agents.goalnav).
"""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path
from typing import Any, Callable, NamedTuple

from conav_jax import runs
from conav_jax.envs.agents.base import Agent, StateAgent


class AgentSpec(NamedTuple):
    """How to build one agent."""

    build: Callable[..., Agent | StateAgent]  # (env, checkpoint, **kwargs) -> the agent
    summary: str  # one line for the command line's help
    needs_checkpoint: bool = False  # loads a trained run directory
    takes_intentions: bool = False  # reads intention inputs: predictor runs or ground truth
    run_kind: str | None = None  # the conav_jax.runs kind of its checkpoint


def _baseline(name: str) -> Callable[..., Agent]:
    def build(env, checkpoint, **kwargs):
        from conav_jax.envs.agents import baselines

        return {"random": baselines.random_agent, "pioneer": baselines.pioneer_agent,
                "pioneer-drive": baselines.pioneer_drive_agent,
                "follower": baselines.follower_agent, "objectgoal-planner": baselines.objectgoal_planner_agent}[name](env, **kwargs)

    return build


def _expert(env, checkpoint, **kwargs):
    from conav_jax.envs.agents.expert import expert_agent

    return expert_agent(env, **kwargs)


def _conav(env, checkpoint, **kwargs):
    from conav_jax.envs.agents.policy import policy_agent

    return policy_agent(env, checkpoint, **kwargs)


def _ppo(env, checkpoint, **kwargs):
    from conav_jax.envs.agents.ppo import ppo_agent

    return ppo_agent(env, checkpoint, **kwargs)


def _objectgoal(oracle: bool) -> Callable[..., Agent]:
    def build(env, checkpoint, **kwargs):
        from conav_jax.envs.agents.goalnav import objectgoal_agent

        return objectgoal_agent(env, checkpoint, oracle, **kwargs)

    return build


def _imagegoal(env, checkpoint, **kwargs):
    from conav_jax.envs.agents.goalnav import imagegoal_agent

    return imagegoal_agent(env, checkpoint, **kwargs)


AGENTS: dict[str, AgentSpec] = {
    "random": AgentSpec(_baseline("random"), "uniform random actions"),
    "pioneer": AgentSpec(_baseline("pioneer"), "the paper's pioneer: put at once (oracle pathfinder) at the object "
                         "standing point nearest where the human will be in 2 s (privileged)"),
    "pioneer-drive": AgentSpec(_baseline("pioneer-drive"), "the pioneer's target, driven to along the oracle "
                               "geodesic field (privileged)"),
    "follower": AgentSpec(_baseline("follower"), "stays about 1 m behind the human"),
    "objectgoal-planner": AgentSpec(_baseline("objectgoal-planner"), "oracle goal category + oracle map: the nearest "
                                    "instance along its geodesic field (privileged)"),
    "expert": AgentSpec(_expert, "the imitation teacher (privileged: goal, map, the human's future)"),
    "conav": AgentSpec(_conav, "the trained CoNav policy (--checkpoint: a `conav train policy` run)", True, True, runs.POLICY),
    "ppo": AgentSpec(_ppo, "a PPO policy (--checkpoint: a `conav train rl` run)", True, True, runs.PPO),
    "objectgoal-oracle": AgentSpec(_objectgoal(True), "the learned object-goal agent (no map) given the episode's "
                                   "object-B category (privileged; --checkpoint: a `conav train objectnav` run)",
                                   True, False, runs.OBJECTNAV),
    "objectgoal-predicted": AgentSpec(_objectgoal(False), "the learned object-goal agent given the intention "
                                      "predictor's most likely object (--checkpoint: a `conav train objectnav` run, "
                                      "--intention RUN)", True, True, runs.OBJECTNAV),
    "imagegoal": AgentSpec(_imagegoal, "the learned image-goal agent given an image rendered at the human's position "
                           "each step (privileged; --checkpoint: a `conav train imagenav` run)", True, False, runs.IMAGENAV),
}


def user_factory(name: str) -> Callable[..., Any]:
    """The factory a `"package.module:factory"` agent name points at (a dotted attribute path
    after the colon works too). ValueError naming the module or attribute that cannot be found."""
    module_name, _, attr = name.partition(":")
    if not module_name or not attr:
        raise ValueError(f"a user agent is named 'package.module:factory', got {name!r}")
    try:
        obj = importlib.import_module(module_name)
    except ImportError as e:
        raise ValueError(f"agent {name!r}: cannot import module {module_name!r} ({e})") from e
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"agent {name!r}: module {module_name!r} has no {attr!r}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise ValueError(f"agent {name!r}: {attr!r} is not callable (a factory returning an Agent)")
    return obj


def _user_agent(name: str) -> Callable[..., Agent]:
    def build(env, checkpoint, **kwargs):
        factory = user_factory(name)
        takes_env = any(p.default is p.empty and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
                        for p in inspect.signature(factory).parameters.values())
        agent = factory(env, **kwargs) if takes_env else factory(**kwargs)
        if not isinstance(agent, Agent):
            raise ValueError(f"agent {name!r}: the factory returned {type(agent).__name__}, not a conav_jax.Agent "
                             "(title, init(key, obs) -> carry, act(carry, obs, key) -> (carry, action))")
        return agent

    return build


def check_agent(name: str, checkpoint: str | Path | None = None) -> AgentSpec:
    """The spec of agent `name`, after checking it can be built; ValueError otherwise.
    Cheap (no env, no compile, no heavy import) for the named agents: sweeps call it for every
    agent first. A `"package.module:factory"` name imports its module to find the factory."""
    if ":" in name:
        user_factory(name)
        return AgentSpec(_user_agent(name), f"the user's agent {name}")
    spec = AGENTS.get(name)
    if spec is None:
        raise ValueError(f"unknown agent {name!r}; choose from {', '.join(AGENTS)}, or name your own "
                         "as 'package.module:factory'")
    if spec.needs_checkpoint:
        if checkpoint is None:
            raise ValueError(f"agent {name!r} needs a trained run: pass its checkpoint (a run directory)")
        if not Path(checkpoint).is_dir():
            raise ValueError(f"checkpoint run directory not found for agent {name!r}: {checkpoint}")
    return spec


def make_agent(name: str, env, checkpoint: str | Path | None = None, **kwargs: Any) -> Agent | StateAgent:
    """Build agent `name` for `env`. `checkpoint`: the run directory of a learned agent (ignored
    by the others); `kwargs` go to the agent's constructor (e.g. `cfg=BaselineConfig(...)`, or
    `intention_run=`, `trajectory_run=`, `ground_truth=` for agents that read intentions). A
    `"package.module:factory"` name calls `factory(env, **kwargs)` (or `factory(**kwargs)` when
    it takes no required positional argument), which must return an Agent."""
    spec = check_agent(name, checkpoint)
    intention_keys = {"intention_run", "trajectory_run", "ground_truth"} & set(kwargs)
    if intention_keys and not spec.takes_intentions:
        raise ValueError(f"agent {name!r} reads no intention inputs; it takes no {sorted(intention_keys)}")
    return spec.build(env, None if checkpoint is None else str(checkpoint), **kwargs).check()


def run_resolution(trained: list[tuple[str, str | Path]], resolution: tuple[int, int] | None = None) -> tuple[int, int]:
    """The panorama (H, W) an env must render for these (agent name, run dir) pairs: the
    resolution their policies were trained at (ValueError if they differ, or differ from a
    given `resolution`), else `resolution`, else SensorConfig's default. Reads only the runs'
    configs, so it is cheap enough for input checks."""
    from conav_jax.envs.config import SensorConfig

    found: dict[tuple[int, int], str] = {}
    for name, run in trained:
        spec = check_agent(name, run)
        hw = tuple(runs.run_config(run, spec.run_kind)["model"]["resolution"])
        found.setdefault(hw, str(run))
    if len(found) > 1:
        raise ValueError("the trained runs read different panoramas: " +
                         ", ".join(f"{run} {h}x{w}" for (h, w), run in found.items()))
    if found:
        (hw, run), = found.items()
        if resolution is not None and tuple(resolution) != hw:
            raise ValueError(f"resolution {resolution[0]}x{resolution[1]}, but {run} was trained at {hw[0]}x{hw[1]}")
        return hw
    if resolution is not None:
        return tuple(resolution)
    default = SensorConfig()
    return default.resolution
