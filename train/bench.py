"""`conav bench train`: samples/s of one model's jitted training update on random data; and the
throughput of live imitation (train.live), its iteration timed part by part (`live_throughput`).

Random data of the model's training shapes is put on the device -> train.loop's update
(minibatch gather, value_and_grad, clipping, Adam) scanned `--steps` times in one jitted call
-> after a compile-and-warm-up call, the median of timed calls gives samples/s. Prints the
device, batch and resolution.
"""

from __future__ import annotations

import statistics
import time

import jax
import jax.numpy as jnp

from conav_jax.parallel import check_divisible, replicate
from conav_jax.train.loop import TrainConfig, make_chunk, make_optimizer, make_update

DEFAULT_BATCH = {"trajectory": 4096, "intention": 256, "policy": 32}
POLICY_SEQUENCE = 32  # time steps per policy sample (truncated BPTT length)


def _trajectory_setup(key, batch: int, resolution):
    from conav_jax.models import trajectory as model
    from conav_jax.train.trajectory import trajectory_loss

    config = model.TrajectoryConfig()
    k_p, k_h, k_f = jax.random.split(key, 3)
    n = 8 * batch
    data = {
        "history": jnp.cumsum(0.1 * jax.random.normal(k_h, (n, config.history, 2)), axis=1),
        "future": jnp.cumsum(0.1 * jax.random.normal(k_f, (n, config.horizon, 2)), axis=1),
    }
    loss = lambda p, b, k: trajectory_loss(p, config, b, k)
    return model.init(k_p, config), data, loss, {"history": config.history, "horizon": config.horizon}


def _intention_setup(key, batch: int, resolution):
    from conav_jax.models import perceiver
    from conav_jax.train.intention import IntentionDataConfig, intention_loss

    config = perceiver.PerceiverConfig()
    frames = IntentionDataConfig.frames
    k_p, k_x, k_a, k_o = jax.random.split(key, 4)
    n = 2 * batch  # frames dominate memory: (n, F, h, w, 4) float16
    data = {
        "frames": jax.random.uniform(k_x, (n, frames, *config.image_hw, 4), jnp.float16),
        "num_frames": jnp.full((n,), frames, jnp.int32),
        "activity": jax.random.randint(k_a, (n,), 0, config.num_activities),
        "object": jax.random.randint(k_o, (n,), 0, config.num_objects),
        "activity_a": jax.random.randint(k_a, (n,), 0, config.num_activities)[::-1],
    }
    loss = lambda p, b, k: intention_loss(p, config, b, k)
    h, w = config.image_hw
    return perceiver.init(k_p, config), data, loss, {"resolution": f"{h}x{w}", "frames": frames}


def _policy_setup(key, batch: int, resolution, remat: bool = False, conv_dtype: str = "float32",
                  encoder: str | None = None):
    """Windows as `conav train policy` stores them (compact uint8 RGB, float16 depth; every
    step in the loss) and its loss, train.imitation.bc_loss, with the CNN's convolutions in
    `conv_dtype` (PolicyConfig.conv_dtype) and the panorama encoder `encoder` (ENCODERS)."""
    from conav_jax.models import policy
    from conav_jax.train.imitation import bc_loss

    encoder = encoder or policy.DEFAULT_ENCODER
    config = policy.encoder_config(policy.PolicyConfig(resolution=resolution, conv_dtype=conv_dtype), encoder)
    t = POLICY_SEQUENCE
    ks = jax.random.split(key, 8)
    n = batch  # sequences of panoramas are large: (n, T, H, W, 3) uint8 + (n, T, H, W) float16
    obs = {
        "rgb": jax.random.randint(ks[0], (n, t, *resolution, 3), 0, 256, jnp.int32).astype(jnp.uint8),
        "depth": jax.random.uniform(ks[0], (n, t, *resolution), jnp.float16, 0.0, 10.0),
        "gps_compass": jax.random.normal(ks[1], (n, t, 3)),
        "human_pos": jax.random.normal(ks[2], (n, t, 2)),
        "activity_probs": jax.nn.softmax(jax.random.normal(ks[3], (n, t, config.num_activities))),
        "object_probs": jax.nn.softmax(jax.random.normal(ks[4], (n, t, config.num_objects))),
        "future_traj": jax.random.normal(ks[5], (n, t, config.horizon, 2)),
    }
    data = {
        "obs": obs,
        "label": jax.random.uniform(ks[6], (n, t, 2), minval=-1.0, maxval=1.0),
        "mask": jnp.ones((n, t), jnp.float32),
        "reset": jnp.zeros((n, t), bool).at[:, 0].set(True),
    }
    loss = lambda p, b, k: bc_loss(p, config, b, remat)
    h, w = resolution
    return policy.init(ks[7], config), data, loss, {"resolution": f"{h}x{w}", "sequence": t, "remat": remat,
                                                    "conv_dtype": conv_dtype, "encoder": encoder}


