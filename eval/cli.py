"""The `conav` command: the whole command line, at the top of the dependency graph.

argv -> argparse (every sub-command's flags are here and only here) -> frozen configs -> the
stage's plain function (conav_jax.data.episodes, train.*, eval.*, envs.bench) -> a summary on stdout.
Stage modules are imported only by the sub-command that runs, so `conav --help` stays quick.
Before any command runs, JAX's persistent compilation cache is switched on (`--compile-cache`),
so a second run of a command recompiles nothing. Data-parallel commands (`--devices`) first
join a multi-host run if the environment describes one (conav_jax.parallel).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
import signal
import sys
import tempfile
import time
import warnings
from pathlib import Path

from conav_jax import __version__

COMPILE_CACHE_ENV = "CONAV_COMPILE_CACHE"  # a directory, or "off"


# -- shared argument types and groups ----------------------------------------------------------


def parse_resolution(text: str) -> tuple[int, int]:
    """`HxW` (e.g. 112x448) -> (H, W)."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must look like 112x448, got {text!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"resolution must be positive, got {text!r}")
    return h, w


def parse_physics_override(text: str) -> tuple[str, object]:
    """`NAME=VALUE` for a field of envs.config.PhysicsConfig, VALUE converted to the field's type."""
    from conav_jax.envs.config import PhysicsConfig

    fields = {f.name for f in dataclasses.fields(PhysicsConfig)}
    name, sep, value = text.partition("=")
    if not sep or name not in fields:
        raise argparse.ArgumentTypeError(
            f"physics override must be NAME=VALUE with NAME one of {sorted(fields)}, got {text!r}")
    kind = type(getattr(PhysicsConfig(), name))
    try:
        return name, kind(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"physics {name} needs a {kind.__name__}, got {value!r}") from None


def _resolution_arg(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--resolution", type=parse_resolution, default=None, metavar="HxW",
                   help=f"panorama HxW {what} (default: the paper's 112x448, envs.config.SensorConfig)")


def _devices_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--devices", type=int, default=None, metavar="N",
                   help="devices each batch is split over (default: all visible, every host's in a multi-host run)")


def _intention_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--intention", default=None, metavar="RUN",
                   help="conav/ppo/objectgoal-predicted: intention predictor run (`conav train intention`; default "
                   "for conav: the one the policy run names)")
    p.add_argument("--trajectory", default=None, metavar="RUN",
                   help="conav/ppo: trajectory predictor run (`conav train trajectory`; default for conav: the "
                   "one the policy run names)")
    p.add_argument("--ground-truth-intentions", action="store_true",
                   help="conav/ppo: feed the env's ground-truth intentions instead of predictions (privileged "
                   "upper bound, labelled so in every output)")
    p.add_argument("--pretrained", action="store_true",
                   help="conav: the policy and the predictors it reads, shipped with the package (trained on the "
                   "paper preset at 32x128; conav_jax/pretrained/PROVENANCE.json) in place of --checkpoint/"
                   "--intention/--trajectory")


def _use_pretrained(args: argparse.Namespace, agents: tuple[str, ...]) -> None:
    """--pretrained: the conav agent's run and the predictors it reads become the shipped ones
    (ValueError when conav is not run, or --checkpoint / --intention / --trajectory would also
    name them)."""
    if not args.pretrained:
        return
    from conav_jax.pretrained import pretrained_runs
    from conav_jax.envs.agents.registry import AGENTS

    if "conav" not in agents:
        raise ValueError("--pretrained is the conav agent's: add conav to --agent")
    if args.intention is not None or args.trajectory is not None or args.ground_truth_intentions:
        raise ValueError("--pretrained brings its own predictors: drop --intention / --trajectory / "
                         "--ground-truth-intentions")
    runs = pretrained_runs()
    given = parse_checkpoints(args.checkpoint)
    others = [a for a in agents if a != "conav" and a in AGENTS and AGENTS[a].needs_checkpoint]
    if isinstance(given, dict) and "conav" in given or isinstance(given, str) and not others:
        raise ValueError("--pretrained is the conav agent's run: drop its --checkpoint")
    if isinstance(given, str):  # a bare RUN stays the other learned agents'
        given = {None: given}
    checkpoint = {**(given or {}), "conav": str(runs["policy"])}
    args.checkpoint = (str(runs["policy"]) if len(checkpoint) == 1
                       else ",".join(f"{k}={v}" if k else v for k, v in checkpoint.items()))
    args.intention = str(runs["intention"])
    args.trajectory = str(runs["trajectory"]) if "trajectory" in runs else None


def _intention_kwargs(args: argparse.Namespace) -> dict:
    """envs.agents.registry.make_agent's intention keywords from `_intention_args`' flags."""
    out = {}
    for key, run in (("intention_run", args.intention), ("trajectory_run", args.trajectory)):
        if run is not None:
            if not Path(run).is_dir():
                raise ValueError(f"--{key.removesuffix('_run')} run directory not found: {run}")
            out[key] = run
    if args.ground_truth_intentions:
        if out:
            raise ValueError("--ground-truth-intentions excludes --intention / --trajectory")
        out["ground_truth"] = True
    return out


def _train_args(p: argparse.ArgumentParser, defaults) -> None:
    """--data, --out, the TrainConfig fields (with this command's defaults), --no-progress, --devices."""
    from conav_jax.train.loop import TrainConfig

    p.add_argument("--data", required=True, help="dataset dir written by `conav generate`")
    p.add_argument("--out", required=True, help="run dir: log.jsonl and checkpoints (resumed if present)")
    for f in dataclasses.fields(TrainConfig):
        default = getattr(defaults, f.name)
        p.add_argument("--" + f.name.replace("_", "-"), type=type(default), default=default,
                       help=f"TrainConfig.{f.name} (default {default})")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _devices_arg(p)


def _train_config(args: argparse.Namespace):
    from conav_jax.train.loop import TrainConfig

    return TrainConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig)})


def _mesh(args: argparse.Namespace):
    from conav_jax.parallel import make_mesh

    return make_mesh(args.devices)


def _tiny_dataset() -> tempfile.TemporaryDirectory:
    """The tiny preset in a temporary directory (benchmarks run without --data)."""
    from conav_jax.data.episodes import generate_dataset
    from conav_jax.data.presets import preset

    tmp = tempfile.TemporaryDirectory()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        generate_dataset(preset("tiny"), tmp.name)
    return tmp


# -- conav generate ------------------------------------------------------------------------------

_GENERATE_EPILOG = """\
scene source:
  procedural (default)   the preset's apartments: train, val and minival scenes of their own
  --scenes DIR           every DIR/*.json scene file (the conav_jax.data.scene format), split by name:
                         --val-scenes and --minival-scenes take comma-separated scene file names
                         without .json (e.g. --val-scenes apt_3,apt_7); every other file is train.
                         Each split gets --episodes-per-scene episodes per scene. --preset, when
                         given, supplies the task, motion and navigation settings (default: the
                         DatasetConfig defaults); its scene counts and scene generation are unused.

examples:
  conav generate --preset small --out data/small
  conav generate --scenes my_scenes --val-scenes flat_2 --minival-scenes flat_5 \\
      --episodes-per-scene 200 --out data/mine --seed 1
"""


def _add_generate(sub) -> None:
    from conav_jax.data.presets import PRESETS

    p = sub.add_parser(
        "generate",
        help="generate a CoNav episode dataset from a preset or from your own scene files",
        description="Generate a CoNav episode dataset (manifest, scene nav fields, episode shards); "
        "the same seed gives the same bytes.",
        epilog=_GENERATE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--preset", choices=sorted(PRESETS), default=None,
                   help="dataset preset (default: tiny); with --scenes, only its task, motion and navigation settings")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=None, help="dataset seed (default: the preset's, 0)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    own = p.add_argument_group("own scenes")
    own.add_argument("--scenes", default=None, metavar="DIR", help="build episodes in DIR/*.json instead of generated apartments")
    own.add_argument("--episodes-per-scene", type=int, default=None, metavar="N", help="episodes per scene (needed with --scenes)")
    own.add_argument("--val-scenes", default="", metavar="NAME,...", help="scene files (names without .json) for val")
    own.add_argument("--minival-scenes", default="", metavar="NAME,...", help="scene files (names without .json) for minival")
    own.add_argument("--name", default=None, help="dataset name recorded in the manifest (default: DIR's name)")
    p.set_defaults(func=_run_generate)


def scene_split_from_args(scenes_dir: str | os.PathLike, val: str, minival: str) -> dict[str, list[Path]]:
    """split -> scene files: the named files to val and minival, the rest of DIR/*.json to train.
    ValueError for a name that is not a file in DIR or a file named twice."""
    directory = Path(scenes_dir)
    if not directory.is_dir():
        raise FileNotFoundError(f"--scenes: directory not found: {directory}")
    files = {p.stem: p for p in sorted(directory.glob("*.json"))}
    if not files:
        raise ValueError(f"--scenes: no *.json scene files in {directory}")
    named: dict[str, str] = {}
    split: dict[str, list[Path]] = {"train": [], "val": [], "minival": []}
    for which, spec in (("val", val), ("minival", minival)):
        for name in (n.strip() for n in spec.split(",")):
            if not name:
                continue
            name = name.removesuffix(".json")
            if name not in files:
                raise ValueError(f"--{which}-scenes: no scene file {name}.json in {directory}; has {', '.join(files)}")
            if name in named:
                raise ValueError(f"--{which}-scenes: {name} is already in {named[name]}; splits must not share scenes")
            named[name] = which
            split[which].append(files[name])
    split["train"] = [p for stem, p in files.items() if stem not in named]
    return {k: v for k, v in split.items() if v}


