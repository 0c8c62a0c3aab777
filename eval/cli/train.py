"""`conav train MODEL`: the intention and trajectory predictors, the CoNav policy (imitation),
the learned object-goal and image-goal baselines, and PPO; flags -> configs ->
conav_jax.train.* -> a summary of the run's validation.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from conav_jax.eval.cli.args import (
    add_fields,
    config_from_args,
    devices_arg,
    mesh,
    parse_resolution,
    resolution_arg,
    train_args,
    train_config,
    field_docs,
)

def add(sub) -> None:
    from conav_jax.models.perceiver import PerceiverConfig
    from conav_jax.models.policy import ABLATIONS, PolicyConfig
    from conav_jax.models.trajectory import TrajectoryConfig
    from conav_jax.train.intention import INTENTION_TRAIN, IntentionDataConfig
    from conav_jax.train.policy import POLICY_TRAIN, TRAIN_INTENTIONS, ImitationConfig
    from conav_jax.train.trajectory import TRAJECTORY_TRAIN
    from conav_jax.train.ppo import PPOConfig

    train = sub.add_parser("train", help="train the intention / trajectory predictors, the policy, PPO")
    models = train.add_subparsers(dest="model", metavar="MODEL", required=True)

    p = models.add_parser("intention", help="train the intention (activity/object B) Perceiver")
    train_args(p, INTENTION_TRAIN)
    dd, dm = IntentionDataConfig(), PerceiverConfig()
    resolution_arg(p, "the frames come from; agents acting with the run must render it")
    p.add_argument("--image", type=parse_resolution, default=None, metavar="HxW",
                   help="Perceiver frame HxW: the crop around the human, in panorama pixels (front view: resized "
                   f"to it; default {dm.image_hw[0]}x{dm.image_hw[1]}, or the --resolution height rounded down to a "
                   "multiple of 8 where that is smaller)")
    p.add_argument("--view", choices=("human", "front"), default=dd.view, help=field_docs(IntentionDataConfig)["view"])
    add_fields(p, IntentionDataConfig, ("frames", "viewpoints", "mirror", "recolour"))
    add_fields(p, PerceiverConfig, ("dim", "num_latents", "num_blocks", "activity_a_head", "graph_mix", "seen_objects"),
               flags={"num_latents": "--latents", "num_blocks": "--blocks"}, num_latents="latent array length")
    p.add_argument("--val-split", default="minival",
                   help="split validated on (default minival: hyper-parameters are chosen there, never on the "
                   "reported val split)")
    p.set_defaults(func=_run_train_intention)

    p = models.add_parser("trajectory", help="train the trajectory (short-term intention) predictor")
    train_args(p, TRAJECTORY_TRAIN)
    p.add_argument("--hidden", type=int, default=TrajectoryConfig.hidden, help="LSTM/MLP width")
    p.set_defaults(func=_run_train_trajectory)

    p = models.add_parser("policy", help="imitation-train the CoNav policy from the expert (BC, then DAgger)")
    train_args(p, POLICY_TRAIN)
    d = ImitationConfig()
    p.add_argument("--intention", default=None, metavar="RUN",
                   help="intention run (conav train intention): validate with its predictions")
    p.add_argument("--trajectory", default=None, metavar="RUN",
                   help="trajectory run (conav train trajectory): validate with its predictions")
    p.add_argument("--ablation", choices=sorted(ABLATIONS), default="all", help="intention inputs kept (Table 3 row; default all)")
    _add_imitation_args(p, "expert")
    p.add_argument("--remat", action="store_true",
                   help="recompute the CNN per window step in the backward pass: less memory (large float32 "
                   "panoramas at large batches need it), more compute: slower at small panoramas, faster at "
                   "large ones with --conv-dtype bfloat16 (BENCHMARKS.md)")
    _add_network_args(p)
    p.add_argument("--train-intentions", choices=TRAIN_INTENTIONS, default=d.train_intentions,
                   help="intention inputs in the training data: ground truth (the paper) or the predictor runs' outputs")
    p.add_argument("--object-saliency", action=argparse.BooleanOptionalAction, default=PolicyConfig.object_saliency,
                   help="with the object input, also read it as a saliency map over the panorama (default: on; "
                   "--no-object-saliency reads the object distribution as a vector only)")
    p.add_argument("--share-expert", action=argparse.BooleanOptionalAction, default=True,
                   help="read the expert's ceiling and round-0 recording from DATA/expert_cache when an earlier run "
                   "with the same data, resolution, episodes, batching, windows and inputs made them, else write them "
                   "there (the expert ignores the seed: the same bytes; default: on)")
    p.set_defaults(func=_run_train_policy)

    _add_train_live(models)

    d = PPOConfig()
    p = models.add_parser("rl", help="train the policy with PPO in the simulator")
    p.add_argument("--data", required=True, help="dataset dir written by `conav generate`")
    p.add_argument("--out", required=True, help="new run dir: log.jsonl and checkpoints")
    p.add_argument("--init-from", default=None, metavar="POLICY_RUN",
                   help="start from an imitation policy run (its network, weights and value head)")
    add_fields(p, PPOConfig, ("num_envs", "total_env_steps", "rollout_steps", "lr", "reset_every"),
               flags={"total_env_steps": "--steps"})
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--recurrent", dest="recurrent", action="store_true", default=d.recurrent,
                      help="LSTM carry through time (default)")
    mode.add_argument("--feedforward", dest="recurrent", action="store_false", help="zero LSTM carry every step")
    resolution_arg(p, "of a new network (with --init-from: the imitation run's)")
    p.add_argument("--hidden", type=int, default=None,
                   help=f"LSTM width of a new network (default {PolicyConfig.hidden}; not with --init-from)")
    add_fields(p, PPOConfig, ("seed", "eval_every", "eval_split", "ckpt_every"))
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    devices_arg(p)
    p.set_defaults(func=_run_train_rl)
    _add_train_goalnav(models)


# The goal-navigation baselines `conav train live --baseline` trains (train.goalnav); the
# image-goal agent's goal image is rendered only by its offline trainer.
LIVE_BASELINES = ("objectnav",)


def _add_train_live(models) -> None:
    from conav_jax.models.policy import ABLATIONS, PolicyConfig
    from conav_jax.train.live import DEFAULT_POLICY, LiveConfig

    p = models.add_parser("live", help="imitation-train the CoNav policy from the live simulator: N lanes step T "
                          "control steps, the expert labels every visited state, one update per window, every "
                          "train episode in turn, nothing stored")
    p.add_argument("--data", required=True, help="dataset dir written by `conav generate`")
    p.add_argument("--out", required=True, help="run dir (a policy run: `conav eval --agent conav --checkpoint RUN`)")
    source = p.add_mutually_exclusive_group()  # one of them unless the ablation reads no intention (none)
    source.add_argument("--intention", default=None, metavar="RUN", help="intention run the learner reads")
    source.add_argument("--ground-truth-intentions", action="store_true",
                        help="the learner reads the env's ground-truth intentions (a privileged run)")
    p.add_argument("--trajectory", default=None, metavar="RUN", help="trajectory run (with --intention)")
    p.add_argument("--ablation", choices=sorted(ABLATIONS), default="all", help="intention inputs kept (Table 3 row)")
    p.add_argument("--baseline", choices=LIVE_BASELINES, default=None,
                   help="train a goal-navigation baseline in place of the CoNav policy: objectnav, the object-goal "
                   "agent imitating the replanning object-goal planner (an objectnav run: `conav eval --agent "
                   "objectgoal-oracle|objectgoal-predicted --checkpoint RUN`); no --ablation or intention flags")
    p.add_argument("--object-saliency", action=argparse.BooleanOptionalAction, default=PolicyConfig.object_saliency,
                   help="with the object input (the CoNav rows that read it, --baseline objectnav), also read it as a "
                   "saliency map over the panorama (oracle segmentation, recorded as privileged; default: on)")
    resolution_arg(p, "of the policy's panorama")
    _add_network_args(p, visual_norm=DEFAULT_POLICY.visual_norm)
    add_fields(p, LiveConfig)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run_train_live)


def _run_train_live(args: argparse.Namespace) -> int:
    from conav_jax.envs.agents.policy import needed_predictors
    from conav_jax.models.policy import ablation_config
    from conav_jax.envs.agents.registry import run_resolution
    from conav_jax.train.live import LiveConfig, train_live_from_data

    if args.baseline is not None:
        return _run_train_live_baseline(args)
    if args.intention is not None and args.trajectory is None and args.ablation == "all":
        raise ValueError("--ablation all reads the trajectory predictor: give --trajectory RUN")
    base = network_base(args, run_resolution([], args.resolution))
    model = ablation_config(dataclasses.replace(base, object_saliency=args.object_saliency), args.ablation)
    if needed_predictors(model) and args.intention is None and not args.ground_truth_intentions:
        raise ValueError(f"--ablation {args.ablation} reads intentions: give --intention RUN (and --trajectory RUN) "
                         "or --ground-truth-intentions")
    live = config_from_args(LiveConfig, args)
    result = _trained(args, train_live_from_data, args.data, args.out, model, live, intention_run=args.intention,
                      trajectory_run=args.trajectory, progress=not args.no_progress)
    if result is None:
        return 1
    print(f"conav train live: {result.env_steps:,} env timesteps over {result.episodes_started:,} episodes -> "
          f"{result.run_dir}")
    return 0


def _run_train_live_baseline(args: argparse.Namespace) -> int:
    """`conav train live --baseline objectnav`: train.goalnav.train_objectnav_live_from_data."""
    from conav_jax.envs.agents.registry import run_resolution
    from conav_jax.train import goalnav
    from conav_jax.train.live import LiveConfig

    given = [flag for flag, on in (("--intention", args.intention is not None),
                                   ("--trajectory", args.trajectory is not None),
                                   ("--ground-truth-intentions", args.ground_truth_intentions),
                                   ("--ablation", args.ablation != "all")) if on]
    if given:
        raise ValueError(f"--baseline {args.baseline} reads its goal category from the episode: no {', '.join(given)}")
    hw = run_resolution([], args.resolution)
    model = goalnav.objectnav_model(hw, args.object_saliency, network_base(args, hw))
    result = _trained(args, goalnav.train_objectnav_live_from_data, args.data, args.out, model,
                      config_from_args(LiveConfig, args), progress=not args.no_progress)
    if result is None:
        return 1
    print(f"conav train live --baseline {args.baseline}: {result.env_steps:,} env timesteps over "
          f"{result.episodes_started:,} episodes -> {result.run_dir}")
    return 0


def _add_network_args(p, visual_norm: bool | None = None) -> None:
    """The panorama CNN's flags `conav train policy|objectnav|imagenav|live` share (read by
    `network_base`); `visual_norm` is the default of --visual-norm (None: PolicyConfig's)."""
    from conav_jax.models.policy import CONV_DTYPES, DEFAULT_ENCODER, ENCODERS, PolicyConfig

    visual_norm = PolicyConfig.visual_norm if visual_norm is None else visual_norm

    p.add_argument("--conv-dtype", choices=sorted(CONV_DTYPES), default=PolicyConfig.conv_dtype,
                   help="dtype of the policy's convolutions and of the activations between them: bfloat16 halves the "
                   "CNN's memory traffic and runs it on tensor cores, accumulating in float32 (default float32; part "
                   "of the run's model: a run resumes only with the value it began with)")
    p.add_argument("--encoder", choices=sorted(ENCODERS), default=DEFAULT_ENCODER,
                   help="the policy's panorama CNN: conv, stride-2 convolutions (every published run and the shipped "
                   "policy), or patch, whose first layer embeds 4x4 pixel blocks (a faster update at large "
                   "panoramas, BENCHMARKS.md; part of the run's model)")
    p.add_argument("--visual-norm", action=argparse.BooleanOptionalAction, default=visual_norm,
                   help="layer-normalise the panorama's embedding before the LSTM: without it, large panoramas and "
                   "learning rates let the embedding grow until the policy ignores its inputs (default: "
                   f"{'on' if visual_norm else 'off, as the published offline runs'}; part of the run's model)")


def network_base(args: argparse.Namespace, resolution: tuple[int, int]):
    """The PolicyConfig of `--encoder` and `--conv-dtype` at panoramas of `resolution`."""
    from conav_jax.models.policy import PolicyConfig, encoder_config

    return encoder_config(PolicyConfig(resolution=tuple(resolution), conv_dtype=args.conv_dtype,
                                       visual_norm=args.visual_norm), args.encoder)


def _add_train_goalnav(models) -> None:
    """`conav train objectnav` and `conav train imagenav`: the learned goal-navigation baselines."""
    from conav_jax.models.policy import PolicyConfig
    from conav_jax.train.policy import POLICY_TRAIN

    for name, what in (("objectnav", "the object-goal agent (after ZSON): panorama, GPS+compass and a goal category, "
                        "imitating the object-goal planner (nearest instance of object B's category)"),
                       ("imagenav", "the image-goal agent (after FGPrompt): panorama, GPS+compass and a goal image "
                        "taken at the goal, imitating the geodesic planner to the goal")):
        p = models.add_parser(name, help=f"imitation-train {what.split(':')[0]} (BC, then DAgger)",
                              description=f"Imitation-train {what}: behaviour cloning, then DAgger rounds, in the "
                              "train scenes, validated on minival; no human task and no human position. Evaluate "
                              f"the run with `conav eval --agent {'objectgoal-oracle|objectgoal-predicted' if name == 'objectnav' else 'imagegoal'} "
                              "--checkpoint RUN`.")
        train_args(p, POLICY_TRAIN)
        _add_imitation_args(p, "planner")
        p.add_argument("--remat", action="store_true", help="recompute the CNN per window step in the backward pass")
        _add_network_args(p)
        if name == "objectnav":
            p.add_argument("--object-saliency", action=argparse.BooleanOptionalAction, default=PolicyConfig.object_saliency,
                           help="also read the goal category as a saliency map over the panorama (the pixels of "
                           "that category: oracle segmentation, recorded as privileged; default: on)")
        p.set_defaults(func=_run_train_goalnav)


def _trained(args: argparse.Namespace, train, *a, **kw):
    """`train(*a, **kw)`'s result, or None after saying why the run stopped: a loss that became
    non-finite (FloatingPointError, train.loop.NonFiniteLoss among them)."""
    try:
        return train(*a, **kw)
    except FloatingPointError as e:
        print(f"conav train {args.model}: {e}")
        return None


def _run_train_intention(args: argparse.Namespace) -> int:
    from conav_jax.models.perceiver import PerceiverConfig
    from conav_jax.envs.human_crop import default_crop_hw
    from conav_jax.train.intention import IntentionDataConfig, train_intention_from_data

    resolution = args.resolution or IntentionDataConfig.resolution
    data = config_from_args(IntentionDataConfig, args, resolution=resolution)
    model = config_from_args(PerceiverConfig, args, image_hw=args.image or default_crop_hw(resolution))
    result = _trained(args, train_intention_from_data, args.data, args.out, train_config(args), model, data,
                      progress=not args.no_progress, mesh=mesh(args), val_split=args.val_split)
    if result is None:
        return 1
    v, split = result.val, args.val_split
    print(f"intention run: {result.run_dir} ({result.step} steps), validated on {split}")
    for head, name in (("activity", "activity B"), ("object", "object B")):
        top = lambda suffix: f"top-1 {v[f'{head}_top1{suffix}']:.3f}, top-5 {v[f'{head}_top5{suffix}']:.3f}"  # noqa: E731
        w = model.graph_mix if model.activity_a_head else 0.0
        print(f"{split} {name}: {top('')} (the predictor's output: {1 - w:.2f} direct heads + {w:.2f} graph prior)")
        if model.activity_a_head:
            print(f"    direct heads, no graph prior: {top('_direct')}")
            print(f"    watched A through P(B | A) counted on train alone (structural prior): "
                  f"{top('_generator_graph_prior')}")
        print(f"    prior (most frequent B given the true A) {v[f'prior_{head}_top1']:.3f} / "
              f"{v[f'prior_{head}_top5']:.3f}, chance {v[f'chance_{head}_top1']:.3f} / {v[f'chance_{head}_top5']:.3f}")
    if model.activity_a_head:
        print(f"{split} watched activity A: top-1 {v['activity_a_top1']:.3f}, top-5 {v['activity_a_top5']:.3f} "
              f"(chance {1 / model.num_activities:.3f}); top-1 uses the true A's object "
              f"{v['activity_a_object_top1']:.3f}")
    print(f"{split} frames showing the human: {v['val_frames_with_human']:.1%}; "
          f"the human's pixels inside the frames: {v['val_human_pixels_in_view']:.1%}")
    return 0


def _run_train_trajectory(args: argparse.Namespace) -> int:
    from conav_jax.models.trajectory import TrajectoryConfig
    from conav_jax.train.trajectory import train_trajectory_from_data

    result = _trained(args, train_trajectory_from_data, args.data, args.out, train_config(args),
                      TrajectoryConfig(hidden=args.hidden), progress=not args.no_progress, mesh=mesh(args))
    if result is None:
        return 1
    v = result.val
    print(f"trajectory run: {result.run_dir} ({result.step} steps)")
    print(f"val ADE {v['ade_m']:.3f} m, FDE {v['fde_m']:.3f} m "
          f"(constant velocity: ADE {v['cv_ade_m']:.3f} m, FDE {v['cv_fde_m']:.3f} m)")
    return 0


def policy_model(args: argparse.Namespace):
    """The PolicyConfig a `conav train policy` command asks for."""
    from conav_jax.models.policy import ablation_config
    from conav_jax.envs.agents.registry import run_resolution

    base = dataclasses.replace(network_base(args, run_resolution([], args.resolution)),
                               object_saliency=args.object_saliency)
    return ablation_config(base, args.ablation)


def _run_train_policy(args: argparse.Namespace) -> int:
    from conav_jax.envs.agents.policy import needed_predictors
    from conav_jax.train.policy import train_policy_from_data

    imitation = imitation_config(args, train_intentions=args.train_intentions)
    model = policy_model(args)
    for flag, run in (("--intention", args.intention), ("--trajectory", args.trajectory)):
        if run is not None and not Path(run).is_dir():
            raise FileNotFoundError(f"{flag} run directory not found: {run}")
    if imitation.train_intentions == "predicted":
        missing = [f"--{k}" for k in needed_predictors(model) if getattr(args, k) is None]
        if missing:
            raise ValueError(f"--train-intentions predicted needs the predictor runs {', '.join(missing)}")
    result = _trained(args, train_policy_from_data, args.data, args.out, train_config(args), model, imitation,
                      intention_run=args.intention, trajectory_run=args.trajectory, progress=not args.no_progress,
                      mesh=mesh(args), remat=args.remat, share_expert=args.share_expert)
    if result is None:
        return 1
    _print_imitation_result("policy", "expert", result, imitation.val_split)
    return 0


def _add_imitation_args(p, teacher: str) -> None:
    """The imitation flags `conav train policy|objectnav|imagenav` share (ImitationConfig's fields,
    read back by `imitation_config`)."""
    from conav_jax.train.policy import ImitationConfig

    resolution_arg(p, "rendered and read by the policy")
    add_fields(p, ImitationConfig, ("dagger_rounds", "dagger_steps", "dagger_beta", "dagger_episodes", "episodes",
                                    "val_episodes", "val_split", "seq_len", "burn_in", "rollout_batch", "val_batch"),
               dagger_beta=f"DAgger round r records with the {teacher} acting at a step with probability "
               "dagger_beta**r, else the policy (0: the policy alone); a resumed run may change it for the rounds to "
               "come")


def imitation_config(args: argparse.Namespace, **extra):
    """train.policy.ImitationConfig from the imitation flags `conav train policy|objectnav|imagenav` share."""
    from conav_jax.train.policy import ImitationConfig

    return config_from_args(ImitationConfig, args, **extra)


def _print_imitation_result(kind: str, teacher: str, result, split: str) -> None:
    from conav_jax.train.policy import rates_line

    print(f"{kind} run: {result.run_dir}")
    ceiling = f"{teacher} (ceiling):"
    print(f"{split} {ceiling} {rates_line(result.expert_val)}")
    print(f"{split} {'policy:':<{len(ceiling)}} {rates_line(result.val)}")


def _run_train_rl(args: argparse.Namespace) -> int:
    from conav_jax.models.policy import PolicyConfig
    from conav_jax.envs.agents.registry import run_resolution
    from conav_jax.train.ppo import PPOConfig, train_ppo_from_data

    config = config_from_args(PPOConfig, args)
    policy_config = None
    if args.init_from:
        if args.hidden is not None or args.resolution is not None:
            raise ValueError("--hidden and --resolution size a new network; with --init-from the network is the imitation run's")
    else:
        policy_config = PolicyConfig(resolution=run_resolution([], args.resolution), hidden=args.hidden or PolicyConfig.hidden)
    result = _trained(args, train_ppo_from_data, args.data, args.out, config, policy_config, args.init_from,
                      progress=not args.no_progress, mesh=mesh(args))
    if result is None:
        return 1
    print(f"ppo run: {result.run_dir} ({result.env_steps} env steps)")
    if result.val:
        print(f"{config.eval_split} " + ", ".join(f"{k} {v:.1f}" for k, v in result.val.items()))
    return 0


def _run_train_goalnav(args: argparse.Namespace) -> int:
    from conav_jax.envs.agents.registry import run_resolution
    from conav_jax.train import goalnav

    imitation = imitation_config(args)
    hw = run_resolution([], args.resolution)
    base = network_base(args, hw)
    if args.model == "objectnav":
        model, train = goalnav.objectnav_model(hw, args.object_saliency, base), goalnav.train_objectnav_from_data
    else:
        model, train = goalnav.imagenav_model(hw, base), goalnav.train_imagenav_from_data
    result = _trained(args, train, args.data, args.out, train_config(args), model, imitation,
                      progress=not args.no_progress, mesh=mesh(args), remat=args.remat)
    if result is None:
        return 1
    _print_imitation_result(args.model, "planner", result, imitation.val_split)
    return 0

