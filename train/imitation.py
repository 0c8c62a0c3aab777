"""Imitation learning for the CoNav policy: the expert's and the policy's rollouts, their data, BC.

`make_rollout_fn` runs the env with the expert and the policy side by side (a share `beta` of
the steps is acted by the expert: 1 for behaviour cloning, 0 for DAgger's own-policy rounds);
the expert labels every visited state. The expert is the CoNav expert by default, or any
teacher Agent (the goal-navigation baselines imitate geodesic planners, train/goalnav.py), and
a goal sensor may add observations the policy reads (a goal image). Records -> `sequences`
(fixed-length windows with a burn-in, compact uint8/float16 panoramas) -> `bc_loss` (paper's
L2 on (v_lin, v_ang)), trained by train.loop. Recordings run the same rollout a chunk of steps
at a time (`make_recorder`, `record_windows`): each chunk is cut into windows on the device, and
a call ends once its episodes have. train/policy.py drives the rounds; envs.agents.policy steps the policy and
builds the evaluated agent from a run.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import State
from jax.sharding import Mesh

from conav_jax.models import policy
from conav_jax.models.policy import PolicyConfig
from conav_jax.nav.expert import ExpertConfig, initial_carry
from conav_jax.nn.lstm import LSTMState
from conav_jax.parallel import replicate, shard_batch, to_host
from conav_jax.envs.agents.base import Agent
from conav_jax.envs.agents.expert import make_expert_step
from conav_jax.envs.agents.goalnav import GOAL_IMAGE
from conav_jax.envs.agents.policy import (
    INTENTION_KEYS,
    PREDICTED,
    check_policy_env,
    make_policy_step,
)
from conav_jax.envs.conav_env import ConavEnv
from conav_jax.envs.rollout import episode_batches, map_episodes

# What a rollout records per step (besides the panorama, kept as "rgb" uint8 and "depth" f16,
# and a goal sensor's "goal_image", kept as uint8 where there is one).
RECORDED_KEYS = ("gps_compass", "human_pos") + INTENTION_KEYS
PANORAMA_BYTES_PER_PIXEL = 3 + 2 + 1  # a record's panorama: uint8 RGB, float16 depth, int8 segmentation (compact_obs)
GOAL_IMAGE_BYTES_PER_PIXEL = 3  # a goal image, uint8 RGB


# -- rollouts and their records ---------------------------------------------------------------


class StepRecord(NamedTuple):
    """One recorded step, fields (B, T, ...) from a rollout. `obs` holds the policy's inputs in
    compact form: "rgb" (H, W, 3) uint8, "depth" (H, W) float16 metres, "segmentation" (H, W) int8
    where the env observes it, and RECORDED_KEYS."""

    obs: dict
    label: jax.Array  # (2,) the expert's action in this state
    action: jax.Array  # (2,) the action taken (expert's or policy's)
    valid: jax.Array  # () bool: the episode had not ended before this step
    pose: jax.Array  # (3,) robot (x, y, yaw) world, before the action


def compact_obs(obs: dict) -> dict:
    """The env's observation -> what a record keeps (uint8 RGB, float16 depth: 2.5 of 16 bytes
    a pixel; RGB to the nearest of 255 levels) and, where the observation has it, the int8
    `segmentation` (categories fit)."""
    rgbd = obs["rgbd"]
    out = {
        "rgb": jnp.round(rgbd[..., :3] * 255.0).astype(jnp.uint8),
        "depth": rgbd[..., 3].astype(jnp.float16),
    }
    if "segmentation" in obs:
        out["segmentation"] = obs["segmentation"].astype(jnp.int8)
    out.update({k: obs[k].astype(jnp.float32) for k in RECORDED_KEYS if k in obs})  # an ablation reads fewer
    if GOAL_IMAGE in obs:  # rendered RGB like the panorama's, so as compact
        out[GOAL_IMAGE] = jnp.round(obs[GOAL_IMAGE] * 255.0).astype(jnp.uint8)
    return out


def expand_obs(compact: dict) -> dict:
    """Inverse of `compact_obs` (any leading dims): float32 "rgbd" and the other keys."""
    rgbd = jnp.concatenate(
        [compact["rgb"].astype(jnp.float32) / 255.0, compact["depth"].astype(jnp.float32)[..., None]], axis=-1
    )
    out = {"rgbd": rgbd, **{k: compact[k].astype(jnp.float32) for k in RECORDED_KEYS if k in compact}}
    if "segmentation" in compact:
        out["segmentation"] = compact["segmentation"].astype(jnp.int32)
    if GOAL_IMAGE in compact:
        out[GOAL_IMAGE] = compact[GOAL_IMAGE].astype(jnp.float32) / 255.0
    return out


class _Rollout(NamedTuple):
    """The pieces `make_rollout_fn` and `make_recorder` build their rollouts from."""

    start: Callable  # (key, episode) -> (the scan's initial carry, the episode's run key), one lane
    body: Callable  # (params, beta) -> the scan body `(carry, step key) -> (carry, StepRecord | None)`
    recorded_obs: Callable  # (env state, policy carry) -> the compact observations a StepRecord keeps
    steps: int  # control steps a rollout runs: the bank's longest episode unless given


def _episode_keys(key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """An episode's key -> (its reset's key, its run's key: split into one key per step)."""
    k_reset, k_run = jax.random.split(key)
    return k_reset, k_run


