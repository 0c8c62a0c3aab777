"""`conav train objectnav` / `conav train imagenav`: the paper's learned goal-navigation
baselines (object-goal agent after ZSON, image-goal agent after FGPrompt), by imitation of a
geodesic planner: behaviour cloning, then DAgger rounds (train/policy.py's rounds, unchanged).

train env (train split) -> episodes run to the first reach, the teacher acting (BC) or
labelling the policy's own states (DAgger) -> windows -> L2 imitation loss on train.loop ->
validation on the validation env (minival; `train_*_from_data` builds both from a dataset
directory) -> a run of kind "objectnav" / "imagenav" that envs.agents.goalnav loads.
The object-goal agent also trains live (`train_objectnav_live`: train.live's loop, every train
episode, nothing stored, the planner in the expert's place), as the CoNav rows do; the
image-goal agent's goal image is rendered only by the offline trainer.

No human task: the teachers lead to the goal object's standing point and ignore the human, and
the policies read no human position (PolicyConfig.use_human_pos off).
- Object-goal: the teacher is the object-goal planner descending the field of the nearest
  instance of the episode's object-B category, re-picked from wherever the robot is (so DAgger's
  labels answer from the states the policy reaches). The policy reads the category as the env's
  ground-truth one-hot `object_probs` (ObjectNav trains on its true goal), as a vector and, with
  the saliency channel (default on), as the map of that category's pixels (oracle segmentation).
- Image-goal: the teacher is the geodesic planner to the goal itself; the policy reads the goal
  image taken at the goal's standing pose (envs.agents.goalnav.goal_view_sensor), rendered each
  step with the human where they are, and validates on it (at evaluation the image comes from
  the human's position instead).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from conav_jax import runs
from conav_jax.models.policy import PolicyConfig, ablation_config
from conav_jax.envs import ConavEnv
from conav_jax.envs.agents.baselines import BaselineConfig, goal_planner_agent, objectgoal_planner_agent
from conav_jax.envs.agents.goalnav import check_imagegoal_config, check_objectgoal_config, goal_view_sensor
from conav_jax.train.live import LiveConfig, LiveResult, train_live, train_live_from_data
from conav_jax.train.loop import TrainConfig
from conav_jax.train.policy import (ImitationConfig, ImitationTask, PolicyResult, train_policy,
                                    train_policy_from_data)


def objectnav_model(resolution: tuple[int, int], object_saliency: bool = True, base: PolicyConfig = PolicyConfig()) -> PolicyConfig:
    """`base` as the object-goal policy: the goal category its only intention input, no human
    position, panoramas of `resolution`."""
    return dataclasses.replace(ablation_config(base, "object"), resolution=tuple(resolution),
                               object_saliency=object_saliency, use_human_pos=False)


def imagenav_model(resolution: tuple[int, int], base: PolicyConfig = PolicyConfig()) -> PolicyConfig:
    """`base` as the image-goal policy: a goal image, no intention input, no human position."""
    return dataclasses.replace(ablation_config(base, "none"), resolution=tuple(resolution), use_human_pos=False,
                               goal_image=True)


@dataclasses.dataclass(frozen=True)
class PlannerTeacher:
    """`env -> the planner agent` of a task: the object-goal planner (`object_goal`, re-picking
    the nearest instance every step) or the geodesic planner to the goal. Equal and hashed by its
    settings, so two tasks of one configuration share the programs compiled for either
    (train.live caches its iteration by teacher)."""

    object_goal: bool
    planner: BaselineConfig = BaselineConfig()

    def __call__(self, env: ConavEnv):
        if self.object_goal:
            return objectgoal_planner_agent(env, self.planner, replan=True)
        return goal_planner_agent(env, self.planner)


def objectnav_task(planner: BaselineConfig = BaselineConfig()) -> ImitationTask:
    """The object-goal planner (re-picking the nearest instance every step) as the teacher."""
    return ImitationTask(runs.OBJECTNAV, PlannerTeacher(True, planner), None,
                         {"planner": "objectgoal-planner", "replan": True, "baseline": dataclasses.asdict(planner)})


def imagenav_task(planner: BaselineConfig = BaselineConfig()) -> ImitationTask:
    """The geodesic planner to the goal as the teacher, the goal-pose image as the goal input."""
    return ImitationTask(runs.IMAGENAV, PlannerTeacher(False, planner), goal_view_sensor,
                         {"planner": "goal-planner", "goal_image": "goal standing pose, forward quarter, RGB",
                          "baseline": dataclasses.asdict(planner)})


def check_objectnav_model(model: PolicyConfig) -> None:
    """ValueError unless `model` is an object-goal policy (see `objectnav_model`)."""
    check_objectgoal_config(model, "the object-goal model")
    if model.use_human_pos:
        raise ValueError("the object-goal model reads no human position (PolicyConfig.use_human_pos=False)")


def check_imagenav_model(model: PolicyConfig) -> None:
    """ValueError unless `model` is an image-goal policy (see `imagenav_model`)."""
    check_imagegoal_config(model, "the image-goal model")
    if model.use_human_pos:
        raise ValueError("the image-goal model reads no human position (PolicyConfig.use_human_pos=False)")


def train_objectnav(train_env: ConavEnv, val_env: ConavEnv, run_dir: str | Path, cfg: TrainConfig, model: PolicyConfig,
                    imitation: ImitationConfig = ImitationConfig(), planner: BaselineConfig = BaselineConfig(),
                    **kwargs) -> PolicyResult:
    """Train the object-goal policy `model` (see `objectnav_model`) on `train_env` into `run_dir`,
    validating on `val_env` (the envs as train.policy.train_policy takes them), resuming a run of
    the same config; `kwargs` as train_policy's (progress, mesh, remat...)."""
    check_objectnav_model(model)
    return train_policy(train_env, val_env, run_dir, cfg, model, imitation, task=objectnav_task(planner), **kwargs)


