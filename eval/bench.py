"""`conav bench eval`: evaluation throughput, val episodes per minute for one agent.

`--mode sweep` (default): the whole split (or its first `--episodes`) through the evaluator
`conav eval` uses (envs.rollout.make_evaluator: `batch` lanes, each taking the next episode as
its own ends); after a compile-and-first sweep, the median of repeated timed sweeps gives the
seconds per sweep and episodes/min. `--mode fixed`: one jitted full-length rollout
(envs.rollout.make_rollout) of `batch` episodes, timed the same way: episodes/min = batch /
seconds * 60 and env steps/s. With `--devices N` the lanes (batch) are split over N devices
(conav_jax.parallel). Prints the device, batch and resolution.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time

from conav_jax.parallel import add_devices_arg
from envs.bench import parse_resolution
from envs.agents.registry import AGENTS, check_agent
from eval.sweep import add_intention_args, intention_kwargs_from_args


def add_bench_eval(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="evaluation throughput: val episodes/min for one agent")
    p.add_argument("--data", default=None, help="dataset dir (default: generate the tiny preset in a temp dir)")
    p.add_argument("--split", default="val")
    p.add_argument("--agent", default="pioneer", help=f"one of {', '.join(AGENTS)}")
    p.add_argument("--checkpoint", default=None, help="run dir of the conav (or ppo) agent")
    add_intention_args(p)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--resolution", type=parse_resolution, default=(112, 448))
    p.add_argument("--sensor", choices=["auto", "fast", "pallas", "legacy", "reference"], default="auto",
                   help="panorama caster (envs.SensorConfig.kind; auto: pallas on one GPU, else fast)")
    p.add_argument("--mode", choices=["sweep", "fixed"], default="sweep",
                   help="sweep: the split through conav eval's evaluator; fixed: one full-length batch")
    p.add_argument("--episodes", type=int, default=None, help="sweep mode: the first N episodes (default: all)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", action="store_true", help="print one JSON line")
    add_devices_arg(p)
    p.set_defaults(func=run_bench_eval)


def bench_eval(env, agent, batch: int, repeats: int, mesh=None) -> dict:
    """Time full-length rollouts of `batch` episodes (the split's episodes, cycled), split
    over the devices of `mesh` if given (ValueError unless `batch` divides by their count)."""
    import jax
    import numpy as np

    from conav_jax.parallel import replicate, shard_batch
    from envs.rollout import make_rollout

    steps = env.bank.max_steps
    run = make_rollout(env, agent, steps)
    episodes = np.arange(batch, dtype=np.int32) % env.num_episodes
    episodes = jax.device_put(episodes) if mesh is None else shard_batch(episodes, mesh)

    def key(r: int):
        k = jax.random.PRNGKey(r)
        return k if mesh is None else replicate(k, mesh)

    t0 = time.perf_counter()
    jax.block_until_ready(run(key(0), episodes))
    compile_s = time.perf_counter() - t0
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(run(key(r + 1), episodes))
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    devices = 1 if mesh is None else mesh.size
    return {
        "device": jax.devices()[0].device_kind,
        "devices": devices,
        "batch": batch,
        "steps_per_episode": steps,
        "compile_and_first_call_s": round(compile_s, 2),
        "median_call_s": round(med, 4),
        "episodes_per_min": round(batch / med * 60.0, 1),
        "env_steps_per_s": round(batch * steps / med, 1),
        "env_steps_per_s_per_device": round(batch * steps / med / devices, 1),
    }


def bench_sweep(env, agent, batch: int, repeats: int, episodes: int | None = None, mesh=None) -> dict:
    """Time sweeps of the split's first `episodes` (default all) with `batch` lanes
    (envs.rollout.make_evaluator), the first sweep including the compile."""
    import jax
    import numpy as np

    from envs.rollout import make_evaluator

    if episodes is not None and episodes > env.num_episodes:
        raise ValueError(f"--episodes {episodes}: the split has only {env.num_episodes} episodes")
    n = env.num_episodes if episodes is None else episodes
    evaluator = make_evaluator(env, lambda _: agent, batch, 0, mesh)
    idx = np.arange(n)
    t0 = time.perf_counter()
    evaluator(None, idx)
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        evaluator(None, idx)  # returns host arrays: the sweep has finished
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    t_end = np.asarray(env.bank.t_end)[idx]
    return {
        "device": jax.devices()[0].device_kind,
        "devices": 1 if mesh is None else mesh.size,
        "batch": batch,
        "episodes": n,
        "mean_episode_steps": round(float(t_end.mean()), 1),
        "longest_episode_steps": int(t_end.max()),
        "compile_and_first_sweep_s": round(compile_s, 2),
        "median_sweep_s": round(med, 3),
        "episodes_per_min": round(n / med * 60.0, 1),
    }


def run_bench_eval(args: argparse.Namespace) -> int:
    spec = check_agent(args.agent, args.checkpoint)
    predictors = intention_kwargs_from_args(args)
    if predictors and not spec.takes_intentions:
        raise ValueError(f"agent {args.agent!r} reads no intention inputs (--intention / --trajectory / "
                         "--ground-truth-intentions)")
    if args.batch < 1 or args.repeats < 1 or (args.episodes is not None and args.episodes < 1):
        raise ValueError("--batch, --repeats and --episodes must be at least 1")
    from conav_jax.parallel import check_divisible, make_mesh
    from envs import ConavEnv, EnvConfig, SensorConfig
    from envs.agents.registry import make_agent

    mesh = make_mesh(args.devices)
    check_divisible(args.batch, mesh, "--batch")

    tmp, data = None, args.data
    if data is None:
        from conav_jax.episodes import generate_dataset
        from conav_jax.presets import preset

        tmp = tempfile.TemporaryDirectory()
        data = tmp.name
        generate_dataset(preset("tiny"), data)
    h, w = args.resolution
    env = ConavEnv(data, args.split, EnvConfig(sensor=SensorConfig(height=h, width=w, kind=args.sensor)))
    agent = make_agent(args.agent, env, args.checkpoint, **predictors)
    res = {"agent": args.agent, "mode": args.mode, "resolution": f"{h}x{w}", "sensor": env.config.sensor.kind}
    if args.mode == "sweep":
        res.update(bench_sweep(env, agent, args.batch, args.repeats, args.episodes, mesh))
    else:
        res.update(bench_eval(env, agent, args.batch, args.repeats, mesh))
    if args.json:
        print(json.dumps(res), flush=True)
    elif args.mode == "sweep":
        print(
            f"{res['devices']} x {res['device']} agent={args.agent} res={h}x{w} sensor={res['sensor']} lanes={args.batch}: "
            f"{res['episodes']} episodes (mean {res['mean_episode_steps']} steps, longest {res['longest_episode_steps']}) "
            f"in {res['median_sweep_s']} s = {res['episodes_per_min']:,.1f} episodes/min (median of {args.repeats}); "
            f"compile + first sweep {res['compile_and_first_sweep_s']} s",
            flush=True,
        )
    else:
        print(
            f"{res['devices']} x {res['device']} agent={args.agent} res={h}x{w} sensor={res['sensor']} batch={args.batch} "
            f"({res['steps_per_episode']} steps/episode): {res['episodes_per_min']:,.1f} episodes/min = "
            f"{res['env_steps_per_s']:,.0f} env steps/s ({res['env_steps_per_s_per_device']:,.0f} per device; "
            f"median of {args.repeats}), compile {res['compile_and_first_call_s']} s",
            flush=True,
        )
    if tmp is not None:
        tmp.cleanup()
    return 0
