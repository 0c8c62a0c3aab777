"""`conav bench sim`'s measurements: env steps per second of step + sensors, compile time and memory.

A batch of episodes is reset and stepped with random actions inside one jitted `lax.scan`;
after a compile-and-warm-up call, the median of repeated timed calls (block_until_ready around
each) gives steps/s = batch * steps / seconds. Prints the device, batch and resolution.

`--what breakdown` times the stages of a step separately, each its own jitted scan over the
same batch: physics (episode model + MJX substeps under random velocity commands), the
humanoid pose update, the sensors (panorama, colours, observations) and the full step; and
prints the floor a perfect kernel could reach: ray-geom tests and observation bytes written per
step against H100 rates (FP32 non-tensor throughput, HBM bandwidth).
"""

from __future__ import annotations

import copy
import dataclasses
import statistics
import time

import jax
import jax.numpy as jnp

from conav_jax.parallel import check_divisible, per_device
from conav_jax.envs.rollout import select_lanes


def peak_memory_bytes() -> int | None:
    """The first device's peak bytes in use so far in this process (JAX's allocator statistics;
    memory reserved but not in use does not count); None where the backend keeps none (CPU)."""
    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def _sensor_run(env, batch: int, steps: int, mesh=None):
    """Panoramas only (RGB-D, coloured in the env's materials): `steps` frames of `batch` robots
    at random yaws in their start poses (each of `mesh`'s devices casting its share, `per_device`)."""
    n = env.num_episodes
    reset = jax.vmap(env.reset_to_episode)

    def lanes(keys, episodes):
        state = reset(keys, episodes)
        d = state.pipeline_state

        def body(total, t):
            yaw = jax.vmap(lambda k: jax.random.uniform(jax.random.fold_in(k, t), (), minval=-3.14, maxval=3.14))(keys)
            dd = d.replace(qpos=d.qpos.at[:, 2].set(yaw))
            rgbd, _ = jax.vmap(env.render)(dd, episodes)
            return total + rgbd.mean(axis=(1, 2, 3)), None

        total, _ = jax.lax.scan(body, jnp.zeros(keys.shape[0]), jnp.arange(steps))
        return total

    run_lanes = per_device(lanes, mesh, (True, True))

    def run(key):
        return run_lanes(jax.random.split(key, batch), jnp.arange(batch) % n).sum()

    return run


# Rates of one H100 SXM the floor is computed against (dense FP32 without tensor cores; HBM3).
H100_FP32_FLOPS = 60e12
H100_HBM_BYTES_PER_S = 3.35e12
# Arithmetic per ray-geom test of the fast caster's per-pixel code (envs/panorama.py): a box is
# ~13 ops (2 max/min, compare, select, multiply, pack, running min), a capsule ~45.
BOX_TEST_FLOPS = 13
CAPSULE_TEST_FLOPS = 45


def sensor_floor(env, batch: int) -> dict:
    """Work per env step of the whole batch and the time a perfect kernel would need."""
    cfg = env.config.sensor
    rays = batch * cfg.height * cfg.width
    boxes, caps = int(env._box_ids.shape[0]), int(env._cap_ids.shape[0])
    flops = rays * (boxes * BOX_TEST_FLOPS + caps * CAPSULE_TEST_FLOPS)
    # Observations written: rgbd (H, W, 4) and front (H, W / 4, 4) float32.
    obs_bytes = batch * cfg.height * cfg.width * 4 * 4 * 5 // 4
    t_flops, t_bytes = flops / H100_FP32_FLOPS, obs_bytes / H100_HBM_BYTES_PER_S
    return {
        "rays_per_step": rays,
        "boxes": boxes,
        "capsules": caps,
        "ray_geom_tests_per_step": rays * (boxes + caps),
        "est_flops_per_step": flops,
        "obs_bytes_written_per_step": obs_bytes,
        "h100_compute_floor_s": t_flops,
        "h100_memory_floor_s": t_bytes,
        "h100_sensor_bound_steps_per_s": round(batch / max(t_flops, t_bytes), 1),
    }


