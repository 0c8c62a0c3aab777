"""The paper's learned goal-navigation baselines as Agents: the object-goal agent (after ZSON)
and the image-goal agent (after FGPrompt), and the goal images they read.

Both are the CoNav LSTM policy (conav_jax.models.policy) without the human's position, trained
in the train scenes by imitation of a geodesic planner (train/goalnav.py), and neither reads a
map. Data flow per step: observation (and, for the privileged goal inputs, the State) -> goal
input -> envs.agents.policy's policy step -> action (2,).

- Object-goal: panorama + GPS/compass + a goal category, given as a one-hot `object_probs`
  (read as a vector and, with the saliency channel, where its pixels are: oracle
  segmentation). `objectgoal-oracle` is given the episode's object-B category (privileged);
  `objectgoal-predicted` the argmax of the intention predictor's object distribution, re-read
  every step as the prediction changes.
- Image-goal: panorama + GPS/compass + a goal image: the forward quarter (RGB) of the panorama
  the env's sensor renders at a pose (`goal_image_at`). It trains on images taken at the goal's
  standing pose (`goal_view_sensor`); `imagegoal` is given, every step, the image taken at the
  human's current position facing the human's heading (`human_view_sensor`, privileged), as
  the paper gave FGPrompt an image "captured near the human". A camera there sits inside the
  humanoid's body, whose capsules it does not see from inside; its limbs show only beside and
  below the camera, outside the forward quarter (no pixel of the goal image shows the human on
  the tiny preset's val episodes at 32x128).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from brax.envs.base import State

from conav_jax import runs
from conav_jax.models.policy import PolicyConfig
from conav_jax.envs.agents.base import (
    HUMAN_VIEW_GOAL_IMAGE,
    NO_INTENTIONS,
    ORACLE_GOAL_CATEGORY,
    ORACLE_SEGMENTATION,
    PREDICTED,
    Agent,
    StateAgent,
    sensing_agent,
)
from conav_jax.envs.agents.policy import (
    acting_agent,
    check_policy_env,
    check_run_materials,
    load_policy_run,
    make_policy_step,
    policy_reads,
)
from conav_jax.envs.mjcf import UD
from conav_jax.envs.panorama import front_view

OBJECTGOAL_TITLE = "Object-goal agent"
IMAGEGOAL_TITLE = "Image-goal agent"
GOAL_IMAGE = "goal_image"  # the observation key of the goal image (conav_jax.models.policy reads it)


# -- goal images ---------------------------------------------------------------------------------


def goal_image_at(env, episode: jax.Array, pose: jax.Array, t: jax.Array) -> jax.Array:
    """`(H, W/4, 3)` RGB in [0, 1]: the forward quarter of the panorama the env's sensor renders
    from `pose` (x m, y m, yaw rad; the camera at the robot's camera height) with the human
    posed at step `t` of `episode` (env.render_at)."""
    rgbd, _ = env.render_at(episode, pose, t)
    return front_view(rgbd)[..., :3]


def _step(env, state: State) -> jax.Array:
    """The state's step within its episode, within the episode arrays."""
    t = state.pipeline_state.userdata[UD["t"]].astype(jnp.int32)
    return jnp.clip(t, 0, env.bank.max_steps - 1)


def goal_view_sensor(env) -> Callable[[State], dict]:
    """`sensor(state) -> {"goal_image": (H, W/4, 3)}`: the goal image taken at the episode's goal,
    its standing pose for activity B (facing the object), with the human posed at the state's
    step: what the image-goal policy trains on."""
    b = env.bank_view

    def sensor(state: State) -> dict:
        episode = state.info["episode"]
        pose = b.field_stand[b.scene_index[episode], b.field_b[episode]]
        return {GOAL_IMAGE: goal_image_at(env, episode, pose, _step(env, state))}

    return sensor


def human_view_sensor(env) -> Callable[[State], dict]:
    """`sensor(state) -> {"goal_image": (H, W/4, 3)}`: the goal image taken at the human's
    position at the state's step, facing the human's heading (privileged: a robot has no camera
    there). Once the human does activity B at the goal, it is the image the policy trained on."""
    b = env.bank_view

    def sensor(state: State) -> dict:
        episode, t = state.info["episode"], _step(env, state)
        pose = jnp.concatenate([b.root_xy[episode, t], b.root_yaw[episode, t][None]])
        return {GOAL_IMAGE: goal_image_at(env, episode, pose, t)}

    return sensor


# -- object-goal agent ---------------------------------------------------------------------------


class CategoryPredictor(NamedTuple):
    """An intention predictor whose object output is the one-hot of its most likely category
    (`init() -> carry`, `step(carry, obs) -> (activity_probs, object one-hot, carry)`, as
    envs.agents.policy.make_policy_step steps a predictor)."""

    init: Callable
    step: Callable
    privileged: tuple[str, ...] = ()  # the underlying predictor's


def category_predictor(intention) -> CategoryPredictor:
    """`intention` (envs.agents.predictors) naming one goal category: the argmax of its object
    distribution, every step. A prediction the predictor withholds (NaN: no valid view) stays NaN."""

    def step(carry, obs):
        activity, objects, carry = intention.step(carry, obs)
        one_hot = jax.nn.one_hot(jnp.argmax(objects), objects.shape[-1])
        return activity, jnp.where(jnp.all(jnp.isfinite(objects)), one_hot, jnp.nan), carry

    return CategoryPredictor(intention.init, step, intention.privileged)


def check_objectgoal_config(cfg: PolicyConfig, source_name: str) -> None:
    """ValueError unless `cfg` is an object-goal policy: the object input alone, no goal image."""
    if not cfg.use_object or cfg.use_activity or cfg.use_trajectory or cfg.goal_image:
        raise ValueError(f"{source_name} is not an object-goal policy (it must read the goal category as its only "
                         "intention input, and no goal image)")


def objectgoal_agent_from_params(params, cfg: PolicyConfig, env, intention=None) -> Agent | StateAgent:
    """The object-goal agent acting with these parameters: given the episode's object-B category
    (`objectgoal-oracle`, a StateAgent reading it from the episode), or with an intention
    predictor the argmax of its object distribution, re-read every step (`objectgoal-predicted`,
    observation-only)."""
    check_objectgoal_config(cfg, "the policy")
    segmentation = (ORACLE_SEGMENTATION,) if cfg.uses_saliency else ()
    if intention is not None:
        return acting_agent(params, make_policy_step(cfg, category_predictor(intention)), OBJECTGOAL_TITLE,
                            reads=policy_reads(cfg, PREDICTED, intention),
                            privileged=segmentation + tuple(p for p in intention.privileged if p not in segmentation),
                            name="objectgoal-predicted", intention_source=PREDICTED).check()
    b = env.bank_view

    def category(state: State) -> dict:  # what the policy reads as obs["object_probs"]
        return {"object_probs": jax.nn.one_hot(b.object_b[state.info["episode"]], cfg.num_objects)}

    return sensing_agent(acting_agent(params, make_policy_step(cfg), OBJECTGOAL_TITLE), category,
                         "objectgoal-oracle", OBJECTGOAL_TITLE, (ORACLE_GOAL_CATEGORY,) + segmentation,
                         policy_reads(cfg, NO_INTENTIONS))


def objectgoal_agent(env, run_dir: str | Path, oracle: bool, intention_run: str | Path | None = None,
                     trajectory_run: str | Path | None = None, ground_truth: bool = False) -> Agent | StateAgent:
    """The latest policy of a `conav train objectnav` run as `objectgoal-oracle` (`oracle`: the
    episode's category) or `objectgoal-predicted` (the intention predictor of `intention_run`
    names it; a trajectory run is not read). Errors before anything compiles: FileNotFoundError
    for a missing run or checkpoint, ValueError for a run of another kind, a predicted agent
    without a predictor run or asked for the ground truth (that is `objectgoal-oracle`), or an
    env of another resolution."""
    del trajectory_run  # the object-goal agent reads no trajectory
    name = f"objectnav run {run_dir}"
    if not oracle:
        if ground_truth:
            raise ValueError("objectgoal-predicted reads its goal category from the intention predictor; the "
                             "episode's own category is the objectgoal-oracle agent (no ground_truth)")
        if intention_run is None:
            raise ValueError("objectgoal-predicted reads its goal category from an intention predictor: pass "
                             "intention_run (a `conav train intention` run)")
        if not Path(intention_run).is_dir():
            raise ValueError(f"intention predictor run {intention_run} not found (intention_run)")
    params, cfg, config = load_policy_run(run_dir, runs.OBJECTNAV)
    check_objectgoal_config(cfg, name)
    check_policy_env(env, cfg, name, NO_INTENTIONS)
    intention = None
    if not oracle:
        from conav_jax.envs.agents.predictors import load_intention_predictor

        intention = load_intention_predictor(intention_run)
    check_run_materials(env, config, name, intention)
    return objectgoal_agent_from_params(params, cfg, env, intention)


# -- image-goal agent ----------------------------------------------------------------------------


def check_imagegoal_config(cfg: PolicyConfig, source_name: str) -> None:
    """ValueError unless `cfg` is an image-goal policy: a goal image and no intention input."""
    if not cfg.goal_image or cfg.use_activity or cfg.use_object or cfg.use_trajectory:
        raise ValueError(f"{source_name} is not an image-goal policy (it must read a goal image and no intention input)")


def imagegoal_agent_from_params(params, cfg: PolicyConfig, env) -> StateAgent:
    """The image-goal agent acting with these parameters, given each step the goal image taken
    at the human's position (`human_view_sensor`)."""
    check_imagegoal_config(cfg, "the policy")
    return sensing_agent(acting_agent(params, make_policy_step(cfg), IMAGEGOAL_TITLE), human_view_sensor(env), "imagegoal",
                         IMAGEGOAL_TITLE, (HUMAN_VIEW_GOAL_IMAGE,), policy_reads(cfg, NO_INTENTIONS))


def imagegoal_agent(env, run_dir: str | Path) -> StateAgent:
    """The latest policy of a `conav train imagenav` run as the agent `imagegoal`. Errors as
    `objectgoal_agent`, before anything compiles."""
    name = f"imagenav run {run_dir}"
    params, cfg, config = load_policy_run(run_dir, runs.IMAGENAV)
    check_imagegoal_config(cfg, name)
    check_policy_env(env, cfg, name, NO_INTENTIONS)
    check_run_materials(env, config, name)
    return imagegoal_agent_from_params(params, cfg, env)