def _run_generate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from conav_jax.config import DatasetConfig
    from conav_jax.data.episodes import (
        BlockedStandingPoint,
        generate_dataset,
        generate_from_scenes,
    )
    from conav_jax.data.presets import preset

    if args.workers < 1:
        raise ValueError("--workers must be at least 1")
    own_flags = [f for f, v in (("--episodes-per-scene", args.episodes_per_scene), ("--val-scenes", args.val_scenes),
                                ("--minival-scenes", args.minival_scenes), ("--name", args.name)) if v]
    if args.scenes is None and own_flags:
        raise ValueError(f"{', '.join(own_flags)} only apply with --scenes DIR")

    def bar(total: int, name: str):
        return lambda it: tqdm(it, total=total, desc=f"generate {name}", unit="scene")

    t0 = time.perf_counter()
    # Scenes whose objects the robot cannot reach print one line each, after the progress bar.
    with warnings.catch_warnings(record=True) as caught:
        try:
            if args.scenes is None:
                cfg = preset(args.preset or "tiny", args.seed)
                n_scenes = sum(n for n, _ in cfg.split_sizes().values())
                m = generate_dataset(cfg, args.out, workers=args.workers, progress=bar(n_scenes, cfg.name))
            else:
                if args.episodes_per_scene is None or args.episodes_per_scene < 1:
                    raise ValueError("--scenes needs --episodes-per-scene N (N >= 1)")
                by_split = scene_split_from_args(args.scenes, args.val_scenes, args.minival_scenes)
                base = preset(args.preset, args.seed) if args.preset else DatasetConfig()
                name = args.name or Path(args.scenes).resolve().name
                cfg = dataclasses.replace(base, name=name, seed=base.seed if args.seed is None else args.seed)
                episodes = {split: args.episodes_per_scene * len(paths) for split, paths in by_split.items()}
                n_scenes = sum(len(v) for v in by_split.values())
                m = generate_from_scenes(by_split, episodes, cfg, args.out, workers=args.workers, progress=bar(n_scenes, name))
        finally:
            for w in caught:
                if issubclass(w.category, BlockedStandingPoint):
                    print(f"warning: {w.message}", file=sys.stderr)
                else:
                    warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    dt = time.perf_counter() - t0
    for split, s in m["splits"].items():
        print(f"{split}: {s['episodes']} episodes in {len(s['scenes'])} scenes, "
              f"mean length {s['mean_length_steps']} steps (max {s['max_length_steps']})")
    print(f"wrote {args.out} in {dt:.1f} s, content hash {m['content_hash'][:16]}")
    return 0


# -- conav train ---------------------------------------------------------------------------------


def _add_train(sub) -> None:
    from conav_jax.models.perceiver import PerceiverConfig
    from conav_jax.models.policy import ABLATIONS, PolicyConfig
    from conav_jax.models.trajectory import TrajectoryConfig
    from conav_jax.train.intention import IntentionDataConfig
    from conav_jax.train.loop import TrainConfig
    from conav_jax.train.policy import TRAIN_INTENTIONS, ImitationConfig
    from conav_jax.train.ppo import PPOConfig

    train = sub.add_parser("train", help="train the intention / trajectory predictors, the policy, PPO")
    models = train.add_subparsers(dest="model", metavar="MODEL", required=True)

    p = models.add_parser("intention", help="train the intention (activity/object B) Perceiver")
    _train_args(p, TrainConfig(steps=6000, batch=64, lr=3e-4, weight_decay=0.01))
    dd, dm = IntentionDataConfig(), PerceiverConfig()
    p.add_argument("--frames", type=int, default=dd.frames, help=f"frames per episode (F; default {dd.frames})")
    p.add_argument("--sensor", type=parse_resolution, default=dd.sensor_hw, metavar="HxW",
                   help="panorama HxW the frames come from; agents acting with the run must render it "
                   f"(default {dd.sensor_hw[0]}x{dd.sensor_hw[1]})")
    p.add_argument("--image", type=parse_resolution, default=None, metavar="HxW",
                   help="Perceiver frame HxW: the crop around the human, in panorama pixels (front view: resized "
                   f"to it; default {dm.image_hw[0]}x{dm.image_hw[1]}, or the --sensor height rounded down to a "
                   "multiple of 8 where that is smaller)")
    p.add_argument("--view", choices=("human", "front"), default=dd.view,
                   help="what a frame shows: the panorama cropped around the human (default) or its front quarter "
                   "(the input before the crop)")
    p.add_argument("--mirror", action="store_true",
                   help="mirror each training sample left-right with probability 1/2 at every update (validation "
                   "frames never)")
    p.add_argument("--seen-objects", action="store_true",
                   help="weigh activities by whether the robot's panoramas have shown their object category (read "
                   "from their exact category colours: oracle segmentation, recorded as privileged for the agents "
                   "using the run), by odds counted on the train split; inference only, the training is the same")
    p.add_argument("--viewpoints", type=int, default=dd.viewpoints,
                   help="robot poses each train episode is rendered from: its start pose, then poses drawn around "
                   f"the human (default {dd.viewpoints}; 16 frames of 64x64 take 0.26 GB of device memory per 1,000 "
                   "episodes and viewpoint)")
    p.add_argument("--dim", type=int, default=dm.dim, help=f"Perceiver token and latent width (default {dm.dim})")
    p.add_argument("--latents", type=int, default=dm.num_latents, help=f"latent array length (default {dm.num_latents})")
    p.add_argument("--blocks", type=int, default=dm.num_blocks,
                   help=f"latent self-attention blocks (default {dm.num_blocks})")
    p.add_argument("--no-activity-a-head", dest="activity_a_head", action="store_false",
                   help="predict B with the direct heads only (no activity-A head, no graph prior)")
    p.add_argument("--graph-mix", type=float, default=dm.graph_mix,
                   help="weight of the graph route (the watched activity A through the generator's own activity "
                   f"graph, a structural prior) in the predictions (default {dm.graph_mix})")
    p.add_argument("--val-split", default="minival",
                   help="split validated on (default minival: hyper-parameters are chosen there, never on the "
                   "reported val split)")
    p.set_defaults(func=_run_train_intention)

    p = models.add_parser("trajectory", help="train the trajectory (short-term intention) predictor")
    _train_args(p, TrainConfig(steps=3000, batch=256, lr=2e-3))
    p.add_argument("--hidden", type=int, default=TrajectoryConfig.hidden, help="LSTM/MLP width")
    p.set_defaults(func=_run_train_trajectory)

    p = models.add_parser("policy", help="imitation-train the CoNav policy from the expert (BC, then DAgger)")
    _train_args(p, TrainConfig(steps=2000, batch=16, lr=3e-4, warmup_steps=100, val_every=1000, ckpt_every=500))
    d = ImitationConfig()
    p.add_argument("--intention", default=None, metavar="RUN",
                   help="intention run (conav train intention): validate with its predictions")
    p.add_argument("--trajectory", default=None, metavar="RUN",
                   help="trajectory run (conav train trajectory): validate with its predictions")
    p.add_argument("--ablation", choices=sorted(ABLATIONS), default="all", help="intention inputs kept (Table 3 row; default all)")
    _add_imitation_args(p, "expert")
    p.add_argument("--remat", action="store_true",
                   help="recompute the CNN per window step in the backward pass: less memory (float32 112x448 windows "
                   "at batch >= 256 need it on an H100); slower at 32x128, about 2x faster at 112x448 with "
                   "--conv-dtype bfloat16 (BENCHMARKS.md)")
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

    d = PPOConfig()
    p = models.add_parser("rl", help="train the policy with PPO in the simulator")
    p.add_argument("--data", required=True, help="dataset dir written by `conav generate`")
    p.add_argument("--out", required=True, help="new run dir: log.jsonl and checkpoints")
    p.add_argument("--init-from", default=None, metavar="POLICY_RUN",
                   help="start from an imitation policy run (its network, weights and value head)")
    p.add_argument("--num-envs", type=int, default=d.num_envs, help=f"parallel envs (default {d.num_envs})")
    p.add_argument("--steps", type=int, default=d.total_env_steps, help=f"total env steps (default {d.total_env_steps})")
    p.add_argument("--rollout-steps", type=int, default=d.rollout_steps, help=f"steps per env per iteration (default {d.rollout_steps})")
    p.add_argument("--lr", type=float, default=d.lr, help=f"Adam learning rate (default {d.lr})")
    p.add_argument("--reset-every", type=int, default=None,
                   help="iterations between re-resets onto new episodes (default: enough for the longest episode)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--recurrent", dest="recurrent", action="store_true", default=d.recurrent,
                      help="LSTM carry through time (default)")
    mode.add_argument("--feedforward", dest="recurrent", action="store_false", help="zero LSTM carry every step")
    _resolution_arg(p, "of a new network (with --init-from: the imitation run's)")
    p.add_argument("--hidden", type=int, default=None,
                   help=f"LSTM width of a new network (default {PolicyConfig.hidden}; not with --init-from)")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--eval-every", type=int, default=d.eval_every, help="iterations between val evaluations (0: none)")
    p.add_argument("--eval-split", default=d.eval_split, help=f"split evaluated on while training (default {d.eval_split})")
    p.add_argument("--ckpt-every", type=int, default=d.ckpt_every, help="iterations between checkpoints")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _devices_arg(p)
    p.set_defaults(func=_run_train_rl)
    _add_train_goalnav(models)