def _stage_runs(env, batch: int, steps: int) -> dict:
    """Jitted scans of `steps` repetitions of each stage of ConavEnv.step, over `batch` envs."""
    n = env.num_episodes
    reset = jax.vmap(env.reset_to_episode)
    task = env.task

    def start(key):
        state = reset(jax.random.split(key, batch), jnp.arange(batch) % n)
        return state.pipeline_state, state.info["episode"]

    @jax.jit
    def physics(key):
        d, ep = start(key)

        def body(d, k):
            a = jax.random.uniform(k, (batch, 2), minval=-1.0, maxval=1.0)
            m = jax.vmap(env._episode_model)(ep, d.qpos[:, :2])
            d = jax.vmap(env._physics)(m, d, a[:, 0] * task.v_max_mps, a[:, 1] * task.w_max_radps)
            return d, None

        d, _ = jax.lax.scan(body, d, jax.random.split(key, steps))
        return d.qpos.sum()

    @jax.jit
    def humanoid(key):
        d, ep = start(key)

        def body(carry, t):
            d, acc = carry
            d = jax.vmap(env._pose_human, in_axes=(0, 0, None))(d, ep, t)
            return (d, acc + d.mocap_pos[:, 0, 0].sum()), None

        (d, acc), _ = jax.lax.scan(body, (d, jnp.zeros(())), jnp.arange(1, steps + 1))
        return acc

    @jax.jit
    def sensors(key):
        d, ep = start(key)

        def body(total, k):
            yaw = jax.random.uniform(k, (batch,), minval=-3.14, maxval=3.14)
            dd = d.replace(qpos=d.qpos.at[:, 2].set(yaw))
            obs = jax.vmap(lambda d, e: env._observe(d, e, ("rgbd", "front")))(dd, ep)
            # Every pixel of both images is read: XLA would otherwise compute only the ones used.
            return total + obs["rgbd"].mean() + obs["front"].mean(), None

        total, _ = jax.lax.scan(body, jnp.zeros(()), jax.random.split(key, steps))
        return total

    return {"physics": physics, "humanoid": humanoid, "sensors": sensors, "step": _step_run(env, batch, steps)}


def step_lanes(env, steps: int, mesh=None):
    """A compiled function (keys (B, 2), episodes (B,)) -> per-lane totals (B,) of `steps` full
    env steps under random actions from each lane's key, run on each of `mesh`'s devices over
    its share of the lanes (`per_device`: one single-device program per device, so the Pallas
    caster runs on every device and nothing is partitioned by XLA); the reference of the
    multi-device benchmarks."""
    reset = jax.vmap(env.reset_to_episode)
    step = jax.vmap(env.step)

    def lanes(keys, episodes):
        state = reset(keys, episodes)

        def body(state, t):
            a = jax.vmap(lambda k: jax.random.uniform(jax.random.fold_in(k, t), (2,), minval=-1.0, maxval=1.0))(keys)
            state = step(state, a)
            return state, state.reward

        state, r = jax.lax.scan(body, state, jnp.arange(steps))
        return r.sum(0) + state.obs["rgbd"][:, 0, 0, 3]

    return per_device(lanes, mesh, (True, True))


def _step_run(env, batch: int, steps: int, mesh=None):
    """Full env steps of `batch` episodes under random actions (`step_lanes`)."""
    run_lanes = step_lanes(env, steps, mesh)

    def run_steps(key):
        return run_lanes(jax.random.split(key, batch), jnp.arange(batch) % env.num_episodes).sum()

    return run_steps


def _time(run, repeats: int) -> tuple[float, float]:
    """(compile + first call seconds, median seconds of `repeats` timed calls)."""
    t0 = time.perf_counter()
    jax.block_until_ready(run(jax.random.PRNGKey(0)))
    compile_s = time.perf_counter() - t0
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(run(jax.random.PRNGKey(r + 1)))
        times.append(time.perf_counter() - t0)
    return compile_s, statistics.median(times)


