"""`conav bench eval`'s measurements: evaluation throughput, val episodes per minute for one agent.

`--mode sweep` (default): the whole split (or its first `--episodes`) through the evaluator
`conav eval` uses (envs.rollout.make_evaluator: `batch` lanes, each taking the next episode as
its own ends); after a compile-and-first sweep, the median of repeated timed sweeps gives the
seconds per sweep and episodes/min. `--mode fixed`: one jitted full-length rollout
(envs.rollout.make_rollout) of `batch` episodes, timed the same way: episodes/min = batch /
seconds * 60 and env steps/s. With `--devices N` the lanes (batch) are split over N devices
(conav_jax.parallel). Prints the device, batch and resolution. `untrained_agent` builds a learned
agent from freshly initialised parameters, so a sweep's speed is measured without a trained run.
"""

from __future__ import annotations

import statistics
import time

# The learned agents `untrained_agent` builds, and the word their rows carry.
UNTRAINED_AGENTS = ("conav", "ppo", "objectgoal-oracle", "objectgoal-predicted", "imagegoal")
UNTRAINED = "untrained"
# (encoder, conv dtype) of the CoNav policy an untrained agent gets by default: the network the
# paper preset's learned runs train (`conav reproduce --preset paper --encoder patch`), so an
# untrained sweep costs what theirs does.
UNTRAINED_NETWORK = ("patch", "bfloat16")


def untrained_agent(name: str, env, config, key, frames: int | None = None):
    """Learned agent `name` (one of UNTRAINED_AGENTS) acting with `models.policy.init(key,
    config)`'s parameters, and where it reads predictions with freshly initialised predictors
    (`untrained_predictors`: the Perceiver over `frames` crops around the human, the trajectory
    model): the computation of a trained agent, at the env's resolution, for timing without a
    run directory. Its title says it is untrained. ValueError for another name or a `config`
    the agent cannot read (`config.resolution` must be the env's panorama)."""
    import dataclasses

    import jax

    from conav_jax.envs.agents import goalnav
    from conav_jax.envs.agents.base import NO_INTENTIONS
    from conav_jax.envs.agents.policy import check_policy_env, policy_agent_from_params
    from conav_jax.models import policy

    if name not in UNTRAINED_AGENTS:
        raise ValueError(f"no untrained variant of agent {name!r}; learned agents: {', '.join(UNTRAINED_AGENTS)}")
    k_policy, k_predictors = jax.random.split(key)
    params = _init(policy, k_policy, config)
    reads_intention = name == "objectgoal-predicted" or name in ("conav", "ppo") and (config.use_activity or
                                                                                     config.use_object)
    intention, trajectory_ = untrained_predictors(env, k_predictors, frames)
    intention = intention if reads_intention else None
    source = f"untrained {name} policy"
    if name in ("conav", "ppo"):
        agent = policy_agent_from_params(
            params, config, intention, trajectory_ if config.use_trajectory else None,
            name=name, title="CoNav Agent" if name == "conav" else "PPO Agent")
        check_policy_env(env, config, source, agent.intention_source)
    elif name == "imagegoal":
        check_policy_env(env, config, source, NO_INTENTIONS)
        agent = goalnav.imagegoal_agent_from_params(params, config, env)
    else:
        check_policy_env(env, config, source, NO_INTENTIONS)
        agent = goalnav.objectgoal_agent_from_params(params, config, env, intention)
    title = f"{agent.title or agent.name} ({UNTRAINED})"
    return agent._replace(title=title) if hasattr(agent, "_replace") else dataclasses.replace(agent, title=title)


def _init(model, key, config):
    import jax

    return jax.jit(model.init, static_argnums=1)(key, config)  # one compiled program, not one per leaf