SETUPS = {"trajectory": _trajectory_setup, "intention": _intention_setup, "policy": _policy_setup}


def bench_train(model: str, batch: int, resolution: tuple[int, int], steps: int, repeats: int, mesh=None,
                remat: bool = False, conv_dtype: str = "float32", encoder: str | None = None) -> dict:
    """Time `steps` updates of `model` at `batch` samples (split over `mesh`'s devices if given,
    data and parameters replicated, as train.loop runs them); returns a dict of figures. The
    policy's `remat`, `conv_dtype` and `encoder` as train.policy and PolicyConfig take them."""
    if model not in SETUPS:
        raise ValueError(f"unknown model {model!r}; choose from {sorted(SETUPS)}")
    if batch <= 0 or steps <= 0 or repeats <= 0:
        raise ValueError(f"batch, steps and repeats must be > 0, got {batch}, {steps}, {repeats}")
    if mesh is not None:
        check_divisible(batch, mesh)
    if (remat or conv_dtype != "float32" or encoder is not None) and model != "policy":
        raise ValueError(f"bench_train.remat, bench_train.conv_dtype and bench_train.encoder apply to the policy "
                         f"model, not bench_train.model {model}")
    extra = {"remat": remat, "conv_dtype": conv_dtype, "encoder": encoder} if model == "policy" else {}
    params, data, loss, shape_info = SETUPS[model](jax.random.PRNGKey(0), batch, resolution, **extra)
    cfg = TrainConfig(steps=steps * (repeats + 1), batch=batch, warmup_steps=0)
    optimizer = make_optimizer(cfg)
    n = jax.tree.leaves(data)[0].shape[0]
    chunk = jax.jit(make_chunk(make_update(loss, optimizer, cfg, n, mesh), batch), static_argnames="length")
    state = (params, optimizer.init(params))
    if mesh is not None:
        data, state = replicate((data, state), mesh)

    def call(state):
        params, opt_state, _, _, sums = chunk(*state, data, length=steps)
        jax.block_until_ready(sums)
        return params, opt_state

    t0 = time.perf_counter()
    state = call(state)
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        state = call(state)
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    num_params = sum(x.size for x in jax.tree.leaves(params))
    return {
        "model": model,
        "device": jax.devices()[0].device_kind,
        "devices": 1 if mesh is None else mesh.size,
        "batch": batch,
        **shape_info,
        "params": int(num_params),
        "updates_per_call": steps,
        "compile_and_first_call_s": round(compile_s, 2),
        "median_call_s": round(med, 4),
        "samples_per_s": round(batch * steps / med, 1),
        "samples_per_s_per_device": round(batch * steps / med / (1 if mesh is None else mesh.size), 1),
        "updates_per_s": round(steps / med, 2),
        **({"timesteps_per_s": round(batch * steps * POLICY_SEQUENCE / med, 1)} if model == "policy" else {}),
    }


LIVE_PARTS = ("simulate", "expert", "learner", "update")  # live_throughput's cumulative parts


