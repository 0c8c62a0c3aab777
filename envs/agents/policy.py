"""The CoNav LSTM policy acting in the env, and the CoNav (and PPO) agent of a trained run.

obs -> `predict` (the policy's intention inputs: the predictors' outputs, or the env's ground
truth) -> `act` (conav_jax.models.policy) -> action (2,). Where the intention inputs come from
is decided once, by `intention_source`, and recorded on the agent: all of them from predictors
(`predicted`), all from the env (`ground_truth`, privileged: training data, upper bounds), or
none (the ablation reads none). A policy never mixes the two, and an agent built for
evaluation never reads the ground truth unless it was asked to.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from conav_jax import runs
from conav_jax.models import policy
from conav_jax.models.policy import PolicyConfig
from conav_jax.nn.lstm import LSTMState
from conav_jax.envs.agents.base import (
    FUTURE_HUMAN_POSITIONS,
    GROUND_TRUTH,
    GROUND_TRUTH_INTENTIONS,
    NO_INTENTIONS,
    ORACLE_SEGMENTATION,
    PREDICTED,
    Agent,
)
from conav_jax.envs.agents.predictors import load_intention_predictor, load_trajectory_predictor
from conav_jax.envs.config import check_materials, materials_of_run

INTENTION_KEYS = ("activity_probs", "object_probs", "future_traj")
# The arguments that give each predictor run, and ask for ground truth, for error messages
# (the command line names its own flags for them).
PREDICTOR_ARGS = {"intention": "intention_run", "trajectory": "trajectory_run"}
GROUND_TRUTH_ARG = "ground_truth=True"


class PolicyCarry(NamedTuple):
    """The acting policy's memory: its LSTM state ((hidden,) each), the intention predictor's
    carry (None without one) and `predicted`, the predictors' latest outputs the policy read,
    by observation key (activity_probs / object_probs / future_traj; {} without predictors),
    which the viewer shows."""

    lstm: LSTMState
    intention: Any
    predicted: dict


class PolicyStep(NamedTuple):
    """`init() -> PolicyCarry`; `step(params, obs, carry) -> (action (2,), carry)` for one env,
    which is `act(params, *predict(obs, carry))`: `predict` gathers the policy's inputs (with
    the predictors' outputs where `source` is "predicted"), `act` runs the network."""

    init: Callable[[], PolicyCarry]
    step: Callable[[dict, dict, PolicyCarry], tuple[jax.Array, PolicyCarry]]
    predict: Callable[[dict, PolicyCarry], tuple[dict, PolicyCarry]]
    act: Callable[[dict, dict, PolicyCarry], tuple[jax.Array, PolicyCarry]]
    source: str  # envs.agents.base intention source: predicted / ground_truth / none


def policy_inputs(cfg: PolicyConfig) -> tuple[str, ...]:
    """The observation keys the policy reads: the panorama, pose, human position (unless
    switched off), the intention inputs its ablation keeps, the segmentation its saliency
    channel reads and the goal image if it has one."""
    on = (cfg.use_activity, cfg.use_object, cfg.use_trajectory)
    return (("rgbd", "gps_compass") + (("human_pos",) if cfg.use_human_pos else ())
            + tuple(k for k, use in zip(INTENTION_KEYS, on) if use) + (("segmentation",) if cfg.uses_saliency else ())
            + (("goal_image",) if cfg.goal_image else ()))


def policy_reads(cfg: PolicyConfig, source: str, intention=None) -> tuple[str, ...]:
    """The observation keys the policy's stepping reads when its intentions come from `source`:
    its inputs (the intention ones only from the env's ground truth; no goal image, which its
    agent supplies) and what its predictors read (the segmentation for an `intention` predictor
    that keeps the objects seen)."""
    keys = [k for k in policy_inputs(cfg) if k != "goal_image" and (k not in INTENTION_KEYS or source == GROUND_TRUTH)]
    if source == PREDICTED:
        keys += (["rgbd", "human_pos"] if cfg.use_activity or cfg.use_object else []) + (
            ["human_history"] if cfg.use_trajectory else [])
        if ORACLE_SEGMENTATION in getattr(intention, "privileged", ()):
            keys.append("segmentation")
    return tuple(dict.fromkeys(keys))