def _add_network_args(p) -> None:
    """The panorama CNN's flags `conav train policy|objectnav|imagenav` share (read by `_network_base`)."""
    from conav_jax.models.policy import CONV_DTYPES, DEFAULT_ENCODER, ENCODERS, PolicyConfig

    p.add_argument("--conv-dtype", choices=sorted(CONV_DTYPES), default=PolicyConfig.conv_dtype,
                   help="dtype of the policy's convolutions and of the activations between them: bfloat16 halves the "
                   "CNN's memory traffic and runs it on tensor cores, accumulating in float32 (default float32; part "
                   "of the run's model: a run resumes only with the value it began with)")
    p.add_argument("--encoder", choices=sorted(ENCODERS), default=DEFAULT_ENCODER,
                   help="the policy's panorama CNN: conv, stride-2 convolutions (every published run and the shipped "
                   "policy), or patch, whose first layer embeds 4x4 pixel blocks (1.9x the 112x448 update on a GPU; "
                   "part of the run's model, BENCHMARKS.md)")


def _network_base(args: argparse.Namespace, image_hw: tuple[int, int]):
    """The PolicyConfig of `--encoder` and `--conv-dtype` at panoramas of `image_hw`."""
    from conav_jax.models.policy import PolicyConfig, encoder_config

    return encoder_config(PolicyConfig(image_hw=tuple(image_hw), conv_dtype=args.conv_dtype), args.encoder)


def _add_train_goalnav(models) -> None:
    """`conav train objectnav` and `conav train imagenav`: the learned goal-navigation baselines."""
    from conav_jax.models.policy import PolicyConfig
    from conav_jax.train.loop import TrainConfig

    for name, what in (("objectnav", "the object-goal agent (after ZSON): panorama, GPS+compass and a goal category, "
                        "imitating the object-goal planner (nearest instance of object B's category)"),
                       ("imagenav", "the image-goal agent (after FGPrompt): panorama, GPS+compass and a goal image "
                        "taken at the goal, imitating the geodesic planner to the goal")):
        p = models.add_parser(name, help=f"imitation-train {what.split(':')[0]} (BC, then DAgger)",
                              description=f"Imitation-train {what}: behaviour cloning, then DAgger rounds, in the "
                              "train scenes, validated on minival; no human task and no human position. Evaluate "
                              f"the run with `conav eval --agent {'objectgoal-oracle|objectgoal-predicted' if name == 'objectnav' else 'imagegoal'} "
                              "--checkpoint RUN`.")
        _train_args(p, TrainConfig(steps=2000, batch=16, lr=3e-4, warmup_steps=100, val_every=1000, ckpt_every=500))
        _add_imitation_args(p, "planner")
        p.add_argument("--remat", action="store_true", help="recompute the CNN per window step in the backward pass")
        _add_network_args(p)
        if name == "objectnav":
            p.add_argument("--object-saliency", action=argparse.BooleanOptionalAction, default=PolicyConfig.object_saliency,
                           help="also read the goal category as a saliency map over the panorama (the pixels of "
                           "that category: oracle segmentation, recorded as privileged; default: on)")
        p.set_defaults(func=_run_train_goalnav)


def _run_train_intention(args: argparse.Namespace) -> int:
    from conav_jax.models.perceiver import PerceiverConfig
    from conav_jax.envs.human_crop import default_crop_hw
    from conav_jax.train.intention import IntentionDataConfig, train_intention
    from conav_jax.train.loop import NonFiniteLoss

    data = IntentionDataConfig(sensor_hw=args.sensor, frames=args.frames, view=args.view, viewpoints=args.viewpoints,
                               mirror=args.mirror)
    image = args.image or default_crop_hw(args.sensor)
    model = PerceiverConfig(image_hw=image, dim=args.dim, num_latents=args.latents, num_blocks=args.blocks,
                            activity_a_head=args.activity_a_head, graph_mix=args.graph_mix,
                            seen_objects=args.seen_objects)
    try:
        result = train_intention(args.data, args.out, _train_config(args), model, data, progress=not args.no_progress,
                                 mesh=_mesh(args), val_split=args.val_split)
    except NonFiniteLoss as e:
        print(f"conav train intention: {e}")
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
    from conav_jax.train.loop import NonFiniteLoss
    from conav_jax.train.trajectory import train_trajectory

    try:
        result = train_trajectory(args.data, args.out, _train_config(args), TrajectoryConfig(hidden=args.hidden),
                                  progress=not args.no_progress, mesh=_mesh(args))
    except NonFiniteLoss as e:
        print(f"conav train trajectory: {e}")
        return 1
    v = result.val
    print(f"trajectory run: {result.run_dir} ({result.step} steps)")
    print(f"val ADE {v['ade_m']:.3f} m, FDE {v['fde_m']:.3f} m "
          f"(constant velocity: ADE {v['cv_ade_m']:.3f} m, FDE {v['cv_fde_m']:.3f} m)")
    return 0


def _policy_model(args: argparse.Namespace):
    """The PolicyConfig a `conav train policy` command asks for."""
    from conav_jax.models.policy import ablation_config
    from conav_jax.envs.agents.registry import run_resolution

    base = dataclasses.replace(_network_base(args, run_resolution([], args.resolution)),
                               object_saliency=args.object_saliency)
    return ablation_config(base, args.ablation)


def _run_train_policy(args: argparse.Namespace) -> int:
    from conav_jax.train.loop import NonFiniteLoss
    from conav_jax.train.policy import train_policy

    imitation = _imitation_config(args, train_intentions=args.train_intentions)
    for flag, run in (("--intention", args.intention), ("--trajectory", args.trajectory)):
        if run is not None and not Path(run).is_dir():
            raise FileNotFoundError(f"{flag} run directory not found: {run}")
    try:
        result = train_policy(args.data, args.out, _train_config(args), _policy_model(args), imitation,
                              intention_run=args.intention, trajectory_run=args.trajectory,
                              progress=not args.no_progress, mesh=_mesh(args), remat=args.remat,
                              share_expert=args.share_expert)
    except NonFiniteLoss as e:
        print(f"conav train policy: {e}")
        return 1
    _print_imitation_result("policy", "expert", result, imitation.val_split)
    return 0


def _add_imitation_args(p, teacher: str) -> None:
    """The imitation flags `conav train policy|objectnav|imagenav` share (read by `_imitation_config`)."""
    from conav_jax.train.policy import RECORD_BUDGET_BYTES, ImitationConfig

    d = ImitationConfig()
    p.add_argument("--dagger-rounds", type=int, default=d.dagger_rounds,
                   help="DAgger rounds after behaviour cloning (a finished run resumes with more)")
    p.add_argument("--dagger-steps", type=int, default=None,
                   help="updates per DAgger round (default: --steps); a resumed run may change it for the rounds to come")
    p.add_argument("--dagger-beta", type=float, default=d.dagger_beta, metavar="P",
                   help=f"DAgger round r records with the {teacher} acting at a step with probability P**r, else the "
                        "policy (default 0: the policy alone); a resumed run may change it for the rounds to come")
    p.add_argument("--dagger-episodes", type=int, default=None, metavar="N",
                   help="train episodes each DAgger round records, a different random subset of --episodes each round "
                        "(default: all of them); a round's windows stay on the GPU while the run trains, and the "
                        "policy's own episodes run about three times the expert's; a resumed run may change it for "
                        "the rounds to come")
    _resolution_arg(p, "rendered and read by the policy")
    p.add_argument("--episodes", type=int, default=None, help="train episodes recorded (default: all)")
    p.add_argument("--val-episodes", type=int, default=None, help="val episodes validated on (default: all)")
    p.add_argument("--val-split", default=d.val_split, help=f"split validated on (default {d.val_split}: hyper-parameters "
                   "are chosen there, never on the reported val split)")
    p.add_argument("--seq-len", type=int, default=d.seq_len, help="steps per training window")
    p.add_argument("--burn-in", type=int, default=d.burn_in, help="LSTM warm-up steps before each window")
    p.add_argument("--rollout-batch", type=int, default=None,
                   help=f"episodes per recording call (default: as many as {RECORD_BUDGET_BYTES / 2**30:.0f} GiB of "
                   "records hold; results do not depend on it)")
    p.add_argument("--val-batch", type=int, default=ImitationConfig.val_batch,
                   help="episodes per validation call (default %(default)s)")


