"""`conav bench sim`: env steps per second of step + sensors, compile time and memory.

A batch of episodes is reset and stepped with random actions inside one jitted `lax.scan`;
after a compile-and-warm-up call, the median of repeated timed calls (block_until_ready around
each) gives steps/s = batch * steps / seconds. Prints the device, batch and resolution.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time

import jax
import jax.numpy as jnp


def parse_resolution(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must look like 112x448, got {text!r}") from None
    return h, w


def add_bench_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="simulator throughput: env steps/s with sensors")
    p.add_argument("--data", default=None, help="dataset dir (default: generate the tiny preset in a temp dir)")
    p.add_argument("--split", default="val")
    p.add_argument("--batch", type=int, nargs="+", default=[1024])
    p.add_argument("--resolution", type=parse_resolution, nargs="+", default=[(112, 448)])
    p.add_argument("--sensor", choices=["fast", "reference", "both"], default="fast")
    p.add_argument("--steps", type=int, default=20, help="env steps per timed call")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--geoms-per-pass", type=int, default=None, help="fast caster geoms per pass")
    p.add_argument("--what", choices=["step", "sensor"], default="step",
                   help="step: full env steps (physics, humanoid, sensors); sensor: panoramas only")
    p.add_argument("--json", action="store_true", help="print one JSON line per configuration")
    p.set_defaults(func=run_bench_sim)


def _memory_bytes() -> int | None:
    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def _sensor_run(env, batch: int, steps: int):
    """Panoramas only: `steps` frames of `batch` robots at random yaws in their start poses."""
    n = env.num_episodes
    reset = jax.vmap(env.reset_to_episode)

    @jax.jit
    def run(key):
        state = reset(jax.random.split(key, batch), jnp.arange(batch) % n)
        d = state.pipeline_state
        episodes = state.info["episode"]

        def body(total, k):
            yaw = jax.random.uniform(k, (batch,), minval=-3.14, maxval=3.14)
            dd = d.replace(qpos=d.qpos.at[:, 2].set(yaw))
            depth, _ = jax.vmap(lambda di, e: env.panorama(env._episode_model(e, di.qpos[:2]), di, e))(dd, episodes)
            return total + depth.mean(), None

        total, _ = jax.lax.scan(body, jnp.zeros(()), jax.random.split(key, steps))
        return total

    return run


def bench_sim(env, batch: int, steps: int, repeats: int, what: str = "step") -> dict:
    """Time `steps` env steps (or panoramas) of `batch` episodes; returns a dict of figures."""
    n = env.num_episodes
    reset = jax.vmap(env.reset_to_episode)
    step = jax.vmap(env.step)

    @jax.jit
    def run_steps(key):
        keys = jax.random.split(key, batch)
        state = reset(keys, jnp.arange(batch) % n)

        def body(state, k):
            a = jax.random.uniform(k, (batch, 2), minval=-1.0, maxval=1.0)
            state = step(state, a)
            return state, state.reward.sum()

        state, r = jax.lax.scan(body, state, jax.random.split(key, steps))
        return r.sum() + state.obs["rgbd"][:, 0, 0, 3].sum()

    run = run_steps if what == "step" else _sensor_run(env, batch, steps)
    t0 = time.perf_counter()
    jax.block_until_ready(run(jax.random.PRNGKey(0)))
    compile_s = time.perf_counter() - t0
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(run(jax.random.PRNGKey(r + 1)))
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    return {
        "device": jax.devices()[0].device_kind,
        "batch": batch,
        "steps_per_call": steps,
        "compile_and_first_call_s": round(compile_s, 2),
        "median_call_s": round(med, 4),
        "what": what,
        ("env_steps_per_s" if what == "step" else "frames_per_s"): round(batch * steps / med, 1),
        "peak_bytes_in_use": _memory_bytes(),
    }


def run_bench_sim(args: argparse.Namespace) -> int:
    from envs import ConavEnv, EnvConfig, SensorConfig

    data = args.data
    tmp = None
    if data is None:
        from conav_jax.episodes import generate_dataset
        from conav_jax.presets import preset

        tmp = tempfile.TemporaryDirectory()
        data = tmp.name
        generate_dataset(preset("tiny"), data)
    kinds = ["fast", "reference"] if args.sensor == "both" else [args.sensor]
    for (h, w) in args.resolution:
        for kind in kinds:
            extra = {} if args.geoms_per_pass is None else {"geoms_per_pass": args.geoms_per_pass}
            cfg = EnvConfig(sensor=SensorConfig(height=h, width=w, kind=kind, **extra))
            env = ConavEnv(data, args.split, cfg)
            for batch in args.batch:
                res = {"sensor": kind, "resolution": f"{h}x{w}", **bench_sim(env, batch, args.steps, args.repeats, args.what)}
                if args.json:
                    print(json.dumps(res), flush=True)
                else:
                    rate = res.get("env_steps_per_s", res.get("frames_per_s"))
                    unit = "env steps/s" if args.what == "step" else "panoramas/s"
                    print(
                        f"{res['device']} sensor={kind} res={h}x{w} batch={batch}: "
                        f"{rate:,.0f} {unit} (median of {args.repeats}), "
                        f"compile {res['compile_and_first_call_s']} s, peak mem {res['peak_bytes_in_use']}",
                        flush=True,
                    )
    if tmp is not None:
        tmp.cleanup()
    return 0