def needed_predictors(cfg: PolicyConfig) -> tuple[str, ...]:
    """The predictors ("intention", "trajectory") the policy's intention inputs need."""
    return (("intention",) if cfg.use_activity or cfg.use_object else ()) + (("trajectory",) if cfg.use_trajectory else ())


def intention_source(cfg: PolicyConfig, intention=None, trajectory=None) -> str:
    """Where the policy's intention inputs come from given these predictors: "none" when it
    reads none, "predicted" when every one it reads has its predictor, "ground_truth" when none
    is given. ValueError for a mix, naming the predictor that is missing: a policy never reads
    ground truth for one input and predictions for another."""
    needed = needed_predictors(cfg)
    if not needed:
        return NO_INTENTIONS
    given = {"intention": intention is not None, "trajectory": trajectory is not None}
    if not any(given[k] for k in needed):
        return GROUND_TRUTH
    missing = [k for k in needed if not given[k]]
    if missing:
        args = " and ".join(PREDICTOR_ARGS[k] for k in missing)
        raise ValueError(f"the policy reads {' and '.join(needed)} predictions but no {' or '.join(missing)} "
                         f"predictor is given ({args}); it never mixes predictions with ground truth")
    return PREDICTED


def make_policy_step(cfg: PolicyConfig, intention=None, trajectory=None, recurrent: bool = True) -> PolicyStep:
    """The LSTM policy acting for one env. With predictors (envs.agents.predictors) its
    intention inputs are their outputs: `intention` replaces activity/object probabilities from
    the front view, `trajectory` the future trajectory from the human's history; without any,
    they are the env's ground-truth observations (how the paper trains). `intention_source`
    decides which, and refuses a mix. Inputs the ablation drops are never computed. With
    `recurrent=False` the LSTM carry stays at zero (PPO's feed-forward policies)."""
    source = intention_source(cfg, intention, trajectory)
    use_intention = source == PREDICTED and (cfg.use_activity or cfg.use_object)
    use_trajectory = source == PREDICTED and cfg.use_trajectory
    keys = policy_inputs(cfg)
    predicted_keys = (("activity_probs", "object_probs") if use_intention else ()) + (
        ("future_traj",) if use_trajectory else ())

    def init() -> PolicyCarry:
        lstm = jax.tree.map(lambda x: x[0], policy.initial_carry(cfg, 1))
        shapes = {"activity_probs": (cfg.num_activities,), "object_probs": (cfg.num_objects,),
                  "future_traj": (cfg.horizon, 2)}
        predicted = {k: jnp.zeros(shapes[k], jnp.float32) for k in predicted_keys}
        return PolicyCarry(lstm, intention.init() if use_intention else None, predicted)

    def predict(obs: dict, carry: PolicyCarry) -> tuple[dict, PolicyCarry]:
        inputs = {k: obs[k] for k in keys if k not in predicted_keys}
        icarry = carry.intention
        if use_intention:
            activity, obj, icarry = intention.step(icarry, obs)
            inputs.update(activity_probs=activity, object_probs=obj)
        if use_trajectory:
            inputs["future_traj"] = trajectory.predict(obs["human_history"])
        predicted = {k: inputs[k].astype(jnp.float32).reshape(carry.predicted[k].shape) for k in predicted_keys}
        return inputs, carry._replace(intention=icarry, predicted=predicted)

    def act(params, inputs: dict, carry: PolicyCarry):
        batched = {k: inputs[k][None] for k in keys}
        lstm = jax.tree.map(lambda x: x[None], carry.lstm)
        action, _, new = policy.apply(params, cfg, batched, lstm)
        if not recurrent:
            return action[0], carry
        return action[0], carry._replace(lstm=jax.tree.map(lambda x: x[0], new))

    def step(params, obs: dict, carry: PolicyCarry):
        with jax.named_scope("predictors"):
            inputs, carry = predict(obs, carry)
        with jax.named_scope("policy"):
            return act(params, inputs, carry)

    return PolicyStep(init, step, predict, act, source)


