"""`conav bench WHAT`: throughput benchmarks (simulator, panorama caster against MuJoCo Warp's
renderer, training updates, evaluation sweeps) and the intention and label diagnostics; each
prints the device, batch and resolution, one JSON line per configuration with --json.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
from pathlib import Path

from conav_jax.eval.cli.args import (
    INTENTION_FLAGS,
    agent_run_args,
    devices_arg,
    intention_kwargs,
    mesh,
    parse_physics_override,
    parse_resolution,
    resolution_arg,
    tiny_dataset,
    translate_errors,
    use_pretrained,
)


def add(sub) -> None:
    from conav_jax.models.policy import CONV_DTYPES, DEFAULT_ENCODER, ENCODERS
    from conav_jax.envs.agents.registry import AGENTS
    from conav_jax.envs.config import MATERIALS, SENSOR_KINDS
    from conav_jax.eval.bench import UNTRAINED_AGENTS, UNTRAINED_NETWORK
    from conav_jax.train.bench import DEFAULT_BATCH, LIVE_PARTS, SETUPS

    bench = sub.add_parser("bench", help="throughput benchmarks (run them on a GPU)")
    # One sub-parser per benchmark, each with its `_run_bench_*` below.
    what = bench.add_subparsers(dest="bench", metavar="WHAT", required=True)

    p = what.add_parser("sim", help="simulator throughput: env steps/s with sensors")
    _dataset_args(p)
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
    p.add_argument("--no-pallas-shade", dest="pallas_shade", action="store_false",
                   help="pallas caster: colour instance materials in XLA instead of a Pallas kernel")
    p.add_argument("--materials", nargs="+", choices=MATERIALS, default=["instance"],
                   help="surfaces to time: per-instance materials with shading, or one flat colour per category")
    p.add_argument("--physics", type=parse_physics_override, nargs="+", default=[], metavar="NAME=VALUE",
                   help="PhysicsConfig fields to override, e.g. timestep_s=0.02 solver_iterations=2 substep_unroll=10")
    p.add_argument("--json", action="store_true", help="print one JSON line per configuration")
    devices_arg(p)
    translate_errors(p, mesh="--devices")
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
    devices_arg(p)
    p.set_defaults(func=_run_bench_train)

    p = what.add_parser("live", help="live imitation throughput: env timesteps trained/s of train.live's iteration "
                        "and its parts (simulate, + expert labels, + predictors and learner, + update)")
    p.add_argument("--data", default=None, help="dataset dir (default: a tiny one generated on the fly)")
    p.add_argument("--split", default="train")
    p.add_argument("--resolution", type=parse_resolution, default=(112, 448), metavar="HxW")
    p.add_argument("--lanes", type=int, nargs="+", default=[8192], help="lane counts N to time")
    p.add_argument("--window-steps", type=int, default=4, help="T, control steps per iteration")
    p.add_argument("--beta", type=float, default=0.5, help="the expert's share of the actions")
    p.add_argument("--encoder", default="patch", help="the policy's panorama encoder (models.policy.ENCODERS)")
    p.add_argument("--conv-dtype", default="bfloat16", help="dtype of the policy's convolutions")
    p.add_argument("--ground-truth-intentions", action="store_true",
                   help="no predictors: the learner reads ground truth (default: untrained predictors run)")
    p.add_argument("--remat", action="store_true", help="recompute the encoder for the gradient (LiveConfig.remat)")
    p.add_argument("--profile", default=None, metavar="DIR",
                   help="also trace two iterations into DIR and print their device time by part of the iteration")
    p.add_argument("--parts", nargs="+", default=list(LIVE_PARTS), choices=LIVE_PARTS,
                   help="the cumulative parts to compile and time (update: the whole iteration, what a run pays)")
    p.add_argument("--runs", type=int, default=1, metavar="K",
                   help="time the whole iteration of K runs (seeds 0..K-1) trained together as one program, as "
                        "`conav reproduce --runs-per-process K` trains them (with --parts update)")
    p.add_argument("--repeats", type=int, default=3)
    p.set_defaults(func=_run_bench_live)

    p = what.add_parser("eval", help="evaluation throughput: val episodes/min for one agent")
    _dataset_args(p)
    p.add_argument("--agent", default="pioneer", help=f"one of {', '.join(AGENTS)}")
    agent_run_args(p)
    p.add_argument("--untrained", action="store_true",
                   help="a learned agent (" + ", ".join(UNTRAINED_AGENTS) + ") with freshly initialised weights "
                   "and predictors from the default configs at --resolution, labelled untrained: its sweep speed "
                   "without a trained run")
    p.add_argument("--encoder", default=None, choices=sorted(ENCODERS),
                   help="with --untrained: the policy's panorama encoder (models.policy.ENCODERS; default "
                   f"{UNTRAINED_NETWORK[0]}, as the paper preset's learned runs)")
    p.add_argument("--conv-dtype", default=None, choices=sorted(CONV_DTYPES),
                   help=f"with --untrained: dtype of the policy's convolutions (default {UNTRAINED_NETWORK[1]})")
    translate_errors(p, **INTENTION_FLAGS)
    p.add_argument("--batch", type=int, default=256)
    resolution_arg(p, "(default with a trained run: the run's)")
    p.add_argument("--sensor", choices=SENSOR_KINDS, default="auto",
                   help="panorama caster (envs.SensorConfig.kind; auto: pallas on a GPU, else fast)")
    p.add_argument("--mode", choices=["sweep", "fixed"], default="sweep",
                   help="sweep: the split through conav eval's evaluator; fixed: one full-length batch")
    p.add_argument("--episodes", type=int, default=None, help="sweep mode: the first N episodes (default: all)")
    p.add_argument("--profile", default=None, metavar="DIR",
                   help="sweep mode, one device: also trace the sweep's first --profile-chunks chunks of 16 steps "
                        "into DIR and print their device time by part of a step")
    p.add_argument("--profile-chunks", type=int, default=8, metavar="K",
                   help="chunks of 16 steps a profile traces (the first fills every lane)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", action="store_true", help="print one JSON line")
    devices_arg(p)
    p.set_defaults(func=_run_bench_eval)

    p = what.add_parser("render", help="our panorama caster against MuJoCo Warp's batch renderer (needs warp-lang)")
    _dataset_args(p)
    p.add_argument("--batch", type=int, nargs="+", default=[1024])
    p.add_argument("--resolution", type=parse_resolution, nargs="+", default=[(112, 448)], metavar="HxW")
    p.add_argument("--sensor", choices=[k for k in SENSOR_KINDS if k != "reference"], default="auto",
                   help="our caster (auto: pallas on a GPU, else fast)")
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

    p = what.add_parser("suite", help="the benchmarks BENCHMARKS.md leads with, in turn, each in a process of its "
                        "own, their JSON lines appended to --out with the command and commit (resumes: a benchmark "
                        "already there is skipped)")
    p.add_argument("--out", required=True, help="JSON-lines file the results are appended to")
    p.add_argument("--small", default=None, metavar="DIR", help="`conav generate --preset small` data (simulator)")
    p.add_argument("--paper", default=None, metavar="DIR", help="`conav generate --preset paper` data (val sweeps)")
    p.add_argument("--demo", default=None, metavar="DIR", help="`conav generate --preset demo` data (live iteration)")
    p.add_argument("--only", default=None, metavar="NAME,...", help="these benchmarks of the suite (default: all)")
    p.add_argument("--dry-run", action="store_true", help="print the commands and run nothing")
    p.set_defaults(func=_run_bench_suite)


def _dataset_args(p) -> None:
    """--data and --split of the benchmarks that build an env (without --data: the tiny preset)."""
    p.add_argument("--data", default=None, help="dataset dir (default: generate the tiny preset in a temp dir)")
    p.add_argument("--split", default="val")


def _run_bench_live(args: argparse.Namespace) -> int:
    import jax

    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.eval.bench import untrained_predictors
    from conav_jax.models.policy import encoder_config
    from conav_jax.train.bench import live_throughput
    from conav_jax.train.live import DEFAULT_POLICY

    h, w = args.resolution
    tmp = None if args.data is not None else tiny_dataset()
    env = ConavEnv(args.data or tmp.name, args.split, EnvConfig(sensor=SensorConfig(resolution=(h, w)), end_at_reach=True))
    model = encoder_config(dataclasses.replace(DEFAULT_POLICY, resolution=(h, w), conv_dtype=args.conv_dtype),
                           args.encoder)  # the policy live runs train
    predictors = (None, None) if args.ground_truth_intentions else untrained_predictors(env, jax.random.PRNGKey(0))
    for lanes in args.lanes:
        profile = None if args.profile is None else str(Path(args.profile) / f"lanes{lanes}")
        res = live_throughput(env, model, lanes=lanes, window_steps=args.window_steps, repeats=args.repeats,
                              intention=predictors[0], trajectory=predictors[1], beta=args.beta, remat=args.remat,
                              profile_dir=profile, parts=tuple(args.parts), runs=args.runs)
        print(json.dumps({**res, "encoder": args.encoder, "conv_dtype": args.conv_dtype, "visual_norm": model.visual_norm,
                          "materials": env.config.sensor.materials}), flush=True)
    return 0


def _run_bench_sim(args: argparse.Namespace) -> int:
    from conav_jax.parallel import make_mesh
    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.bench import bench_sim
    from conav_jax.envs.config import PhysicsConfig

    physics = PhysicsConfig(**dict(args.physics))
    tmp = None if args.data is not None else tiny_dataset()
    data = args.data or tmp.name
    # The breakdown and compile times are one device's: without --devices they take one, and
    # bench_sim refuses several asked for; the other modes split the batch over the mesh.
    one_device = args.what in ("breakdown", "compile") and args.devices is None
    mesh = make_mesh(args.devices) if args.devices != 1 and not one_device else None
    kinds = []
    for k in args.sensor:
        for kk in (["fast", "reference"] if k == "both" else [k]):
            if kk not in kinds:
                kinds.append(kk)
    for (h, w) in args.resolution:
        for kind in kinds:
            extra = {name: getattr(args, name) for name in ("fast_min", "pallas_block_w", "pallas_num_warps")
                     if getattr(args, name) is not None}
            extra["pallas_shade"] = args.pallas_shade
            cfg = EnvConfig(sensor=SensorConfig(resolution=(h, w), kind=kind, **extra), physics=physics)
            env = ConavEnv(data, args.split, cfg)
            kind = env.config.sensor.kind  # what "auto" became here
            for batch, materials in itertools.product(args.batch, args.materials):
                res = {"sensor": kind, "resolution": f"{h}x{w}", "physics_impl": env.config.physics.impl,
                       **bench_sim(env, batch, args.steps, args.repeats, args.what, mesh, materials)}
                if args.physics:
                    res["physics_overrides"] = dict(args.physics)
                if kind == "fast":
                    res["fast_min"] = env.config.sensor.fast_min
                if kind == "pallas":
                    res["pallas"] = {"block_w": cfg.sensor.pallas_block_w, "num_warps": cfg.sensor.pallas_num_warps,
                                     "shade": cfg.sensor.pallas_shade}
                if args.json or args.what in ("breakdown", "compile"):
                    print(json.dumps(res), flush=True)
                else:
                    rate = res.get("env_steps_per_s", res.get("frames_per_s"))
                    unit = "env steps/s" if args.what == "step" else "panoramas/s"
                    print(f"{res['device']} sensor={kind} physics={res['physics_impl']} res={h}x{w} batch={batch} "
                          f"materials={res['materials']}: "
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


def _bench_eval_agent(args: argparse.Namespace, env):
    """The agent `conav bench eval` times: a run's, or with --untrained freshly initialised."""
    from conav_jax.envs.agents.registry import make_agent
    from conav_jax.eval.bench import untrained_agent

    if not args.untrained:
        return make_agent(args.agent, env, args.checkpoint, **intention_kwargs(args))
    import jax

    from conav_jax.models.policy import PolicyConfig, encoder_config
    from conav_jax.train import goalnav

    hw = env.config.sensor.resolution
    base = encoder_config(PolicyConfig(resolution=hw, conv_dtype=args.conv_dtype), args.encoder)
    config = {"objectgoal-oracle": goalnav.objectnav_model(hw, base=base),
              "objectgoal-predicted": goalnav.objectnav_model(hw, base=base),
              "imagegoal": goalnav.imagenav_model(hw, base=base)}.get(args.agent, base)
    return untrained_agent(args.agent, env, config, jax.random.PRNGKey(0))