def _imitation_config(args: argparse.Namespace, **extra):
    """train.policy.ImitationConfig from the imitation flags `conav train policy|objectnav|imagenav` share."""
    from conav_jax.train.policy import ImitationConfig

    return ImitationConfig(
        episodes=args.episodes, val_episodes=args.val_episodes, val_split=args.val_split,
        dagger_rounds=args.dagger_rounds, dagger_steps=args.dagger_steps, dagger_beta=args.dagger_beta,
        dagger_episodes=args.dagger_episodes,
        seq_len=args.seq_len, burn_in=args.burn_in,
        rollout_batch=args.rollout_batch, val_batch=args.val_batch, **extra,
    )


def _print_imitation_result(kind: str, teacher: str, result, split: str) -> None:
    from conav_jax.train.policy import rates_line

    print(f"{kind} run: {result.run_dir}")
    ceiling = f"{teacher} (ceiling):"
    print(f"{split} {ceiling} {rates_line(result.expert_val)}")
    print(f"{split} {'policy:':<{len(ceiling)}} {rates_line(result.val)}")


def _run_train_rl(args: argparse.Namespace) -> int:
    from conav_jax.models.policy import PolicyConfig
    from conav_jax.envs.agents.registry import run_resolution
    from conav_jax.train.ppo import PPOConfig, train_ppo

    config = PPOConfig(
        num_envs=args.num_envs, rollout_steps=args.rollout_steps, reset_every=args.reset_every,
        total_env_steps=args.steps, lr=args.lr, recurrent=args.recurrent, seed=args.seed,
        eval_every=args.eval_every, eval_split=args.eval_split, ckpt_every=args.ckpt_every,
    )
    policy_config = None
    if args.init_from:
        if args.hidden is not None or args.resolution is not None:
            raise ValueError("--hidden and --resolution size a new network; with --init-from the network is the imitation run's")
    else:
        policy_config = PolicyConfig(image_hw=run_resolution([], args.resolution), hidden=args.hidden or PolicyConfig.hidden)
    try:
        result = train_ppo(args.data, args.out, config, policy_config, args.init_from, progress=not args.no_progress,
                           mesh=_mesh(args))
    except FloatingPointError as e:
        print(f"conav train rl: {e}")
        return 1
    print(f"ppo run: {result.run_dir} ({result.env_steps} env steps)")
    if result.val:
        print(f"{config.eval_split} " + ", ".join(f"{k} {v:.1f}" for k, v in result.val.items()))
    return 0


def _run_train_goalnav(args: argparse.Namespace) -> int:
    from conav_jax.envs.agents.registry import run_resolution
    from conav_jax.train import goalnav
    from conav_jax.train.loop import NonFiniteLoss

    imitation = _imitation_config(args)
    hw = run_resolution([], args.resolution)
    base = _network_base(args, hw)
    if args.model == "objectnav":
        model, train = goalnav.objectnav_model(hw, args.object_saliency, base), goalnav.train_objectnav
    else:
        model, train = goalnav.imagenav_model(hw, base), goalnav.train_imagenav
    try:
        result = train(args.data, args.out, _train_config(args), model, imitation, progress=not args.no_progress,
                       mesh=_mesh(args), remat=args.remat)
    except NonFiniteLoss as e:
        print(f"conav train {args.model}: {e}")
        return 1
    _print_imitation_result(args.model, "planner", result, imitation.val_split)
    return 0


# -- conav eval, view, curve ---------------------------------------------------------------------


def _add_eval(sub) -> None:
    from conav_jax.envs.agents.registry import AGENTS

    p = sub.add_parser("eval", help="evaluate agents on a split: per-episode records, metrics with CIs, Table 2/3 report")
    p.add_argument("--data", required=True, help="dataset dir written by `conav generate`")
    p.add_argument("--split", default="val")
    p.add_argument("--agent", required=True,
                   help="comma-separated agent names: " + "; ".join(f"{k} ({s.summary})" for k, s in AGENTS.items()))
    p.add_argument("--checkpoint", default=None, metavar="RUN | AGENT=RUN,...",
                   help="run dir of the learned agents (conav, ppo, objectgoal-oracle, objectgoal-predicted, "
                   "imagegoal); for several learned agents of different runs, AGENT=RUN per agent, comma-separated "
                   "(e.g. conav=runs/dagger,objectgoal-oracle=runs/objectnav,objectgoal-predicted=runs/objectnav,"
                   "imagegoal=runs/imagenav); an entry without AGENT= is the run of the learned agents not named")
    _intention_args(p)
    p.add_argument("--ablation-checkpoints", default=None, metavar="NAME=RUN,...",
                   help="conav runs for the Table 3 ablation; the names none, activity, object, "
                   "activity_object, all mark which intention inputs a run uses")
    p.add_argument("--episodes", type=int, default=None, help="evaluate only the first N episodes")
    p.add_argument("--batch", type=int, default=256, help="parallel lanes: episodes in flight at once")
    p.add_argument("--seed", type=int, default=0, help="rollout keys and bootstrap resampling")
    _resolution_arg(p, "(default with a trained run: the run's)")
    p.add_argument("--out", required=True, help="output directory")
    _devices_arg(p)
    p.set_defaults(func=_run_eval)


def parse_ablations(text: str | None) -> tuple[tuple[str, str], ...]:
    """`name=RUN,...` -> ((name, run), ...)."""
    if not text:
        return ()
    out = []
    for item in text.split(","):
        name, sep, run = item.strip().partition("=")
        if not sep or not name or not run:
            raise ValueError(f"--ablation-checkpoints entries look like name=RUN_DIR, got {item!r}")
        out.append((name, run))
    return tuple(out)


def parse_checkpoints(text: str | None) -> str | dict[str | None, str] | None:
    """`RUN` -> RUN; `AGENT=RUN,...` (with at most one bare RUN: the other learned agents') ->
    {agent: run, None: run}."""
    if not text or "=" not in text:
        return text
    out: dict[str | None, str] = {}
    for item in text.split(","):
        name, sep, run = item.strip().partition("=")
        name, run = (name, run) if sep else (None, name)
        if name == "" or not run or name in out:
            raise ValueError(f"--checkpoint entries look like AGENT=RUN_DIR (at most one bare RUN_DIR, each agent "
                             f"once), got {item!r}")
        out[name] = run
    return out


def _run_eval(args: argparse.Namespace) -> int:
    from conav_jax.eval import sweep

    agents = tuple(n.strip() for n in args.agent.split(",") if n.strip())
    _use_pretrained(args, agents)
    plan = sweep.plan_eval(
        args.data, args.split, agents, args.out,
        checkpoint=parse_checkpoints(args.checkpoint), intention_kwargs=_intention_kwargs(args),
        ablations=parse_ablations(args.ablation_checkpoints), episodes=args.episodes, batch=args.batch,
        seed=args.seed, resolution=args.resolution, devices=args.devices,
    )
    mesh = _mesh(args)
    env = sweep.load_env(plan)
    doc = sweep.sweep(plan, env, progress=True, mesh=mesh)
    print((plan.out / "report.md").read_text().split("## Figures")[0].rstrip())
    print(f"wrote {plan.out} ({len(doc['agents'])} agents, {len(doc['ablations'])} ablations, {env.num_episodes} "
          f"episodes, {mesh.size} device(s))")
    return 0


def _add_view(sub) -> None:
    from conav_jax.envs.agents.registry import AGENTS

    p = sub.add_parser("view", help="record one episode as a rerun .rrd (scene, human, robot, panorama, intentions)")
    p.add_argument("--data", required=True, help="dataset dir written by `conav generate`")
    p.add_argument("--split", default="val")
    p.add_argument("--episode", type=int, required=True, help="episode index within the split")
    p.add_argument("--agent", default="pioneer", help=f"who drives the robot: {', '.join(AGENTS)}")
    p.add_argument("--checkpoint", default=None,
                   help="run dir of the learned agent (conav, ppo, objectgoal-oracle, objectgoal-predicted, imagegoal)")
    _intention_args(p)
    _resolution_arg(p, "(default with a trained run: the run's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="output .rrd file")
    p.add_argument("--spawn", action="store_true", help="also stream to a spawned rerun viewer")
    p.set_defaults(func=_run_view)


def _run_view(args: argparse.Namespace) -> int:
    from conav_jax.eval.viewer import view_episode

    _use_pretrained(args, (args.agent,))
    print(view_episode(args.data, args.split, args.episode, args.agent, args.out, args.checkpoint,
                       _intention_kwargs(args), args.resolution, args.seed, args.spawn))
    return 0


def _add_curve(sub) -> None:
    p = sub.add_parser("curve", help="PPO learning curve (success vs env steps) from run logs, as PNG")
    p.add_argument("runs", nargs="+", metavar="[TITLE=]RUN", help="`conav train rl` run dirs")
    p.add_argument("--out", required=True, help="output .png")
    p.add_argument("--window", type=int, default=None,
                   help="training iterations pooled per point (default: each run's reset cycle, else 4)")
    p.set_defaults(func=_run_curve)


def _run_curve(args: argparse.Namespace) -> int:
    from conav_jax.runs import read_log
    from conav_jax.eval.plots import learning_curve

    if args.window is not None and args.window < 1:
        raise ValueError(f"--window must be at least 1, got {args.window}")
    logs = {}
    for spec in args.runs:
        title, _, run = spec.rpartition("=")
        logs[title or Path(run).name] = read_log(run)
    print(f"wrote {learning_curve(logs, args.out, args.window)}")
    return 0


# -- conav demo ----------------------------------------------------------------------------------


def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="the whole pipeline on the tiny preset (CPU, minutes)")
    p.add_argument("--out", required=True, help="output directory (data, runs, eval, episode.rrd)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resolution", default="16x64", type=parse_resolution, metavar="HxW",
                   help="panorama HxW the demo trains at (small: CPU; default 16x64)")
    p.add_argument("--no-pretrained", dest="pretrained", action="store_false",
                   help="evaluate and record the demo's own briefly trained policy (at --resolution) instead of the "
                   "shipped one (conav_jax/pretrained, 32x128)")
    p.set_defaults(func=_run_demo)