def _rollout_parts(env, policy_cfg, expert_cfg, *, record, num_steps=None, intention=None, trajectory=None,
                   record_predicted=False, teacher=None, goal_obs=None) -> _Rollout:
    pol = make_policy_step(policy_cfg, intention, trajectory)  # ValueError for a predictor missing beside another
    check_policy_env(env, policy_cfg, "the policy", pol.source)
    if record and not env.config.intention_obs:
        raise ValueError("recording imitation data needs the ground-truth intentions: EnvConfig(intention_obs=True)")
    if record_predicted and pol.source != PREDICTED:
        raise ValueError("record_predicted needs the predictor of every intention input the policy reads")
    if teacher is None:
        expert = make_expert_step(env, expert_cfg)
        teacher_init, teacher_act = lambda key, state: initial_carry(), lambda state, carry, key: expert(state, carry)
    else:
        teacher_init, teacher_act = teacher.init, teacher.act

    def start(key, episode):
        k_reset, k_run = _episode_keys(key)
        state = env.reset_to_episode(k_reset, episode)
        return (state, teacher_init(k_reset, state), pol.init()), k_run

    def observe(state):
        return state.obs if goal_obs is None else {**state.obs, **goal_obs(state)}

    def recorded_obs(obs, pcarry):
        return compact_obs({**obs, **pcarry.predicted} if record_predicted else obs)

    def body_fn(params, beta):
        def body(c, k):
            state, ecarry, pcarry = c
            obs = observe(state)
            label, ecarry = teacher_act(state, ecarry, jax.random.fold_in(k, 1))
            if record_predicted:  # the predictors follow every step, whoever acts
                inputs, pcarry = pol.predict(obs, pcarry)

            def mixed(pcarry):
                if record_predicted:
                    action, pcarry = pol.act(params, inputs, pcarry)
                else:
                    action, pcarry = pol.step(params, obs, pcarry)
                return jnp.where(jax.random.uniform(k) < beta, label, action), pcarry

            # beta is the same for the whole batch, so under vmap this stays a real branch.
            action, pcarry = jax.lax.cond(beta >= 1.0, lambda p: (label, p), mixed, pcarry)
            rec = None
            if record:
                rec = StepRecord(recorded_obs(obs, pcarry), label, action, state.done < 0.5, state.pipeline_state.qpos)
            return (env.step(state, action), ecarry, pcarry), rec

        return body

    return _Rollout(start, body_fn, lambda state, pcarry: recorded_obs(observe(state), pcarry),
                    num_steps or env.bank.max_steps)


