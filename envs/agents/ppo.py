"""The agent of a `conav train rl` (PPO) run: its policy's mean action, deterministic.

The PPO policy is the CoNav policy network (conav_jax.models.policy) with a value head, so it
acts through the same stepping as the imitation policy (envs.agents.policy), intention inputs
included: the predictors' outputs when predictor runs are given, the env's ground truth only
when asked for (privileged, recorded as such). Feed-forward runs keep a zero LSTM carry.
"""

from __future__ import annotations

from pathlib import Path

from conav_jax import runs
from conav_jax.envs.agents.base import Agent
from conav_jax.envs.agents.policy import (
    check_policy_env,
    load_policy_run,
    load_predictors,
    policy_agent_from_params,
    predictor_runs,
)


def ppo_agent(env, run_dir: str | Path, intention_run: str | Path | None = None,
              trajectory_run: str | Path | None = None, ground_truth: bool = False) -> Agent:
    """The latest checkpoint of a `conav train rl` run as the Agent "ppo". FileNotFoundError for
    a missing run or checkpoint, ValueError for another kind of run, missing predictor runs
    (PPO runs name none: pass them, or ask for ground truth) or an env it cannot read; all
    before any compile."""
    params, cfg, config = load_policy_run(run_dir, runs.PPO)
    if "ppo" not in config or "recurrent" not in config["ppo"]:
        raise ValueError(f"{run_dir}: PPO checkpoint without its ppo config")
    name = f"PPO run {run_dir}"
    intention, trajectory = load_predictors(*predictor_runs(cfg, name, {}, intention_run, trajectory_run, ground_truth))
    agent = policy_agent_from_params(params, cfg, intention, trajectory, name="ppo", title="PPO Agent",
                                     recurrent=bool(config["ppo"]["recurrent"]))
    check_policy_env(env, cfg, name, agent.intention_source)
    return agent