def _run_stage(argv) -> int:
    """One stage of `conav demo` or `conav reproduce`, run in this process as a fresh `conav`
    process would run it: JAX's in-memory caches are cleared first. A later stage that reuses a
    function traced by an earlier one lowers to a program of the same computation but other
    function names, whose compile-cache key then misses on the next run (seen on the demo's
    evaluation: 40 s on a second run instead of 15 s)."""
    import jax

    jax.clear_caches()
    return main(list(argv), compile_cache=False)  # the compile cache was set up for the whole command


def _run_demo(args: argparse.Namespace) -> int:
    from conav_jax.eval.demo import demo_commands

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    for argv in demo_commands(out, args.seed, "x".join(map(str, args.resolution)), args.pretrained):
        print(f"\n$ conav {shlex.join(argv)}", flush=True)
        t0 = time.perf_counter()
        rc = _run_stage(argv)
        if rc:
            print(f"conav demo: stage `{argv[0]}` failed (exit {rc})")
            return rc
        print(f"[{' '.join(argv[:2]) if argv[0] == 'train' else argv[0]}] done in {time.perf_counter() - t0:.0f} s",
              flush=True)
    print(f"\ndemo finished in {time.perf_counter() - t_start:.0f} s: report {out / 'eval' / 'report.md'}, "
          f"recording {out / 'episode0.rrd'} (open with `rerun {out / 'episode0.rrd'}`)")
    return 0


# -- conav reproduce ------------------------------------------------------------------------------


def _add_reproduce(sub) -> None:
    from conav_jax.models.policy import ENCODERS
    from conav_jax.eval.reproduce import BUDGETS, LARGE_PANORAMA_DAGGER_EPISODES, STAGES, ReproduceConfig

    d = {f.name: f.default for f in dataclasses.fields(ReproduceConfig)}

    p = sub.add_parser(
        "reproduce", help="the paper's Tables 2 and 3: every stage from data to tables, resumable",
        description="Generate the data, train the predictors, the learned baselines and every CoNav row "
        "(Table 3's five intention ablations and DAgger, each for --seeds seeds), evaluate every agent on the "
        "val split and write results.json and tables.md. Stages already done are skipped; a stage cut short "
        "resumes where it stopped (every training run resumes from its checkpoints).")
    h, w = d["resolution"]
    p.add_argument("--preset", choices=sorted(BUDGETS), default=d["preset"])
    p.add_argument("--out", required=True, help="output directory (data, runs, eval, results.json, tables.md)")
    p.add_argument("--seeds", type=int, default=d["seeds"],
                   help=f"training seeds of every learned CoNav row (default {d['seeds']})")
    p.add_argument("--stage", choices=STAGES, default=None,
                   help="run only this stage (default: every stage not done); a command whose runs are not trained "
                   "yet waits, and the stage stays to run")
    p.add_argument("--resolution", type=parse_resolution, default=d["resolution"], metavar="HxW",
                   help=f"panorama HxW of every agent (default the paper's {h}x{w})")
    p.add_argument("--workers", type=int, default=min(d["workers"], os.cpu_count() or 1),
                   help="dataset generation processes")
    p.add_argument("--dagger-beta", type=float, default=d["dagger_beta"], metavar="P",
                   help="DAgger with the expert acting at a step of round r with probability P**r (`conav train "
                        "policy --dagger-beta`); 0 (default): the policy alone. Other values train and evaluate runs "
                        "of their own (runs/dagger_betaP_s*), and the tables show every DAgger variant evaluated")
    p.add_argument("--dagger-rounds", type=int, default=d["dagger_rounds"], metavar="N",
                   help="DAgger rounds after BC (default: the preset's, " +
                        ", ".join(f"{k} {b.dagger_rounds}" for k, b in BUDGETS.items()) +
                        "); another count trains and evaluates runs of its own (runs/dagger[_betaP]_roundsN_s*)")
    p.add_argument("--dagger-episodes", type=int, default=d["dagger_episodes"], metavar="N",
                   help="train episodes each DAgger round records (`conav train policy --dagger-episodes`; default: "
                        f"{LARGE_PANORAMA_DAGGER_EPISODES} at panoramas of 112x448 and more, else all the policy's); "
                        "another count trains and evaluates runs of its own (runs/dagger[...]_episodesN_s*)")
    p.add_argument("--encoder", choices=sorted(ENCODERS), default=d["encoder"],
                   help="the CoNav policy's panorama encoder in every BC and DAgger run (`conav train policy "
                        f"--encoder`; default {d['encoder']}, the published runs'; patch trains about 2x faster at "
                        "112x448); one OUT directory holds one encoder")
    p.add_argument("--mirror", action="store_true",
                   help="train the intention predictor on frames mirrored half the time (`conav train intention --mirror`)")
    p.add_argument("--seen-objects", action="store_true",
                   help="the intention predictor weighs activities by whether the robot's panoramas have shown their "
                   "object (`conav train intention --seen-objects`: oracle segmentation, listed as privileged)")
    p.add_argument("--seed", type=int, default=None, metavar="S",
                   help="run only training seed S's commands of the bc, dagger and eval stages (each BC run is "
                        "evaluated as soon as it has trained; an evaluation of a run not trained yet waits): a machine "
                        "with the time for one seed leaves it finished, and its pack small; a stage is done once "
                        "every seed's commands are")
    p.add_argument("--gpus", type=int, default=1, metavar="N",
                   help="run up to N commands at once, each in a process of its own on one GPU (the first N of "
                        "CUDA_VISIBLE_DEVICES, else 0..N-1), a command starting as soon as the runs it reads are made; "
                        "each logs to OUT/logs/ (default 1: one command at a time, in this process, on every visible "
                        "device)")
    p.add_argument("--unpack", default=None, metavar="PACK",
                   help="first unpack a pack.tar written by --stage pack (continuing on a fresh machine)")
    p.add_argument("--dry-run", action="store_true", help="print the stages and their commands, run nothing")
    p.set_defaults(func=_run_reproduce)


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def _run_reproduce(args: argparse.Namespace) -> int:
    # `timeout` and batch schedulers stop a run with SIGTERM: raise, so the command it cut records its time.
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        return _reproduce_stages(args)
    finally:
        signal.signal(signal.SIGTERM, previous)