def untrained_predictors(env, key, frames: int | None = None):
    """(intention predictor, trajectory predictor) of freshly initialised parameters at the
    env's panorama: the Perceiver over `frames` crops around the human (default: as many as an
    intention run trains on), recorded every as many steps as a run trained on the env's split
    would (`frame_spacing` of its activities A), and the trajectory model. A trained pair's
    computation, for timing without runs."""
    import jax

    from conav_jax.envs.agents.predictors import (
        DEFAULT_FRAMES,
        FrameSpec,
        frame_spacing,
        make_intention_predictor,
        spacing_stride,
        trajectory_predictor,
    )
    from conav_jax.envs.human_crop import default_crop_hw
    from conav_jax.models import perceiver, trajectory
    from conav_jax.models.perceiver import PerceiverConfig
    from conav_jax.models.trajectory import TrajectoryConfig

    frames = DEFAULT_FRAMES if frames is None else frames
    stride = spacing_stride(frame_spacing(env.split.episodes["t_walk_start"], frames))
    k_intention, k_trajectory = jax.random.split(key)
    hw = env.config.sensor.resolution
    seen = PerceiverConfig(image_hw=default_crop_hw(hw))
    traj = TrajectoryConfig()
    return (make_intention_predictor(_init(perceiver, k_intention, seen), seen, frames,
                                     FrameSpec("human", hw, materials=env.config.sensor.materials), frame_stride=stride),
            trajectory_predictor(_init(trajectory, k_trajectory, traj), traj))


def bench_eval(env, agent, batch: int, repeats: int, mesh=None) -> dict:
    """Time full-length rollouts of `batch` episodes (the split's episodes, cycled), split
    over the devices of `mesh` if given (ValueError unless `batch` divides by their count)."""
    import jax
    import numpy as np

    from conav_jax.parallel import replicate, shard_batch
    from conav_jax.envs.rollout import make_rollout

    steps = env.bank.max_steps
    episodes = np.arange(batch, dtype=np.int32) % env.num_episodes
    episodes = jax.device_put(episodes) if mesh is None else shard_batch(episodes, mesh)

    def key(r: int):
        k = jax.random.PRNGKey(r)
        return k if mesh is None else replicate(k, mesh)

    t0 = time.perf_counter()
    run = make_rollout(env, agent, steps, mesh=mesh)  # the agent's weights its arguments (envs.agents.lift)
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


def bench_sweep(env, agent, batch: int, repeats: int, episodes: int | None = None, mesh=None,
                profile_dir: str | None = None, profile_chunks: int = 8) -> dict:
    """Time sweeps of the split's first `episodes` (default all) with `batch` lanes
    (envs.rollout.make_evaluator, the agent's weights its arguments as in `conav eval`), the
    first sweep including the lift (envs.agents.lift) and the compile. With `profile_dir` (one
    device, more episodes than lanes), the same compiled program is traced there for its first
    `profile_chunks` chunks of 16 steps (a whole sweep's trace is too big to keep; the first
    chunk fills every lane) and the result's "profile" holds their device time by part of a
    rollout step (envs.rollout.SWEEP_PROFILE_SCOPES; conav_jax.profiling.profile_program)."""
    import jax
    import numpy as np

    from conav_jax.envs.agents.lift import lift_agent
    from conav_jax.envs.rollout import SWEEP_PROFILE_SCOPES, make_evaluator

    if episodes is not None and episodes > env.num_episodes:
        raise ValueError(f"bench_sweep.episodes {episodes}: the split has only {env.num_episodes} episodes")
    n = env.num_episodes if episodes is None else episodes
    if profile_dir is not None and mesh is not None and mesh.size > 1:
        raise ValueError(f"a sweep's profile runs on one device (mesh None), not a mesh of {mesh.size}")
    if profile_dir is not None and profile_chunks < 1:
        raise ValueError(f"bench_sweep.profile_chunks must be at least 1, not {profile_chunks}")
    if profile_dir is not None and batch >= n:
        raise ValueError(f"a sweep's profile traces the refilling rollout, which needs more episodes ({n}) than "
                         f"lanes ({batch})")
    idx = np.arange(n)
    t0 = time.perf_counter()
    lifted = lift_agent(env, agent)  # the weights as arguments, as `conav eval` runs a learned agent
    evaluator = make_evaluator(env, lifted.agent_fn, batch, 0, mesh)
    evaluator(lifted.params, idx)
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        evaluator(lifted.params, idx)  # returns host arrays: the sweep has finished
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    t_end = np.asarray(env.bank.t_end)[idx]
    profile = {}
    if profile_dir is not None:
        from conav_jax.profiling import profile_program

        run, args = evaluator.pool_program(lifted.params, idx, max_chunks=profile_chunks)
        compiled = run.lower(*args).compile()  # the program the sweeps ran, from jit's cache
        traced = profile_program(compiled, (env.bank, *args), SWEEP_PROFILE_SCOPES, profile_dir, calls=1)
        profile["profile"] = {"chunks": profile_chunks, **traced}
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
        **profile,
    }