def train_objectnav_live(env: ConavEnv, model: PolicyConfig, live: LiveConfig, out_dir: str | Path,
                         planner: BaselineConfig = BaselineConfig(), **kwargs) -> LiveResult:
    """Train the object-goal policy `model` (see `objectnav_model`; give large panoramas
    `visual_norm=True`, as train.live.DEFAULT_POLICY) by live imitation of the replanning
    object-goal planner on `env`'s train split (end_at_reach, as train.live.train_live takes
    it) into the objectnav run `out_dir`; `kwargs` as train_live's (progress, compiler_options)."""
    check_objectnav_model(model)
    return train_live(env, model, live, out_dir, task=objectnav_task(planner), **kwargs)


def train_objectnav_live_from_data(data_dir: str | Path, out_dir: str | Path, model: PolicyConfig,
                                   live: LiveConfig = LiveConfig(), planner: BaselineConfig = BaselineConfig(),
                                   **kwargs) -> LiveResult:
    """`train_objectnav_live` on the train split of the dataset `data_dir`, its env as
    train.live.train_live_from_data builds it (the model checked before the dataset is loaded)."""
    check_objectnav_model(model)
    return train_live_from_data(data_dir, out_dir, model, live, task=objectnav_task(planner), **kwargs)


def train_imagenav(train_env: ConavEnv, val_env: ConavEnv, run_dir: str | Path, cfg: TrainConfig, model: PolicyConfig,
                   imitation: ImitationConfig = ImitationConfig(), planner: BaselineConfig = BaselineConfig(),
                   **kwargs) -> PolicyResult:
    """Train the image-goal policy `model` (see `imagenav_model`) on `train_env`, as `train_objectnav`."""
    check_imagenav_model(model)
    return train_policy(train_env, val_env, run_dir, cfg, model, imitation, task=imagenav_task(planner), **kwargs)


def train_objectnav_from_data(data_dir: str | Path, run_dir: str | Path, cfg: TrainConfig, model: PolicyConfig,
                              imitation: ImitationConfig = ImitationConfig(),
                              planner: BaselineConfig = BaselineConfig(), **kwargs) -> PolicyResult:
    """`train_objectnav` on the dataset `data_dir`, its envs as train.policy.imitation_envs builds
    them (the model checked before the dataset is loaded)."""
    check_objectnav_model(model)
    return train_policy_from_data(data_dir, run_dir, cfg, model, imitation, task=objectnav_task(planner), **kwargs)


def train_imagenav_from_data(data_dir: str | Path, run_dir: str | Path, cfg: TrainConfig, model: PolicyConfig,
                             imitation: ImitationConfig = ImitationConfig(),
                             planner: BaselineConfig = BaselineConfig(), **kwargs) -> PolicyResult:
    """`train_imagenav` on the dataset `data_dir`, as `train_objectnav_from_data`."""
    check_imagenav_model(model)
    return train_policy_from_data(data_dir, run_dir, cfg, model, imitation, task=imagenav_task(planner), **kwargs)