def _reproduce_stages(args: argparse.Namespace) -> int:
    import shutil
    import subprocess

    from conav_jax.eval import reproduce as rp

    cfg = rp.ReproduceConfig(out=Path(args.out).resolve(), preset=args.preset, seeds=args.seeds,
                             resolution=tuple(args.resolution), workers=args.workers, dagger_beta=args.dagger_beta,
                             dagger_rounds=args.dagger_rounds, dagger_episodes=args.dagger_episodes,
                             encoder=args.encoder, mirror=args.mirror, seen_objects=args.seen_objects)
    if args.gpus < 1:
        print(f"conav reproduce: --gpus must be at least 1, got {args.gpus}", file=sys.stderr)
        return 2
    if args.seed is not None and not 0 <= args.seed < cfg.seeds:
        print(f"conav reproduce: --seed {args.seed} is not one of the run's seeds 0..{cfg.seeds - 1}", file=sys.stderr)
        return 2
    cfg.out.mkdir(parents=True, exist_ok=True)
    if args.unpack:
        print(f"unpacked {len(rp.unpack(Path(args.unpack), cfg.out))} files from {args.unpack}")
    progress = rp.read_progress(cfg.out)
    try:
        rp.check_out(progress, cfg)
    except ValueError as e:
        print(f"conav reproduce: {e}", file=sys.stderr)
        return 2
    plan = rp.plan_stages(cfg)
    # Data are regenerated from their seed on a fresh machine (tables and pack read none: their
    # record of the data's making stays).
    if args.stage not in ("tables", "pack") and not all(p.exists() for p in plan[0].outputs):
        progress["stages"].pop(plan[0].name, None)
        for argv in plan[0].commands:
            progress["commands"].pop(rp.command_key(argv, cfg.out), None)
    stages = [st for st in plan if args.stage in (None, st.name)]
    if args.stage not in (None, plan[0].name, "tables", "pack") and plan[0].name not in progress["stages"]:
        # A stage asked for alone on a machine without the data (a fresh one, after --unpack) makes them first.
        print(f"[{plan[0].name}] the data are missing: making them before [{args.stage}]")
        stages.insert(0, plan[0])
    # CONAV_COMMIT names the commit of a copy of the tree that is not a git checkout.
    commit = os.environ.get("CONAV_COMMIT") or subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
        cwd=Path(__file__).resolve().parents[1]).stdout.strip() or "unknown"
    gpus = rp.visible_gpus() if args.gpus == 1 and not args.dry_run else None
    if gpus is not None and len(gpus) > 1:
        print(f"{len(gpus)} GPUs visible: each command runs on all of them as one device mesh; --gpus {len(gpus)} "
              "runs that many commands at once instead, one GPU each", flush=True)
    if args.gpus > 1 and not args.dry_run:
        stages = _reproduce_parallel(args, cfg, plan, stages, progress)
        if isinstance(stages, int):
            return stages
    for st in stages:
        todo = [argv for argv in st.commands if rp.command_key(argv, cfg.out) not in progress["commands"]]
        if not args.dry_run:
            # A stage asked for alone runs what it can: a command whose runs are not trained yet waits
            # (the learned baselines' evaluations before their training, say) instead of failing.
            todo, waiting = rp.ready_commands(plan, st, rp.stage_seed(st, args.seed), set(progress["commands"]),
                                             cfg.out)
            for argv in waiting:
                print(f"[{st.name}] waits for the runs it reads: conav {shlex.join(argv)}")
        if args.dry_run:
            print(f"[{st.name}] {'done' if st.name in progress['stages'] and not todo else 'to run'}")
            for argv in st.commands:
                line = f"copy {argv[1]} -> {argv[2]}" if argv[0] == "@copy" else f"conav {shlex.join(argv)}"
                print(f"  {'(done) ' if rp.command_key(argv, cfg.out) in progress['commands'] else ''}{line}")
            continue
        if st.name in progress["stages"] and not todo and st.name not in ("tables", "pack"):  # those two are of now
            print(f"[{st.name}] done ({progress['stages'][st.name]:.0f} s), skipped")
            continue
        t_stage = time.perf_counter()
        for argv in todo:
            print(f"\n$ conav {shlex.join(argv)}" if argv[0] != "@copy" else f"\ncopy {argv[1]} -> {argv[2]}", flush=True)
            t0, rc = time.perf_counter(), 0
            try:
                if argv[0] == "@copy":
                    if not Path(argv[2]).exists():
                        shutil.copytree(argv[1], argv[2])
                else:
                    rc = _run_stage(argv)
            finally:  # a command cut short (failed, interrupted, SIGTERM) still counts its time
                key, seconds = rp.command_key(argv, cfg.out), round(time.perf_counter() - t0, 1)
                if rc or sys.exc_info()[0] is not None:
                    cut = progress.setdefault("cut", {})
                    cut[key] = round(cut.get(key, 0.0) + seconds, 1)
                else:
                    progress["commands"][key] = seconds
                rp.write_progress(cfg.out, progress)
            if rc:
                print(f"conav reproduce: stage {st.name} failed (exit {rc}) at: conav {shlex.join(argv)}")
                return rc
        left = [argv for argv in st.commands if rp.command_key(argv, cfg.out) not in progress["commands"]]
        if left:  # commands waiting for their runs, or with --seed the other seeds' commands
            if args.seed is None:
                print(f"[{st.name}] {len(left)} of the stage's {len(st.commands)} commands wait for their runs: "
                      "the stage is not done", flush=True)
                continue
            mine = sum(rp.command_seed(argv) == args.seed for argv in left)
            print(f"[{st.name}] seed {args.seed}: " + (f"{mine} command(s) wait for their runs" if mine else
                  "its commands done") + f"; {len(left)} of the stage's {len(st.commands)} to run", flush=True)
            continue
        if st.name == "tables":
            extra = {"preset": cfg.preset, "seeds": cfg.seeds, "resolution": "x".join(map(str, cfg.resolution)),
                     "encoder": cfg.encoder,
                     "commit": commit, "command": "conav " + shlex.join(sys.argv[1:] or ["reproduce"]),
                     "stage_seconds": rp.stage_seconds(plan, progress, cfg.out), "command_seconds": progress["commands"],
                     "cut_seconds": progress.get("cut", {})}
            # FileNotFoundError without the scripted agents' evaluation
            results = rp.collect_results(cfg.out, cfg.seeds, extra, cfg.dagger)
            results["episodes"] = json.loads((cfg.out / "eval" / "scripted" / "metrics.json").read_text())["episodes"]
            (cfg.out / "results.json").write_text(json.dumps(results, indent=1) + "\n")
            (cfg.out / "tables.md").write_text(rp.render_tables(results))
        if st.name == "pack":
            path, size, left_out = rp.write_pack(cfg, progress)
            print(f"wrote {path} ({size / 2**20:.1f} MiB)")
            for ckpt in left_out:
                print(f"left out of the pack for want of room: {ckpt.relative_to(cfg.out)} (continued from this "
                      "pack, that run starts its first round again)")
        progress["stages"][st.name] = round(time.perf_counter() - t_stage, 1)
        rp.write_progress(cfg.out, progress)
        print(f"[{st.name}] done in {progress['stages'][st.name]:.0f} s", flush=True)
    if (cfg.out / "tables.md").exists() and not args.dry_run:
        print((cfg.out / "tables.md").read_text())
    return 0


def _reproduce_parallel(args: argparse.Namespace, cfg, plan: list, stages: list, progress: dict) -> list | int:
    """`--gpus N`: every command of `stages` not done (training seed `--seed`'s alone in the seeded
    stages) runs through `reproduce.run_parallel`; stages whose commands are all done are marked so,
    with their commands' summed time. Returns the stages left to run here (tables, pack), or an
    exit code."""
    from conav_jax.eval import reproduce as rp

    work = [st for st in stages if st.name not in ("tables", "pack")]
    if not work:
        return stages
    try:
        gpus = rp.gpu_slots(args.gpus)
    except ValueError as e:
        print(f"conav reproduce: {e}", file=sys.stderr)
        return 2
    import jax

    jax.config.update("jax_platforms", "cpu")  # this process runs no program: its GPUs are the commands'
    todo = []
    for st in work:
        seed = rp.stage_seed(st, args.seed)
        todo += [argv for argv in st.commands if rp.command_key(argv, cfg.out) not in progress["commands"]
                 and seed in (None, rp.command_seed(argv))]
    print(f"{len(todo)} command(s) to run, up to {len(gpus)} at once on GPU(s) {', '.join(gpus)}", flush=True)
    t0 = time.perf_counter()
    rc, waiting = rp.run_parallel(plan, todo, cfg.out, progress, gpus, args.compile_cache)
    for argv in waiting:
        print(f"{'not started after the failure' if rc else 'waits for the runs it reads'}: conav {shlex.join(argv)}")
    for st in work:
        keys = [rp.command_key(argv, cfg.out) for argv in st.commands]
        if all(k in progress["commands"] for k in keys):
            progress["stages"][st.name] = round(sum(progress["commands"][k] for k in keys), 1)
    rp.write_progress(cfg.out, progress)
    print(f"{len(todo) - len(waiting)} command(s) ended in {time.perf_counter() - t0:.0f} s", flush=True)
    if rc:
        print(f"conav reproduce: a command failed (exit {rc}); its log is named above", file=sys.stderr)
        return rc
    return [st for st in stages if st.name in ("tables", "pack")]


# -- conav bench -----------------------------------------------------------------------------------


