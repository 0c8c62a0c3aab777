"""The CoNav agent from a `conav train policy` run: checkpoint -> LSTM policy -> envs Agent.

Its intention inputs are the predictors' (train.intention / train.trajectory runs) when their
run directories are given, else the env's ground truth (obs activity_probs, object_probs,
future_traj, as in training); inputs the run's ablation drops are never read or predicted.
"""

from __future__ import annotations

from pathlib import Path

from envs.conav_env import ConavEnv
from envs.rollout import Agent


def policy_agent(
    env: ConavEnv,
    run_dir: str | Path,
    intention_run: str | Path | None = None,
    trajectory_run: str | Path | None = None,
) -> Agent:
    """The latest policy of `run_dir` as an envs.rollout.Agent named "conav" (carry: the LSTM
    state and the intention predictor's). FileNotFoundError for a missing run or checkpoint,
    ValueError for a run of another kind or an env the policy cannot read (resolution,
    missing ground-truth intentions); all before anything is compiled."""
    from train.imitation import check_policy_env, policy_agent_from_params
    from train.policy import load_policy_run

    params, cfg, _ = load_policy_run(run_dir)
    intention = trajectory = None
    if intention_run is not None and (cfg.use_activity or cfg.use_object):
        from train.intention import load_intention_predictor

        intention = load_intention_predictor(intention_run)
    if trajectory_run is not None and cfg.use_trajectory:
        from train.trajectory import load_trajectory_predictor

        trajectory = load_trajectory_predictor(trajectory_run)
    check_policy_env(env, cfg, f"policy run {run_dir}", intention, trajectory)
    return policy_agent_from_params(params, cfg, intention, trajectory, name="conav")