def make_rollout_fn(
    env: ConavEnv,
    policy_cfg: PolicyConfig,
    expert_cfg: ExpertConfig = ExpertConfig(),
    *,
    record: bool = True,
    num_steps: int | None = None,
    intention=None,
    trajectory=None,
    record_predicted: bool = False,
    teacher: Agent | None = None,
    goal_obs: Callable[[State], dict] | None = None,
):
    """A pure function `(params, key, episodes (B,) int32, beta ()) -> (metrics, records)`;
    jit it (once: params and beta are arguments, so every round and every validation reuses
    the compiled code).

    `teacher`: the Agent that labels and, for `beta`, acts (e.g. envs.agents.baselines'
    object-goal planner); its key is drawn apart from the mixing draws. None: the CoNav expert
    of `expert_cfg`, as before teachers existed (same code, same bytes). `goal_obs(state) ->
    dict`: observations added to the env's before the policy reads them and the records keep
    them (a goal image, envs.agents.goalnav); None: the env's alone.

    Each episode runs `num_steps` (default: the bank's longest) control steps with the expert
    and the policy side by side: at each step the expert's action (its label) is taken with
    probability `beta`, else the policy's; with `beta >= 1` the policy is not evaluated at all.
    `metrics`: the env's final per-episode metrics dict of (B,) (envs.metrics). `records`: a
    StepRecord of (B, T, ...) if `record`, else None (validation needs no observations).

    With `record_predicted` the records hold the predictors' outputs in place of the ground-truth
    intention inputs they replace (the predictors run at every step, also while the expert acts),
    so a policy trains on what it will read at evaluation. `make_recorder` runs the same steps
    in chunks, keeping only training windows."""
    parts = _rollout_parts(env, policy_cfg, expert_cfg, record=record, num_steps=num_steps, intention=intention,
                           trajectory=trajectory, record_predicted=record_predicted, teacher=teacher, goal_obs=goal_obs)

    def one(params, init, k_run, beta):
        (state, _, _), recs = jax.lax.scan(parts.body(params, beta), init, jax.random.split(k_run, parts.steps))
        return state.metrics, recs

    def run(params, key, episodes, beta):
        keys = jax.random.split(key, episodes.shape[0])
        # The start is vmapped on its own so that every carry leaf enters the scan batched (vmap
        # stacks even the constant ones): for a partly unbatched carry, vmap batches the scan's
        # body, the whole env step, again until the batched leaves settle.
        init, k_runs = jax.vmap(parts.start)(keys, episodes)
        return jax.vmap(one, in_axes=(None, 0, 0, None))(params, init, k_runs, jnp.asarray(beta, jnp.float32))

    return run


class Recorder(NamedTuple):
    """`make_recorder`'s pure functions (jit `start` and `advance`, e.g. with
    envs.rollout.jit_with_bank) and its step counts; `record_windows` drives them."""

    start: Callable  # (key, episodes (B,)) -> step keys (B, padded steps, 2)
    # (params, carry, tail, step keys, t0 (), beta, key, episodes) -> (carry, tail, windows, keep):
    # steps [t0, t0 + chunk_steps), the chunk's windows (B, chunk // seq_len, burn_in + seq_len,
    # ...) and which hold a step in the loss. The first chunk (t0 = 0) starts the episodes (the
    # carry it is given only has the shapes) and reads the burn-in's zero records as its tail.
    advance: Callable
    # (key, episodes) -> the shapes of the carry and of the tail `advance` takes (eval_shape:
    # nothing compiled or run)
    shapes: Callable
    steps: int  # the rollout's control steps (make_rollout_fn's)
    chunk_steps: int  # steps per `advance`, a multiple of seq_len and >= burn_in
    seq_len: int
    burn_in: int