def bench_breakdown(env, batch: int, steps: int, repeats: int) -> dict:
    """Per-stage seconds per env step (of the whole batch), their rates, and the floor."""
    out = {"device": jax.devices()[0].device_kind, "batch": batch, "steps_per_call": steps, "what": "breakdown"}
    for name, run in _stage_runs(env, batch, steps).items():
        compile_s, med = _time(run, repeats)
        out[name] = {
            "compile_and_first_call_s": round(compile_s, 2),
            "s_per_step": med / steps,
            "env_steps_per_s": round(batch * steps / med, 1),
        }
    parts = sum(out[k]["s_per_step"] for k in ("physics", "humanoid", "sensors"))
    out["rest_of_step_s_per_step"] = out["step"]["s_per_step"] - parts  # contacts, reward, freeze
    out["floor"] = sensor_floor(env, batch)
    out["sensor_s_over_floor"] = round(out["sensors"]["s_per_step"] / max(
        out["floor"]["h100_compute_floor_s"], out["floor"]["h100_memory_floor_s"]), 1)
    out["peak_bytes_in_use"] = peak_memory_bytes()
    return out


def bench_compile(env, batch: int) -> dict:
    """Seconds to trace + lower and to compile the batched reset, the batched step, and one
    program holding both (what an evaluator that refills finished lanes compiles: every
    iteration may reset some lanes while it steps the others), one device, no compile cache."""
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    reset, step = jax.vmap(env.reset), jax.vmap(env.step)
    action = jnp.zeros((batch, env.action_size), jnp.float32)

    def step_or_reset(state, action, keys):  # lane 0 steps, the rest restart
        return select_lanes(jnp.arange(batch) == 0, step(state, action), reset(keys))

    out = {"device": jax.devices()[0].device_kind, "batch": batch, "what": "compile"}
    with jax.enable_checks(False), jax.log_compiles(False):
        for name, fn in (("reset", lambda keys: reset(keys)), ("step", lambda state, action, keys: step(state, action)),
                         ("step_and_reset", step_or_reset)):
            args = (keys,) if name == "reset" else (jax.eval_shape(reset, keys), action, keys)
            t0 = time.perf_counter()
            lowered = jax.jit(fn).lower(*args)
            t1 = time.perf_counter()
            lowered.compile()
            out[name] = {"trace_and_lower_s": round(t1 - t0, 2), "compile_s": round(time.perf_counter() - t1, 2)}
    return out


def with_materials(env, materials: str | None):
    """`env` rendering `materials` (SensorConfig.materials; None: its own): a shallow copy
    sharing the bank and the models, so one process times both without building a second env."""
    if materials is None or materials == env.config.sensor.materials:
        return env
    other = copy.copy(env)
    other.config = dataclasses.replace(env.config, sensor=dataclasses.replace(env.config.sensor, materials=materials))
    return other


def bench_sim(env, batch: int, steps: int, repeats: int, what: str = "step", mesh=None,
              materials: str | None = None) -> dict:
    """Time `steps` env steps (or panoramas) of `batch` episodes (in all, split over `mesh`'s
    devices if given) with the env's sensor rendering `materials` (SensorConfig.materials;
    None: the env's own); returns a dict of figures, rates in total and per device."""
    env = with_materials(env, materials)
    if what in ("compile", "breakdown") and mesh is not None and mesh.size > 1:
        raise ValueError(f"bench_sim.what {what} runs on one device: bench_sim.mesh must hold one, not {mesh.size}")
    if what == "compile":
        return bench_compile(env, batch)
    if what == "breakdown":
        return bench_breakdown(env, batch, steps, repeats)
    if mesh is not None:
        check_divisible(batch, mesh)
    run = _step_run(env, batch, steps, mesh) if what == "step" else _sensor_run(env, batch, steps, mesh)
    compile_s, med = _time(run, repeats)
    devices = 1 if mesh is None else mesh.size
    rate = batch * steps / med
    return {
        "device": jax.devices()[0].device_kind,
        "devices": devices,
        "batch": batch,
        "batch_per_device": batch // devices,
        ("env_steps_per_s_per_device" if what == "step" else "frames_per_s_per_device"): round(rate / devices, 1),
        "steps_per_call": steps,
        "compile_and_first_call_s": round(compile_s, 2),
        "median_call_s": round(med, 4),
        "what": what,
        "materials": env.config.sensor.materials,
        ("env_steps_per_s" if what == "step" else "frames_per_s"): round(rate, 1),
        "peak_bytes_in_use": peak_memory_bytes(),
    }