def live_throughput(env, policy_config=None, lanes: int = 256, window_steps: int = 32, repeats: int = 5,
                    intention=None, trajectory=None, beta: float = 0.5, seed: int = 0, remat: bool = False,
                    profile_dir: str | None = None, parts: tuple[str, ...] = LIVE_PARTS, runs: int = 1) -> dict:
    """Env timesteps trained per second of train.live's iteration on `env` (its train split) at
    `lanes` x `window_steps` steps per iteration, and its breakdown: each cumulative part of an
    iteration compiled as its own program and timed alone (the simulator: refills, the
    learner's panorama and the env step; + the expert's labels; + the predictors and the
    learner acting; + the update, the whole iteration). Every program carries its lanes on from
    call to call; after a compile-and-warm-up call, the median of `repeats` calls, each with
    `block_until_ready`. `beta`: the expert's share of the actions (below 1 the learner acts
    too). `policy_config` defaults to PolicyConfig at the env's resolution; `intention`,
    `trajectory` as train.live.train_live takes predictor objects (none: ground truth);
    `remat` as LiveConfig.remat. `parts`: which of LIVE_PARTS to compile and time ("update" is
    the whole iteration, what a run pays). With `profile_dir`, two more calls of the whole
    iteration are traced there and the result's "profile" holds their device time by part
    (conav_jax.profiling.profile_program over train.live.PROFILE_SCOPES). `runs` > 1: the whole
    iteration of that many runs (seeds seed..seed+runs-1) trained together as one program
    (train.live.train_live_seeds), its timesteps those of all the runs; parts must be
    ("update",)."""
    from conav_jax.models import policy
    from conav_jax.models.policy import PolicyConfig
    from conav_jax.envs.bench import peak_memory_bytes
    from conav_jax.envs.rollout import jit_with_bank
    from conav_jax.train import live as lv

    if lanes <= 0 or window_steps <= 0 or repeats <= 0:
        raise ValueError(f"lanes, window_steps and repeats must be > 0, got {lanes}, {window_steps}, {repeats}")
    if not parts or set(parts) - set(LIVE_PARTS):
        raise ValueError(f"parts must be some of {LIVE_PARTS}, got {parts}")
    if profile_dir is not None and "update" not in parts:
        raise ValueError("a profile traces the whole iteration: parts must hold 'update'")
    if runs < 1 or runs > 1 and tuple(parts) != ("update",):
        raise ValueError(f"runs must be >= 1, and runs > 1 times the whole iteration alone (parts ('update',)); "
                         f"got runs {runs}, parts {parts}")
    hw = env.config.sensor.resolution
    policy_config = policy_config or PolicyConfig(resolution=hw)
    config = lv.LiveConfig(lanes=lanes, window_steps=window_steps, warmup_iterations=0, beta_start=beta,
                           beta_end=beta, seed=seed, remat=remat)
    fns = lv.make_live(env, policy_config, config, intention, trajectory)
    params0 = policy.init(jax.random.PRNGKey(seed), policy_config)

    def rollout_part(stages):
        def run(state, key):
            lanes_, cursor, window = fns.rollout(state.params, state.lanes, state.cursor, state.seed, key, jnp.float32(beta), stages)
            return state._replace(lanes=lanes_, cursor=cursor), window
        return run

    programs = {name: rollout_part(i + 1) for i, name in enumerate(lv.ROLLOUT_STAGES)} | {"update": fns.iteration}
    assert tuple(programs) == LIVE_PARTS
    per_iter = lanes * window_steps * runs
    seeds = list(range(seed, seed + runs))
    out = {"device": jax.devices()[0].device_kind, "lanes": lanes, "window_steps": window_steps,
           "resolution": f"{hw[0]}x{hw[1]}", "physics": env.config.physics.impl, "sensor": env.config.sensor.kind,
           "beta": beta, "remat": remat, "intention_source": fns.source, "runs": runs,
           "timesteps_per_iteration": per_iter}
    # Each part starts from its own fresh state, donated call to call as train_live's is; the
    # rollout parts keep compact observations and need no window buffer.
    donate = () if jax.default_backend() == "cpu" else (1,)
    for name, fn in programs.items():
        if name not in parts:
            continue
        if runs > 1:  # as train_live_seeds runs them: one program
            jitted = lv.make_iteration(env, policy_config, config, intention, trajectory, seeds=runs)[1]
            state = lv.stack_runs([fns.init(policy.init(jax.random.PRNGKey(s), policy_config))._replace(
                seed=jnp.full((), s, jnp.int32)) for s in seeds])
        else:
            jitted = jit_with_bank(env, fn, donate_argnums=donate)
            state = fns.init(jax.tree.map(jnp.copy, params0))  # donated: params0 itself must survive
            state = state if name == "update" else state._replace(window_obs={})
        times = []
        for i in range(repeats + 1):
            t0 = time.perf_counter()
            state, res = jitted(state, lv.iteration_keys(seeds, i))
            jax.block_until_ready((state, res))
            times.append(time.perf_counter() - t0)
        med = statistics.median(times[1:])
        out[f"{name}_compile_and_first_call_s"] = round(times[0], 2)
        out[f"{name}_median_call_s"] = round(med, 4)
        out[f"{name}_timesteps_per_s"] = round(per_iter / med, 1)
    if "update" in parts:
        out["timesteps_trained_per_s"] = out["update_timesteps_per_s"]
    out["peak_bytes_in_use"] = peak_memory_bytes()  # over the parts timed
    if profile_dir is not None:
        from conav_jax.profiling import profile_program

        key = lv.iteration_keys(seeds, repeats + 1)
        compiled = jitted.lower(state, key).compile()
        out["profile"] = profile_program(compiled, (env.bank, state, key), lv.PROFILE_SCOPES, profile_dir,
                                         after=lambda res: (env.bank, res[0], key))
    return out