def recorder_chunk_steps(seq_len: int, burn_in: int) -> int:
    """The fewest steps per recording chunk: a multiple of `seq_len` (a window's loss steps
    never straddle two chunks) and at least `burn_in` (its burn-in reaches one chunk back)."""
    return seq_len * max(1, -(-burn_in // seq_len))


def make_recorder(
    env: ConavEnv,
    policy_cfg: PolicyConfig,
    expert_cfg: ExpertConfig = ExpertConfig(),
    *,
    seq_len: int,
    burn_in: int,
    chunk_steps: int | None = None,
    **rollout,
) -> Recorder:
    """`make_rollout_fn(record=True)`'s rollout (`rollout`: its other keyword arguments; the
    same steps and keys) run `chunk_steps` at a time (default: `recorder_chunk_steps`), each
    chunk cut into `sequences`' windows on the device: a recording call holds one chunk of
    records instead of every step of its longest episode, so it runs many more lanes, and it
    stops once every lane's episode has ended (`record_windows`)."""
    if seq_len < 1 or burn_in < 0:
        raise ValueError(f"need seq_len >= 1 and burn_in >= 0, got {seq_len}, {burn_in}")
    chunk = chunk_steps or recorder_chunk_steps(seq_len, burn_in)
    if chunk % seq_len or chunk < burn_in:
        raise ValueError(f"chunk_steps must be a multiple of seq_len {seq_len} and >= burn_in {burn_in}, got {chunk}")
    parts = _rollout_parts(env, policy_cfg, expert_cfg, record=True, **rollout)
    padded = -(-parts.steps // chunk) * chunk

    def fresh(key, episodes):
        """The episodes' start: (the scans' carry, each episode's run key)."""
        return jax.vmap(parts.start)(jax.random.split(key, episodes.shape[0]), episodes)

    def start(key, episodes):
        # make_rollout_fn's step keys (the resets themselves run in the first `advance`); steps
        # past the last run on the last key (every episode has ended by then, frozen, its
        # records not valid).
        _, k_runs = jax.vmap(_episode_keys)(jax.random.split(key, episodes.shape[0]))
        keys = jax.vmap(lambda k: jax.random.split(k, parts.steps))(k_runs)
        return jnp.concatenate([keys, jnp.repeat(keys[:, -1:], padded - parts.steps, axis=1)], axis=1)

    def shapes(key, episodes):
        init = jax.eval_shape(fresh, key, episodes)[0]
        # The burn-in before step 0: zero records, as `sequences` pads (one step's shapes; the
        # observations' alone are traced, not a whole step's).
        state, _, pcarry = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape[1:], x.dtype), init)
        rec = {"obs": jax.eval_shape(parts.recorded_obs, state, pcarry),
               "label": jax.ShapeDtypeStruct((env.action_size,), jnp.float32), "valid": jax.ShapeDtypeStruct((), bool)}
        tail = jax.tree.map(lambda x: jax.ShapeDtypeStruct((episodes.shape[0], burn_in) + x.shape, x.dtype), rec)
        return init, tail

    cols = np.arange(chunk // seq_len)[:, None] * seq_len + np.arange(burn_in + seq_len)[None]  # (C, W)
    in_loss = np.arange(burn_in + seq_len) >= burn_in

    def advance(params, carry, tail, keys, t0, beta, key, episodes):
        # The first chunk starts the episodes: in this program rather than one of its own (a
        # second compile of the reset's env and sensor code).
        first = t0 == 0
        carry = jax.lax.cond(first, lambda c: fresh(key, episodes)[0], lambda c: c, carry)
        scan = lambda c, k: jax.lax.scan(parts.body(params, beta), c, k)  # noqa: E731
        carry, recs = jax.vmap(scan)(carry, jax.lax.dynamic_slice_in_dim(keys, t0, chunk, axis=1))
        recs = {"obs": recs.obs, "label": recs.label, "valid": recs.valid}
        ext = jax.tree.map(lambda a, b: jnp.concatenate([a, b], axis=1), tail, recs)  # the burn-in's steps first
        mask = ext["valid"][:, cols] & in_loss  # (B, C, W)
        # An episode starts at step 0: the first chunk's first step, after its zero-padded burn-in.
        reset = jnp.zeros(ext["valid"].shape[1], bool).at[burn_in].set(first)[cols]
        windows = {
            "obs": jax.tree.map(lambda x: x[:, cols], ext["obs"]),
            "label": ext["label"][:, cols].astype(jnp.float32),
            "mask": mask.astype(jnp.float32),
            "reset": jnp.broadcast_to(reset, mask.shape),
        }
        tail = jax.tree.map(lambda x: x[:, x.shape[1] - burn_in:], ext)
        return carry, tail, windows, mask.any(-1)

    return Recorder(start, advance, shapes, parts.steps, chunk, seq_len, burn_in)


def record_windows(
    recorder: Recorder,
    start: Callable,
    advance: Callable,
    params,
    key: jax.Array,
    episodes: np.ndarray,
    beta: float,
    batch: int,
    mesh: Mesh | None = None,
) -> tuple[dict[str, np.ndarray], dict, int]:
    """A recording over many episodes in batches of `batch` lanes, `start` and `advance` being
    `recorder`'s jitted -> host (metrics (E,), windows, control steps run).

    Batches, their keys and padding are `run_batched`'s (envs.rollout.map_episodes), so the
    metrics and windows are those of `run_batched(make_rollout_fn(...), ..., windows=(seq_len,
    burn_in))`, in the same order; a batch stops after the first chunk at whose end every
    episode has ended (none has a valid step left). Only the windows kept (a step in the loss)
    leave the device."""
    episodes = np.asarray(episodes, np.int32)
    if mesh is not None:
        params = replicate(params, mesh)
    place = jax.device_put if mesh is None else (lambda x: shard_batch(x, mesh))
    per_chunk = recorder.chunk_steps // recorder.seq_len  # windows per lane and chunk
    beta = jnp.float32(beta)
    metrics, parts, rows, cols, steps_run = [], [], [], [], 0
    for s0, n, k, idx in episode_batches(episodes, batch, key, mesh):
        keys = start(k, idx)
        # The first chunk starts the episodes: the carry it is given need only have the shapes.
        carry, tail = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), recorder.shapes(k, idx))
        for t0 in range(0, keys.shape[1], recorder.chunk_steps):
            # Every chunk's carry split over the devices, as the first chunk's zeros are: `advance`
            # may return a leaf alike in every lane replicated, and a carry placed otherwise would
            # compile it a second time.
            carry, tail = place((carry, tail))
            carry, tail, windows, keep = advance(params, carry, tail, keys, jnp.int32(t0), beta, k, idx)
            keep, done = to_host((keep, carry[0].done))  # the one sync per chunk
            kept = np.flatnonzero(keep[:n])  # (lane, window) of the batch's real lanes, row-major
            if kept.size:
                take = jnp.asarray(kept)
                parts.append(to_host(jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:])[take], windows)))
                rows.append(s0 + kept // per_chunk)
                cols.append(t0 // recorder.seq_len + kept % per_chunk)
            steps_run = max(steps_run, t0 + recorder.chunk_steps)
            if np.all(done[:n] > 0.5):
                break
        metrics.append(jax.tree.map(lambda x: x[:n], to_host(carry[0].metrics)))
    metrics = jax.tree.map(lambda *xs: np.concatenate(xs), *metrics)
    metrics["episode"] = episodes
    if not parts:
        raise ValueError("the recording kept no window: no episode had a valid step")
    order = np.lexsort((np.concatenate(cols), np.concatenate(rows)))  # episode, then window: `sequences`' order
    windows = jax.tree.map(lambda *xs: np.concatenate(xs)[order], *parts)
    return metrics, windows, min(steps_run, recorder.steps)


def run_batched(
    rollout,
    params,
    key: jax.Array,
    episodes: np.ndarray,
    beta: float,
    batch: int,
    progress: Callable | None = None,
    mesh: Mesh | None = None,
    windows: tuple[int, int] | None = None,
) -> tuple[dict[str, np.ndarray], StepRecord | dict | None]:
    """A jitted `make_rollout_fn` over many episodes in batches of `batch` -> host (metrics,
    records) over all of them (envs.rollout.map_episodes: padding, keys, and with a `mesh` each
    batch split over its devices, `params` replicated; same results as on one device). With
    `windows=(seq_len, burn_in)` the records come back as `sequences` cuts them, cut batch by
    batch: every episode's records, padded to the longest, never sit on the host at once."""
    episodes = np.asarray(episodes, np.int32)
    if mesh is not None:
        params = replicate(params, mesh)
    cut = None if windows is None else (lambda out: (out[0], sequences(out[1], *windows)))
    metrics, records = map_episodes(lambda k, idx: rollout(params, k, idx, beta), episodes, batch, key, mesh, progress,
                                    host_fn=cut)
    metrics["episode"] = episodes
    return metrics, records


TURN_IN_PLACE_V_LIN = 0.05  # |v_lin| of a label at or below this: it turns the robot in place
FULL_TURN_V_ANG = 0.9  # |v_ang| of a turn in place above this: at (nearly) full rate


def label_statistics(records: StepRecord, metrics: dict) -> dict[str, float]:
    """What imitation data cut from `records` (fields (E, T, ...), without "obs" is fine) would
    teach, over the recorded steps (`valid`): steps per episode; the share after the human
    reached the goal (`metrics["t_arrive"]`: by then the first arrival is lost); the share of
    labels turning in place (|v_lin| <= TURN_IN_PLACE_V_LIN) and, of those, at full rate
    (|v_ang| > FULL_TURN_V_ANG); the mean forward speed of the labels and of the actions taken;
    the mean L1 distance from action to label."""
    valid = np.asarray(records.valid, bool)
    if not valid.any():
        raise ValueError("no recorded step is valid")
    label, action = np.asarray(records.label)[valid], np.asarray(records.action)[valid]
    after = (np.arange(valid.shape[1])[None] > np.asarray(metrics["t_arrive"])[:, None])[valid]
    turn = np.abs(label[:, 0]) <= TURN_IN_PLACE_V_LIN
    return {
        "episodes": int(valid.shape[0]),
        "steps_per_episode": float(valid.sum() / valid.shape[0]),
        "after_arrival_share": float(after.mean()),
        "turn_in_place_share": float(turn.mean()),
        "full_turn_share_of_turns": float((np.abs(label[turn, 1]) > FULL_TURN_V_ANG).mean()) if turn.any() else 0.0,
        "label_v_lin_mean": float(label[:, 0].mean()),
        "action_v_lin_mean": float(action[:, 0].mean()),
        "action_label_l1": float(np.abs(action - label).sum(-1).mean()),
    }


# -- imitation data ------------------------------------------------------------------------------


def sequences(records: StepRecord, seq_len: int, burn_in: int) -> dict[str, np.ndarray]:
    """Cut episode records (E, T, ...) into training windows of `burn_in + seq_len` steps.

    Window c covers steps [c * seq_len - burn_in, (c + 1) * seq_len) of an episode (before the
    episode's start: padding). Its last `seq_len` steps are trained on where valid; the burn-in
    only warms up the LSTM, so a window's loss sees a carry that has run >= burn_in steps (at
    evaluation it runs the whole episode). Windows with no valid step are dropped.
    Returns host arrays, leading N windows: "obs" (dict, compact), "label" (N, W, 2),
    "mask" (N, W) float32 (1 = in the loss) and "reset" (N, W) bool (the episode starts here)."""
    if seq_len < 1 or burn_in < 0:
        raise ValueError(f"need seq_len >= 1 and burn_in >= 0, got {seq_len}, {burn_in}")
    valid = np.asarray(records.valid, bool)
    e, t = valid.shape
    chunks = -(-t // seq_len)
    pad = ((0, 0), (burn_in, chunks * seq_len - t))

    def padded(x):
        return np.pad(np.asarray(x), pad + ((0, 0),) * (np.ndim(x) - 2))

    reset = np.zeros((e, t), bool)
    reset[:, 0] = True
    cols = np.arange(chunks)[:, None] * seq_len + np.arange(burn_in + seq_len)[None]  # (chunks, W)
    in_loss = np.zeros(burn_in + seq_len, bool)
    in_loss[burn_in:] = True
    mask = padded(valid)[:, cols] & in_loss  # (E, chunks, W)
    keep = mask.any(-1)  # (E, chunks)

    def windows(x):
        w = padded(x)[:, cols]
        return w[keep]

    return {
        "obs": {k: windows(v) for k, v in records.obs.items()},
        "label": windows(records.label).astype(np.float32),
        "mask": mask[keep].astype(np.float32),
        "reset": windows(reset),
    }


def concat_sequences(parts: list[dict]) -> dict:
    """DAgger's aggregation: the windows of several datasets, one after another."""
    return jax.tree.map(lambda *xs: np.concatenate(xs), *parts)


def save_sequences(path, data: dict) -> None:
    """Write windows to one .npz (keys flattened as "obs/rgb", "label", ...)."""
    flat = {f"obs/{k}": v for k, v in data["obs"].items()}
    flat.update({k: v for k, v in data.items() if k != "obs"})
    np.savez(path, **flat)


def load_sequences(path) -> dict:
    with np.load(path) as z:
        return {
            "obs": {k[4:]: z[k] for k in z.files if k.startswith("obs/")},
            **{k: z[k] for k in z.files if not k.startswith("obs/")},
        }


# -- behaviour cloning ------------------------------------------------------------------------


def bc_loss(params, cfg: PolicyConfig, batch: dict, remat: bool = False) -> tuple[jax.Array, dict]:
    """The paper's L2 imitation loss, (v_lin - v_lin*)^2 + (v_ang - v_ang*)^2, averaged over
    the batch's in-loss steps. `batch`: windows as `sequences` returns them, (B, W, ...); the
    LSTM runs each window from a zero carry (reset at episode starts). `remat`: encode one
    step at a time and recompute it for the gradient (policy.apply_sequence), for windows of
    large panoramas that do not fit otherwise."""
    carry = policy.initial_carry(cfg, batch["label"].shape[0])
    loss, n, _, _ = sequence_loss(params, cfg, batch, carry, remat)
    return loss, {"steps_in_loss": n}


def sequence_loss(params, cfg: PolicyConfig, batch: dict, carry: LSTMState, remat: bool = False,
                  time_major: bool = False, prepare=expand_obs) -> tuple[jax.Array, jax.Array, LSTMState, jax.Array]:
    """`bc_loss` with the LSTM starting each window from `carry` (B, hidden) -> (loss, steps in
    the loss, the carry after the window's last step, the policy's actions (B, W, 2)): truncated
    BPTT over consecutive windows (train.live), the carry reset where `batch["reset"]` starts an
    episode. `time_major`: every entry of `batch` and the actions (W, B, ...) instead.
    `prepare`: policy.apply_sequence's (default: the observations are `compact_obs`'s; None:
    they are the policy's own)."""
    actions, _, end = policy.apply_sequence(params, cfg, batch["obs"], carry, batch["reset"], remat=remat,
                                            prepare=prepare, time_major=time_major)
    err = jnp.sum(jnp.square(actions - batch["label"]), axis=-1)
    n = jnp.sum(batch["mask"])
    loss = jnp.sum(err * batch["mask"]) / jnp.maximum(n, 1.0)
    return loss, n, end, actions


def make_loss_fn(cfg: PolicyConfig):
    """`bc_loss` in train.loop's shape `(params, batch, key) -> (loss, metrics)`."""

    def loss_fn(params, batch, key):
        del key  # deterministic loss
        return bc_loss(params, cfg, batch)

    return loss_fn
