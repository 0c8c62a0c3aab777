"""Agents by name: what `conav eval`, `conav view` and `conav bench eval` build.

name -> AgentSpec (does it load a trained run? does it read intention inputs?) -> `check_agent`
(cheap: no env, no compile, run directories checked) -> `make_agent(name, env, ...)` -> Agent.
Agents that read intention inputs (conav, ppo) take predictor runs, or `ground_truth=True` for
the env's ground truth; they refuse to run with neither (envs.agents.policy). The learned
object-goal agent's predicted variant takes an intention predictor run and nothing else
(envs.agents.goalnav).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, NamedTuple

from conav_jax import runs
from conav_jax.envs.agents.base import Agent


class AgentSpec(NamedTuple):
    """How to build one agent."""

    build: Callable[..., Agent]  # (env, checkpoint, **kwargs) -> Agent
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


def check_agent(name: str, checkpoint: str | Path | None = None) -> AgentSpec:
    """The spec of agent `name`, after checking it can be built; ValueError otherwise.
    Cheap (no env, no compile, no heavy import): sweeps call it for every agent first."""
    spec = AGENTS.get(name)
    if spec is None:
        raise ValueError(f"unknown agent {name!r}; choose from {', '.join(AGENTS)}")
    if spec.needs_checkpoint:
        if checkpoint is None:
            raise ValueError(f"agent {name!r} needs a trained run: pass --checkpoint RUN_DIR")
        if not Path(checkpoint).is_dir():
            raise ValueError(f"checkpoint run directory not found for agent {name!r}: {checkpoint}")
    return spec


def make_agent(name: str, env, checkpoint: str | Path | None = None, **kwargs: Any) -> Agent:
    """Build agent `name` for `env`. `checkpoint`: the run directory of a learned agent (ignored
    by the others); `kwargs` go to the agent's constructor (e.g. `cfg=BaselineConfig(...)`, or
    `intention_run=`, `trajectory_run=`, `ground_truth=` for agents that read intentions)."""
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
        hw = tuple(runs.run_config(run, spec.run_kind)["model"]["image_hw"])
        found.setdefault(hw, str(run))
    if len(found) > 1:
        raise ValueError("the trained runs read different panoramas: " +
                         ", ".join(f"{run} {h}x{w}" for (h, w), run in found.items()))
    if found:
        (hw, run), = found.items()
        if resolution is not None and tuple(resolution) != hw:
            raise ValueError(f"--resolution {resolution[0]}x{resolution[1]}, but {run} was trained at {hw[0]}x{hw[1]}")
        return hw
    if resolution is not None:
        return tuple(resolution)
    default = SensorConfig()
    return default.height, default.width