def check_policy_env(env, cfg: PolicyConfig, source_name: str, intention_source_: str) -> None:
    """ValueError unless `env` renders the policy's resolution."""
    hw = env.config.sensor.resolution
    if hw != tuple(cfg.resolution):
        h, w = cfg.resolution
        raise ValueError(
            f"{source_name} was trained on {h}x{w} panoramas but the env renders {hw[0]}x{hw[1]}; "
            f"build the env with SensorConfig(resolution=({h}, {w}))"
        )


def check_run_materials(env, config: dict, source_name: str, intention=None) -> None:
    """ValueError, naming both, unless `env` renders the materials (SensorConfig.materials) the
    run of checkpoint config `config` and its intention predictor, if any, were trained on (a
    predictor that records no FrameSpec, such as one written by hand, is taken at its word)."""
    check_materials(materials_of_run(config), env.config.sensor, source_name)
    trained = getattr(getattr(intention, "spec", None), "materials", None)
    if trained is not None:
        check_materials(trained, env.config.sensor, f"the intention predictor of {source_name}")


def privileged_inputs(cfg: PolicyConfig, source: str, intention=None) -> tuple[str, ...]:
    """The privileged inputs a policy with this config reads when its intentions come from
    `source`, with those of its intention predictor (`intention`) where it reads one."""
    out = []
    if source == GROUND_TRUTH:
        out.append(GROUND_TRUTH_INTENTIONS)
        if cfg.use_trajectory:
            out.append(FUTURE_HUMAN_POSITIONS)  # the true future trajectory is where the human will be
    if cfg.use_object and cfg.object_saliency:
        out.append(ORACLE_SEGMENTATION)  # each pixel's category: the observation's segmentation
    if intention is not None and source == PREDICTED and (cfg.use_activity or cfg.use_object):
        out += [p for p in intention.privileged if p not in out]
    return tuple(out)


def policy_agent_from_params(
    params, cfg: PolicyConfig, intention=None, trajectory=None, name: str = "conav", title: str = "CoNav Agent",
    recurrent: bool = True,
) -> Agent:
    """An observation-only Agent acting with these policy parameters (closed over), the keys it
    reads, its intention source and privileged inputs recorded."""
    pol = make_policy_step(cfg, intention, trajectory, recurrent)
    if pol.source == NO_INTENTIONS:
        title = f"{title}, no intention inputs"
    return acting_agent(params, pol, title, reads=policy_reads(cfg, pol.source, intention),
                        privileged=privileged_inputs(cfg, pol.source, intention), name=name,
                        intention_source=pol.source).check()


def acting_agent(params, pol: PolicyStep, title: str, **declared) -> Agent:
    """The observation-only Agent stepping policy `pol` (make_policy_step) with `params`
    (closed over); `declared`: its other Agent fields (reads, privileged, name, ...)."""

    def act(carry, obs, key):
        action, carry = pol.step(params, obs, carry)
        return carry, action

    return Agent(title, lambda key, obs: pol.init(), act, **declared)


# -- agents from runs ----------------------------------------------------------------------------