def _add_bench(sub) -> None:
    from conav_jax.models.policy import CONV_DTYPES, DEFAULT_ENCODER, ENCODERS
    from conav_jax.envs.agents.registry import AGENTS
    from conav_jax.envs.config import SENSOR_KINDS
    from conav_jax.train.bench import DEFAULT_BATCH, SETUPS

    bench = sub.add_parser("bench", help="throughput benchmarks (run them on a GPU)")
    what = bench.add_subparsers(dest="bench", metavar="WHAT", required=True)

    p = what.add_parser("sim", help="simulator throughput: env steps/s with sensors")
    p.add_argument("--data", default=None, help="dataset dir (default: generate the tiny preset in a temp dir)")
    p.add_argument("--split", default="val")
    p.add_argument("--batch", type=int, nargs="+", default=[1024])
    p.add_argument("--resolution", type=parse_resolution, nargs="+", default=[(112, 448)], metavar="HxW")
    p.add_argument("--sensor", nargs="+", choices=[*SENSOR_KINDS, "both"], default=["auto"],
                   help="sensor kinds to time (both = fast and reference)")
    p.add_argument("--fast-min", choices=["reduce", "unroll"], default=None, help="fast caster: min over geoms as")
    p.add_argument("--steps", type=int, default=20, help="env steps per timed call")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--what", choices=["step", "sensor", "breakdown", "compile"], default="step",
                   help="step: full env steps (physics, humanoid, sensors); sensor: panoramas only; "
                   "breakdown: physics, humanoid, sensors and the full step timed separately, plus the floor; "
                   "compile: compile seconds of the batched reset, step, and both in one program (run it with "
                   "--compile-cache off)")
    p.add_argument("--pallas-block-w", type=int, default=None, help="pallas caster: columns per program")
    p.add_argument("--pallas-num-warps", type=int, default=None, help="pallas caster: warps per program")
    p.add_argument("--physics", type=parse_physics_override, nargs="+", default=[], metavar="NAME=VALUE",
                   help="PhysicsConfig fields to override, e.g. timestep_s=0.02 solver_iterations=2 substep_unroll=10")
    p.add_argument("--json", action="store_true", help="print one JSON line per configuration")
    _devices_arg(p)
    p.set_defaults(func=_run_bench_sim)

    p = what.add_parser("intention", help="an intention run's top-1/top-5 on a split, by route, with P(B | A) "
                        "counted on the train split, with the activity graph's links alone, and counted with "
                        "activities restricted to the object categories the robot's panoramas showed")
    p.add_argument("--run", required=True, metavar="RUN", help="a `conav train intention` run")
    p.add_argument("--data", required=True, metavar="DIR", help="the dataset it was trained on")
    p.add_argument("--split", default="val", help="the split to score (default val)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_run_bench_intention)

    p = what.add_parser("labels", help="the expert's labels on its own states and on a policy run's (what a DAgger "
                        "round trains on): turns in place, forward speed, steps after the human's arrival")
    p.add_argument("--run", required=True, metavar="RUN", help="a `conav train policy` run")
    p.add_argument("--data", required=True, metavar="DIR", help="dataset (its train split)")
    p.add_argument("--episodes", type=int, default=96, help="the first N train episodes (default 96)")
    p.add_argument("--intention", default=None, metavar="RUN", help="intention run (default: the one the run names)")
    p.add_argument("--trajectory", default=None, metavar="RUN", help="trajectory run (default: the one the run names)")
    p.add_argument("--batch", type=int, default=None, help="episodes per rollout call (default: what fits recording's memory budget)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_run_bench_labels)

    p = what.add_parser("train", help="training throughput: samples/s of a model's jitted update")
    p.add_argument("--model", choices=sorted(SETUPS), required=True)
    p.add_argument("--batch", type=int, nargs="+", default=None, help=f"samples per update (default {DEFAULT_BATCH})")
    p.add_argument("--resolution", type=parse_resolution, default=(112, 448), metavar="HxW", help="policy panorama HxW")
    p.add_argument("--steps", type=int, default=10, help="updates per timed call")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--remat", action="store_true",
                   help="policy: encode one time step at a time under jax.checkpoint (less memory, more compute)")
    p.add_argument("--conv-dtype", choices=sorted(CONV_DTYPES), default="float32",
                   help="policy: dtype of the CNN's convolutions and activations (PolicyConfig.conv_dtype; float32 accumulation)")
    p.add_argument("--encoder", choices=sorted(ENCODERS), default=None,
                   help=f"policy: the panorama CNN (PolicyConfig's ENCODERS; default {DEFAULT_ENCODER})")
    p.add_argument("--json", action="store_true", help="print one JSON line per batch size")
    _devices_arg(p)
    p.set_defaults(func=_run_bench_train)

    p = what.add_parser("eval", help="evaluation throughput: val episodes/min for one agent")
    p.add_argument("--data", default=None, help="dataset dir (default: generate the tiny preset in a temp dir)")
    p.add_argument("--split", default="val")
    p.add_argument("--agent", default="pioneer", help=f"one of {', '.join(AGENTS)}")
    p.add_argument("--checkpoint", default=None,
                   help="run dir of the learned agent (conav, ppo, objectgoal-oracle, objectgoal-predicted, imagegoal)")
    _intention_args(p)
    p.add_argument("--batch", type=int, default=256)
    _resolution_arg(p, "(default with a trained run: the run's)")
    p.add_argument("--sensor", choices=SENSOR_KINDS, default="auto",
                   help="panorama caster (envs.SensorConfig.kind; auto: pallas on one GPU, else fast)")
    p.add_argument("--mode", choices=["sweep", "fixed"], default="sweep",
                   help="sweep: the split through conav eval's evaluator; fixed: one full-length batch")
    p.add_argument("--episodes", type=int, default=None, help="sweep mode: the first N episodes (default: all)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", action="store_true", help="print one JSON line")
    _devices_arg(p)
    p.set_defaults(func=_run_bench_eval)

    p = what.add_parser("render", help="our panorama caster against MuJoCo Warp's batch renderer (needs warp-lang)")
    p.add_argument("--data", default=None, help="dataset dir (default: generate the tiny preset in a temp dir)")
    p.add_argument("--split", default="val")
    p.add_argument("--batch", type=int, nargs="+", default=[1024])
    p.add_argument("--resolution", type=parse_resolution, nargs="+", default=[(112, 448)], metavar="HxW")
    p.add_argument("--sensor", choices=[k for k in SENSOR_KINDS if k != "reference"], default="auto",
                   help="our caster (auto: pallas on one GPU, else fast)")
    p.add_argument("--rays", choices=["panorama", "pinhole", "both"], default="both",
                   help="MuJoCo Warp's rays: panorama (our equirectangular rays in its four cameras), "
                   "pinhole (its perspective cameras), or both")
    p.add_argument("--steps", type=int, default=10, help="panoramas per robot per timed call")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--check-batch", type=int, default=64, help="worlds the per-pixel agreement is measured on")
    p.add_argument("--bvh-episode", type=int, default=0,
                   help="episode whose scene MuJoCo Warp's BVH topology is built from (it only refits it after); "
                   "-1: the model's padding poses")
    p.add_argument("--json", action="store_true", help="print one JSON line per resolution and batch")
    p.set_defaults(func=_run_bench_render)


def _run_bench_sim(args: argparse.Namespace) -> int:
    from conav_jax.parallel import make_mesh
    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.bench import bench_sim
    from conav_jax.envs.config import PhysicsConfig

    physics = PhysicsConfig(**dict(args.physics))
    tmp = None if args.data is not None else _tiny_dataset()
    data = args.data or tmp.name
    # The breakdown times single-device stages; the other modes split the batch over the mesh.
    mesh = make_mesh(args.devices) if args.devices != 1 and args.what not in ("breakdown", "compile") else None
    kinds = []
    for k in args.sensor:
        for kk in (["fast", "reference"] if k == "both" else [k]):
            if kk not in kinds:
                kinds.append(kk)
    for (h, w) in args.resolution:
        for kind in kinds:
            extra = {name: getattr(args, name) for name in ("fast_min", "pallas_block_w", "pallas_num_warps")
                     if getattr(args, name) is not None}
            cfg = EnvConfig(sensor=SensorConfig(height=h, width=w, kind=kind, **extra), physics=physics)
            env = ConavEnv(data, args.split, cfg)
            kind = env.config.sensor.kind  # what "auto" became here
            if kind == "pallas" and mesh is not None and mesh.size > 1:
                raise ValueError("the pallas caster runs on one device (XLA cannot partition a Pallas call): "
                                 "use --sensor fast with several devices, or --devices 1")
            for batch in args.batch:
                res = {"sensor": kind, "resolution": f"{h}x{w}", "physics_impl": env.config.physics.impl,
                       **bench_sim(env, batch, args.steps, args.repeats, args.what, mesh)}
                if args.physics:
                    res["physics_overrides"] = dict(args.physics)
                if kind == "fast":
                    res["fast_min"] = env.config.sensor.fast_min
                if kind == "pallas":
                    res["pallas"] = {"block_w": cfg.sensor.pallas_block_w, "num_warps": cfg.sensor.pallas_num_warps}
                if args.json or args.what in ("breakdown", "compile"):
                    print(json.dumps(res), flush=True)
                else:
                    rate = res.get("env_steps_per_s", res.get("frames_per_s"))
                    unit = "env steps/s" if args.what == "step" else "panoramas/s"
                    print(f"{res['device']} sensor={kind} physics={res['physics_impl']} res={h}x{w} batch={batch}: "
                          f"{rate:,.0f} {unit} (median of "
                          f"{args.repeats}), compile {res['compile_and_first_call_s']} s, peak mem {res['peak_bytes_in_use']}",
                          flush=True)
    if tmp is not None:
        tmp.cleanup()
    return 0


def _run_bench_intention(args: argparse.Namespace) -> int:
    from conav_jax.train.intention import evaluate_run

    res = evaluate_run(args.run, args.data, args.split)
    if args.json:
        print(json.dumps({"run": str(args.run), "split": args.split, **res}), flush=True)
        return 0
    v = res["counted"]
    print(f"{args.run} on {args.split}: watched activity A top-1 {v.get('activity_a_top1', float('nan')):.3f}, "
          f"top-5 {v.get('activity_a_top5', float('nan')):.3f}, top-1 using the true A's object "
          f"{v.get('activity_a_object_top1', float('nan')):.3f}")
    for head, name in (("activity", "activity B"), ("object", "object B")):
        for route, label in (("counted", "P(B | A) counted on train"), ("graph", "the graph's links, uniform"),
                             ("counted_seen_objects", "P(B | A) counted on train, seen objects only")):
            r = res[route]
            print(f"  {name}, graph route through {label}: predictor output top-1 {r[f'{head}_top1']:.3f} / "
                  f"top-5 {r[f'{head}_top5']:.3f}; graph route alone {r.get(f'{head}_top1_generator_graph_prior', float('nan')):.3f}")
        print(f"  {name}, direct heads alone: top-1 {v[f'{head}_top1_direct']:.3f}; prior (most frequent B given the "
              f"true A) {v[f'prior_{head}_top1']:.3f}")
    return 0


def _run_bench_labels(args: argparse.Namespace) -> int:
    from conav_jax.train.policy import expert_label_statistics

    res = expert_label_statistics(args.data, args.run, args.episodes, args.intention, args.trajectory, args.batch,
                                  args.seed)
    if args.json:
        print(json.dumps({"run": str(args.run), "data": str(args.data), **res}), flush=True)
        return 0
    note = "" if res["data_is_the_runs"] else " (not the data the run was trained on)"
    print(f"{args.run} on the first {res['episodes']} train episodes of {args.data}{note}:")
    for who, title in (("expert", "expert acting (behaviour cloning's data)"), ("policy", "policy acting (a DAgger round's)")):
        r = res[who]
        print(f"  {title}: {r['steps_per_episode']:.0f} steps an episode, {100 * r['after_arrival_share']:.0f}% after the "
              f"human's arrival; labels turning in place {100 * r['turn_in_place_share']:.0f}% "
              f"({100 * r['full_turn_share_of_turns']:.0f}% of them at full rate), label v_lin {r['label_v_lin_mean']:+.2f}, "
              f"action v_lin {r['action_v_lin_mean']:+.2f}, |action - label| {r['action_label_l1']:.2f}")
    return 0


def _run_bench_train(args: argparse.Namespace) -> int:
    from conav_jax.parallel import make_mesh
    from conav_jax.train.bench import DEFAULT_BATCH, bench_train

    mesh = make_mesh(args.devices) if args.devices != 1 else None
    for batch in args.batch or [DEFAULT_BATCH[args.model]]:
        res = bench_train(args.model, batch, args.resolution, args.steps, args.repeats, mesh, args.remat, args.conv_dtype,
                          args.encoder)
        if args.json:
            print(json.dumps(res), flush=True)
        else:
            shape = ", ".join(f"{k}={res[k]}" for k in ("resolution", "frames", "sequence", "history", "conv_dtype", "encoder")
                              if k in res)
            print(f"{res['device']} {res['model']} batch={batch} {shape}: {res['samples_per_s']:,.0f} samples/s "
                  f"({res['updates_per_s']:.1f} updates/s, median of {args.repeats}; "
                  f"compile + first call {res['compile_and_first_call_s']} s)", flush=True)
    return 0


def _run_bench_eval(args: argparse.Namespace) -> int:
    from conav_jax.parallel import check_divisible
    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.agents.registry import check_agent, make_agent, run_resolution
    from conav_jax.eval.bench import bench_eval, bench_sweep

    spec = check_agent(args.agent, args.checkpoint)
    predictors = _intention_kwargs(args)
    if predictors and not spec.takes_intentions:
        raise ValueError(f"agent {args.agent!r} reads no intention inputs (--intention / --trajectory / "
                         "--ground-truth-intentions)")
    if args.batch < 1 or args.repeats < 1 or (args.episodes is not None and args.episodes < 1):
        raise ValueError("--batch, --repeats and --episodes must be at least 1")
    h, w = run_resolution([(args.agent, args.checkpoint)] if spec.needs_checkpoint else [], args.resolution)
    mesh = _mesh(args)
    check_divisible(args.batch, mesh, "--batch")
    tmp = None if args.data is not None else _tiny_dataset()
    env = ConavEnv(args.data or tmp.name, args.split, EnvConfig(sensor=SensorConfig(height=h, width=w, kind=args.sensor)))
    agent = make_agent(args.agent, env, args.checkpoint, **predictors)
    res = {"agent": args.agent, "mode": args.mode, "resolution": f"{h}x{w}", "sensor": env.config.sensor.kind,
           "physics_impl": env.config.physics.impl}
    if args.mode == "sweep":
        res.update(bench_sweep(env, agent, args.batch, args.repeats, args.episodes, mesh))
    else:
        res.update(bench_eval(env, agent, args.batch, args.repeats, mesh))
    if args.json:
        print(json.dumps(res), flush=True)
    elif args.mode == "sweep":
        print(f"{res['devices']} x {res['device']} agent={args.agent} res={h}x{w} sensor={res['sensor']} "
              f"physics={res['physics_impl']} lanes={args.batch}: "
              f"{res['episodes']} episodes (mean {res['mean_episode_steps']} steps, longest {res['longest_episode_steps']}) "
              f"in {res['median_sweep_s']} s = {res['episodes_per_min']:,.1f} episodes/min (median of {args.repeats}); "
              f"compile + first sweep {res['compile_and_first_sweep_s']} s", flush=True)
    else:
        print(f"{res['devices']} x {res['device']} agent={args.agent} res={h}x{w} sensor={res['sensor']} batch={args.batch} "
              f"({res['steps_per_episode']} steps/episode): {res['episodes_per_min']:,.1f} episodes/min = "
              f"{res['env_steps_per_s']:,.0f} env steps/s ({res['env_steps_per_s_per_device']:,.0f} per device; "
              f"median of {args.repeats}), compile {res['compile_and_first_call_s']} s", flush=True)
    if tmp is not None:
        tmp.cleanup()
    return 0


def _run_bench_render(args: argparse.Namespace) -> int:
    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.bench import bench_render

    if min(args.batch) < 1 or args.repeats < 1 or args.steps < 1 or args.check_batch < 1:
        raise ValueError("--batch, --repeats, --steps and --check-batch must be at least 1")
    rays = ("panorama", "pinhole") if args.rays == "both" else (args.rays,)
    tmp = None if args.data is not None else _tiny_dataset()
    data = args.data or tmp.name
    for (h, w) in args.resolution:
        env = ConavEnv(data, args.split, EnvConfig(sensor=SensorConfig(height=h, width=w, kind=args.sensor)))
        for batch in args.batch:
            res = bench_render(env, batch, args.repeats, args.steps, rays, args.check_batch,
                               None if args.bvh_episode < 0 else args.bvh_episode)
            if args.json:
                print(json.dumps(res), flush=True)
                continue
            ours = res["ours"]
            print(f"{res['device']} res={h}x{w} batch={batch}: ours ({ours['sensor']}) {ours['panoramas_per_s']:,.0f} "
                  f"panoramas/s, compile {ours['compile_and_first_call_s']} s, XLA temp {ours['xla_temp_bytes']} B, "
                  f"peak mem {ours['peak_bytes_in_use']}", flush=True)
            for layout in rays:
                mj, agree = res[f"mjwarp_{layout}"], res[f"mjwarp_{layout}"]["agreement"]
                print(f"  MuJoCo Warp ({layout} rays, 4 x {mj['camera_resolution']}): {mj['panoramas_per_s']:,.0f} "
                      f"panoramas/s, compile {mj['compile_and_first_call_s']} s, context {mj['context_create_s']} s "
                      f"and {mj['warp_context_bytes']} B, XLA temp {mj['xla_temp_bytes']} B, peak mem "
                      f"{mj['peak_bytes_in_use']}; depth vs ours on {agree['pixels_compared']} px: max "
                      f"{agree['depth_abs_diff_max_m']:.4g} m, median {agree['depth_abs_diff_median_m']:.3g} m, "
                      f"{100 * agree['depth_within_1cm']:.2f}% within 1 cm, ids agree "
                      f"{100 * agree['geom_id_agreement']:.2f}%", flush=True)
    if tmp is not None:
        tmp.cleanup()
    return 0


# -- the dispatcher --------------------------------------------------------------------------------


def default_compile_cache_dir() -> Path:
    """Where compiled XLA programs are kept between runs: $XDG_CACHE_HOME/conav_jax/xla (or ~/.cache/...)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "conav_jax" / "xla"


def enable_compile_cache(setting: str | None) -> Path | None:
    """Turn on JAX's persistent compilation cache: `setting` a directory, "off", or None for
    $CONAV_COMPILE_CACHE, else the default directory. Returns the directory (None when off).
    Every program is kept, whatever its compile time: a CPU run compiles many small ones."""
    setting = setting or os.environ.get(COMPILE_CACHE_ENV) or str(default_compile_cache_dir())
    if setting.lower() in ("off", "none", "0", ""):
        return None
    import jax

    path = Path(setting).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="conav", description="CoNav: batched human-centered collaborative navigation in MuJoCo MJX")
    parser.add_argument("--version", action="version", version=f"conav_jax {__version__}")
    parser.add_argument("--compile-cache", default=None, metavar="DIR|off",
                        help=f"keep compiled programs in DIR between runs (default: ${COMPILE_CACHE_ENV}, else "
                        f"{default_compile_cache_dir()}); off: compile every time")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_generate, _add_train, _add_eval, _add_view, _add_demo, _add_curve, _add_reproduce, _add_bench):
        add(sub)
    return parser


def main(argv: list[str] | None = None, compile_cache: bool = True) -> int:
    """Run one `conav` command; its exit code. `compile_cache=False` leaves JAX's cache as it is
    (the demo's stages run inside one command)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    try:
        if compile_cache:
            enable_compile_cache(args.compile_cache)
        if hasattr(args, "devices"):  # a data-parallel command: join a multi-host run first
            from conav_jax.parallel import maybe_initialize_distributed

            maybe_initialize_distributed()
        rc = int(args.func(args) or 0)
        sys.stdout.flush()  # here, where a closed pipe is caught, not at exit
        return rc
    except (ValueError, FileNotFoundError) as e:
        print(f"conav {args.command}: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader of our output stopped (`conav ... | head`): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # so the exit's flush cannot fail again
        return 1


if __name__ == "__main__":
    sys.exit(main())