def _run_bench_eval(args: argparse.Namespace) -> int:
    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.agents.registry import AGENTS, run_resolution
    from conav_jax.envs.config import run_materials
    from conav_jax.eval.bench import UNTRAINED, UNTRAINED_NETWORK, bench_eval, bench_sweep
    from conav_jax.parallel import check_divisible

    if args.untrained and (args.checkpoint or args.intention or args.trajectory or args.ground_truth_intentions
                           or args.pretrained):
        raise ValueError("--untrained builds the agent from fresh weights: drop --checkpoint / --intention / "
                         "--trajectory / --ground-truth-intentions / --pretrained")
    if not args.untrained and (args.encoder is not None or args.conv_dtype is not None):
        raise ValueError("--encoder and --conv-dtype set an untrained agent's network (--untrained); a trained "
                         "run's is its own")
    args.encoder = args.encoder or UNTRAINED_NETWORK[0]
    args.conv_dtype = args.conv_dtype or UNTRAINED_NETWORK[1]
    use_pretrained(args, (args.agent,))  # --pretrained: the shipped run and its predictors
    spec = AGENTS.get(args.agent)
    if args.batch < 1 or args.repeats < 1 or args.profile_chunks < 1 or (args.episodes is not None and args.episodes < 1):
        raise ValueError("--batch, --repeats, --profile-chunks and --episodes must be at least 1")
    trained = spec is not None and spec.needs_checkpoint and not args.untrained
    h, w = run_resolution([(args.agent, args.checkpoint)] if trained else [], args.resolution)
    devices = mesh(args)
    check_divisible(args.batch, devices, "--batch")
    tmp = None if args.data is not None else tiny_dataset()
    # A trained run is timed on the materials it was trained on (its loader refuses others).
    materials = run_materials(args.checkpoint) if trained else SensorConfig.materials
    env = ConavEnv(args.data or tmp.name, args.split,
                   EnvConfig(sensor=SensorConfig(resolution=(h, w), kind=args.sensor, materials=materials)))
    agent = _bench_eval_agent(args, env)
    res = {"agent": args.agent, "weights": UNTRAINED if args.untrained else "trained" if trained else "none",
           **({"encoder": args.encoder, "conv_dtype": args.conv_dtype} if args.untrained else {}),
           "mode": args.mode, "resolution": f"{h}x{w}", "sensor": env.config.sensor.kind, "materials": materials,
           "physics_impl": env.config.physics.impl}
    if args.mode == "sweep":
        res.update(bench_sweep(env, agent, args.batch, args.repeats, args.episodes, devices, args.profile,
                               args.profile_chunks))
    elif args.profile is not None:
        raise ValueError("--profile traces sweeps: use --mode sweep")
    else:
        res.update(bench_eval(env, agent, args.batch, args.repeats, devices))
    who = f"{args.agent} ({UNTRAINED})" if args.untrained else args.agent
    if args.json:
        print(json.dumps(res), flush=True)
    elif args.mode == "sweep":
        print(f"{res['devices']} x {res['device']} agent={who} res={h}x{w} sensor={res['sensor']} materials={materials} "
              f"physics={res['physics_impl']} lanes={args.batch}: "
              f"{res['episodes']} episodes (mean {res['mean_episode_steps']} steps, longest {res['longest_episode_steps']}) "
              f"in {res['median_sweep_s']} s = {res['episodes_per_min']:,.1f} episodes/min (median of {args.repeats}); "
              f"compile + first sweep {res['compile_and_first_sweep_s']} s", flush=True)
        if "profile" in res:
            print(f"device ms of the sweep's first {res['profile']['chunks']} chunks by part: "
                  f"{json.dumps(res['profile']['by_scope_ms'])}; trace in "
                  f"{res['profile']['trace_dir']}", flush=True)
    else:
        print(f"{res['devices']} x {res['device']} agent={who} res={h}x{w} sensor={res['sensor']} batch={args.batch} "
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
    tmp = None if args.data is not None else tiny_dataset()
    data = args.data or tmp.name
    for (h, w) in args.resolution:
        env = ConavEnv(data, args.split, EnvConfig(sensor=SensorConfig(resolution=(h, w), kind=args.sensor)))
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


def _run_bench_suite(args: argparse.Namespace) -> int:
    import shlex

    from conav_jax.eval.cli.bench_suite import SUITE, run_suite, suite_command

    names = args.only.split(",") if args.only else list(SUITE)
    data = {"SMALL": args.small, "PAPER": args.paper, "DEMO": args.demo}
    if args.dry_run:
        for name in names:
            print(f"{name}: conav {shlex.join(suite_command(name, data))}")
        return 0
    outcome = run_suite(names, data, Path(args.out))
    failed = [name for name, how in outcome.items() if how == "failed"]
    print(f"suite: {sum(how == 'ran' for how in outcome.values())} ran, "
          f"{sum(how == 'skipped' for how in outcome.values())} already in {args.out}, {len(failed)} failed"
          + (f" ({', '.join(failed)})" if failed else ""))
    return 1 if failed else 0