def policy_config_from_dict(d: dict) -> PolicyConfig:
    """PolicyConfig from a checkpoint's JSON "model" (lists back to tuples; keys renamed since
    the run was written read under today's names, runs.upgrade_config)."""
    names = {f.name for f in dataclasses.fields(PolicyConfig)}
    d = runs.upgrade_config({"kind": runs.POLICY, "model": d})["model"]
    d = {"object_saliency": False, **d}  # checkpoints from before the saliency channel had none
    if set(d) - names:
        raise ValueError(f"checkpoint model config has unknown PolicyConfig fields {sorted(set(d) - names)}")
    return PolicyConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def load_policy_run(run_dir: str | Path, kind: str = runs.POLICY):
    """(params, PolicyConfig, config dict) of the latest checkpoint of a policy (or PPO) run.
    FileNotFoundError for a missing run or checkpoint, ValueError for another kind of run or
    params that do not fit the saved PolicyConfig."""
    ckpt = runs.load_run(run_dir, kind)
    if "model" not in ckpt.config:
        raise ValueError(f"{run_dir}: {kind} checkpoint without a model config")
    cfg = policy_config_from_dict(ckpt.config["model"])
    template = jax.eval_shape(lambda k: policy.init(k, cfg), jax.random.PRNGKey(0))
    params = runs.load_run(run_dir, kind, params_like=template).params
    return params, cfg, ckpt.config


def predictor_runs(cfg: PolicyConfig, source_name: str, named: dict, intention_run=None, trajectory_run=None,
                   ground_truth: bool = False) -> tuple[str | None, str | None]:
    """The (intention, trajectory) predictor runs an evaluated policy reads: those given, else
    those `named` ({"intention_run": ..., "trajectory_run": ...}, from the policy run's config),
    only for the inputs the policy reads; (None, None) with `ground_truth`. ValueError, before
    anything is built, when a run the policy needs is missing and ground truth was not asked for
    (the message names the `intention_run` / `trajectory_run` and `ground_truth` arguments), when a named
    run directory does not exist, or when ground truth is asked for beside predictor runs."""
    if ground_truth:
        if intention_run is not None or trajectory_run is not None:
            raise ValueError("ground_truth excludes intention_run / trajectory_run")
        return None, None
    out = {}
    for kind, given in (("intention", intention_run), ("trajectory", trajectory_run)):
        run = given if given is not None else named.get(f"{kind}_run")
        if kind not in needed_predictors(cfg):
            out[kind] = None
            continue
        if run is None:
            raise ValueError(
                f"{source_name} reads {kind} predictions and no {kind} predictor run is given: pass "
                f"{PREDICTOR_ARGS[kind]} (or {GROUND_TRUTH_ARG} for the privileged upper bound)")
        if not Path(run).is_dir():
            origin = "given" if given is not None else f"named by {source_name}"
            raise ValueError(f"{kind} predictor run {run} ({origin}) not found; pass {PREDICTOR_ARGS[kind]} "
                             f"or {GROUND_TRUTH_ARG}")
        out[kind] = str(run)
    return out["intention"], out["trajectory"]


def load_predictors(intention_run, trajectory_run):
    """(IntentionPredictor | None, TrajectoryPredictor | None) of the given runs."""
    return (None if intention_run is None else load_intention_predictor(intention_run),
            None if trajectory_run is None else load_trajectory_predictor(trajectory_run))


def policy_agent(env, run_dir: str | Path, intention_run: str | Path | None = None,
                 trajectory_run: str | Path | None = None, ground_truth: bool = False) -> Agent:
    """The latest policy of a `conav train policy` run as the Agent "conav". Its intention
    inputs are the predictors' outputs (the runs given, else those the policy run names), or the
    env's ground truth only with `ground_truth=True` (privileged, recorded as such). Errors
    before anything is compiled: FileNotFoundError for a missing run or checkpoint, ValueError
    for a run of another kind, missing predictor runs, or an env the policy cannot read."""
    params, cfg, config = load_policy_run(run_dir)
    name = f"policy run {run_dir}"
    intention, trajectory = load_predictors(
        *predictor_runs(cfg, name, config, intention_run, trajectory_run, ground_truth))
    agent = policy_agent_from_params(params, cfg, intention, trajectory, name="conav")
    check_policy_env(env, cfg, name, agent.intention_source)
    check_run_materials(env, config, name, intention)
    return agent
