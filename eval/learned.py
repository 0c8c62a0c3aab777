"""The CoNav agent from a `conav train policy` run: checkpoint -> LSTM policy -> envs Agent.

Its intention inputs are predicted, as in the paper's evaluation: by the predictor runs given,
else by the ones the policy run names in its config (`conav train policy --intention/--trajectory`).
The env's ground truth (obs activity_probs, object_probs, future_traj, what training uses) feeds
an input only where no predictor exists or when asked for (`ground_truth=True`: an upper bound,
privileged). Inputs the run's ablation drops are never read or predicted.
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
    ground_truth: bool = False,
) -> Agent:
    """The latest policy of `run_dir` as an envs.rollout.Agent named "conav" (carry: the LSTM
    state and the intention predictor's). FileNotFoundError for a missing run or checkpoint,
    ValueError for a run of another kind or an env the policy cannot read (resolution,
    missing ground-truth intentions, a predictor run the policy names that no longer exists);
    all before anything is compiled."""
    from train.imitation import check_policy_env, policy_agent_from_params
    from train.policy import load_policy_run

    params, cfg, config = load_policy_run(run_dir)
    intention_run, trajectory_run = predictor_runs(run_dir, config, intention_run, trajectory_run, ground_truth)
    intention = trajectory = None
    if intention_run is not None and (cfg.use_activity or cfg.use_object):
        from train.intention import load_intention_predictor

        intention = load_intention_predictor(intention_run)
    if trajectory_run is not None and cfg.use_trajectory:
        from train.trajectory import load_trajectory_predictor

        trajectory = load_trajectory_predictor(trajectory_run)
    check_policy_env(env, cfg, f"policy run {run_dir}", intention, trajectory)
    return policy_agent_from_params(params, cfg, intention, trajectory, name="conav")


def predictor_runs(run_dir, config: dict, intention_run, trajectory_run, ground_truth: bool):
    """The (intention, trajectory) predictor runs a policy is evaluated with: the given ones,
    else the runs its training config names, none with `ground_truth`. ValueError if a named
    run directory is missing."""
    if ground_truth:
        if intention_run is not None or trajectory_run is not None:
            raise ValueError("ground-truth intentions exclude --intention-checkpoint / --trajectory-checkpoint")
        return None, None
    out = []
    for key, given in (("intention_run", intention_run), ("trajectory_run", trajectory_run)):
        run = given if given is not None else config.get(key)
        if run is not None and not Path(run).is_dir():
            source = "given" if given is not None else f"named by policy run {run_dir}"
            raise ValueError(f"{key.replace('_run', '')} predictor run {run} ({source}) not found; pass "
                             f"--{key.replace('_run', '')}-checkpoint RUN or --ground-truth-intentions")
        out.append(run)
    return tuple(out)