def bench_render(env, batch: int, repeats: int, steps: int = 10, rays: tuple[str, ...] = ("panorama", "pinhole"),
                 check_batch: int = 64, topology_episode: int | None = 0) -> dict:
    """`conav bench render`: our caster (ConavEnv.render_at with the env's sensor kind) against
    MuJoCo Warp's batch renderer (envs.mjwarp_render: four cameras = one panorama) on the same
    frames: `batch` robots at their episodes' start positions, random yaws, the humanoid at a
    random step; `steps` frames per jitted call, each an RGB-D panorama (B, H, W, 4) as the env
    observes it. Per renderer: panoramas/s (median of `repeats` calls), compile + first call
    seconds, XLA's memory for the program (temporaries, which hold MuJoCo Warp's output buffers)
    and the device's peak bytes in use after it (the process's peak so far: our caster is timed
    first). For MuJoCo Warp also: the render context's creation time and the bytes Warp keeps
    for it (BVH, bounds, ray table), and per-pixel agreement with our caster on `check_batch`
    worlds (envs.mjwarp_render.compare_with_caster) from a second context with segmentation.
    MuJoCo Warp's BVH topology is built from episode `topology_episode`'s scene (None: from the
    model's padding poses; envs.mjwarp_render.seed_topology)."""
    from conav_jax.envs import mjwarp_render

    cfg = env.config.sensor
    n = env.num_episodes
    b = env.bank

    def frames(count: int, key):
        episodes = jnp.arange(count) % n
        k_yaw, k_t = jax.random.split(key)
        yaw = jax.random.uniform(k_yaw, (count,), minval=-jnp.pi, maxval=jnp.pi)
        poses = b.robot_start[episodes].at[:, 2].set(yaw)
        t = (jax.random.uniform(k_t, (count,)) * (b.t_end[episodes] + 1)).astype(jnp.int32)
        return episodes, poses, t

    def timed(render) -> dict:
        def run(key):
            def body(total, k):
                rgbd, _ = render(*frames(batch, k))
                return total + rgbd.mean(), None  # every pixel of every channel is read

            total, _ = jax.lax.scan(body, jnp.zeros(()), jax.random.split(key, steps))
            return total

        t0 = time.perf_counter()
        compiled = jax.jit(run).lower(jax.random.PRNGKey(0)).compile()
        compile_s = time.perf_counter() - t0
        first_s, med = _time(compiled, repeats)
        mem = compiled.memory_analysis()
        return {
            "panoramas_per_s": round(batch * steps / med, 1),
            "median_call_s": round(med, 4),
            "compile_and_first_call_s": round(compile_s + first_s, 2),
            "xla_temp_bytes": None if mem is None else int(mem.temp_size_in_bytes),
            "peak_bytes_in_use": peak_memory_bytes(),
        }

    out = {"device": jax.devices()[0].device_kind, "batch": batch, "resolution": f"{cfg.height}x{cfg.width}",
           "steps_per_call": steps, "what": "render", "ours": {"sensor": cfg.kind, **timed(jax.vmap(env.render_at))}}
    check = frames(min(batch, check_batch), jax.random.PRNGKey(12345))
    for layout in rays:
        r = mjwarp_render.make_renderer(env, batch, layout, topology_episode=topology_episode)
        res = {"rays": layout, "cameras": mjwarp_render.NUM_CAMERAS,
               "camera_resolution": f"{cfg.height}x{cfg.width // mjwarp_render.NUM_CAMERAS}",
               "bvh_topology_episode": topology_episode,
               **timed(lambda e, p, t, renderer=r: mjwarp_render.render_panorama(renderer, e, p, t)),
               "context_create_s": round(r.context_create_s, 3),
               "warp_context_bytes": r.warp_live_bytes, "warp_create_peak_bytes": r.warp_peak_bytes}
        del r  # the context's buffers go with it, before the checking context is made
        checker = mjwarp_render.make_renderer(env, int(check[0].shape[0]), layout, segmentation=True,
                                              topology_episode=topology_episode)
        res["agreement"] = mjwarp_render.compare_with_caster(checker, *check)
        out[f"mjwarp_{layout}"] = res
    return out
