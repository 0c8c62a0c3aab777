"""Imitation from the live simulator: nothing stored, every train episode used (purejaxrl's shape).

One jitted iteration, `(TrainState, key) -> (TrainState, metrics)`: `rollout` steps N lanes T
control steps by lax.scan (at each step the expert labels the state and acts with probability
beta_k, else the learner; the predictors run on the learner's own observations), then `update`
takes one truncated-BPTT step of train.imitation's L2 loss on that window, the LSTM starting
from the carry the lanes ended the previous window with (gradient stopped there). A lane whose
episode has ended restarts on the next episode of the queue: pass p of the queue is a
permutation of the whole train split drawn from (seed, p) alone (`pass_permutation`), so every
train episode runs once per pass, in the same order for every ablation of a seed.
`train_live` drives the iteration, logs to RUN/log.jsonl and checkpoints the whole TrainState
atomically: keys come from (seed, iteration), so a killed run resumes bit for bit. RUN is a
`policy` run that envs.agents.policy.load_policy_run and policy_agent load as train.policy's.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import State
from tqdm import tqdm

from conav_jax import runs
from conav_jax.checkpoints import checkpoint_path, latest_checkpoint, save_checkpoint
from conav_jax.models import policy
from conav_jax.models.policy import PolicyConfig, config_dict, encoder_name
from conav_jax.provenance import PROVENANCE_KEY, provenance
from conav_jax.nav.expert import ExpertConfig
from conav_jax.nn.lstm import LSTMState
from conav_jax.optim import AdamState, adam, clip_by_global_norm, warmup_cosine
from conav_jax.runs import append_log, finite_or_none
from conav_jax.envs.agents.base import GROUND_TRUTH, PREDICTED
from conav_jax.envs.agents.expert import expert_agent
from conav_jax.envs.agents.policy import (
    PolicyCarry,
    check_policy_env,
    load_predictors,
    make_policy_step,
    policy_inputs,
)
from conav_jax.envs.conav_env import ConavEnv
from conav_jax.envs.config import env_settings
from conav_jax.envs.mjcf import UD
from conav_jax.envs.rollout import jit_with_bank, select_lanes
from conav_jax.train import imitation as im
from conav_jax.train.policy import ImitationTask

KIND = runs.POLICY  # loaded as any imitation policy run
BETA_SCHEDULES = ("linear", "exponential")
# Fields that change only how often things are written, not the trained weights: a resumed run
# may change them.
CADENCE_FIELDS = ("ckpt_every", "log_every")
# Streams of the seed's key: the episode queue's permutations and the iterations' draws.
_ORDER_STREAM, _ITERATION_STREAM = 0x0DE5, 0x57E9
# The parts of a rollout step, cumulative (`make_live`'s rollout runs the first `stages`): the
# simulator (refills, the learner's panorama, the env step), the expert's labels, the predictors
# and the learner acting.
ROLLOUT_STAGES = ("simulate", "expert", "learner")
# The named scopes of an iteration (a profile's parts, conav_jax.profiling): a rollout step's
# parts, then the update, then the rest of the rollout (the scan's own buffers).
PROFILE_SCOPES = ("refill", "observe", "expert", "predictors", "prepare", "learner", "env_step", "update", "rollout")
# The observations a window replaces by the prepared panorama (policy.prepare_panorama).
PANORAMA_SOURCES = ("rgbd", "segmentation")
STEPS = "steps"  # the iteration's metrics entry holding its steps (a Window without observations)
# The policy live runs train unless given another (`conav train live`'s network flags default to
# it): its visual embedding is layer-normalised (PolicyConfig.visual_norm), without which the
# 112x448 policy stopped reading its inputs within a few dozen updates.
DEFAULT_POLICY = PolicyConfig(visual_norm=True)


@dataclass(frozen=True)
class LiveConfig:
    """One live imitation run. An iteration steps `lanes` episodes `window_steps` control steps
    (0.1 s each) and applies one update; cadences count iterations."""

    lanes: int = 256  # N: episodes stepped together
    window_steps: int = 32  # T: control steps per iteration, the truncated-BPTT window
    iterations: int = 10_000  # updates, one per window
    lr: float = 3e-4  # peak Adam learning rate
    warmup_iterations: int = 100  # linear warm-up, then cosine decay to 0 at `iterations`
    weight_decay: float = 0.0  # > 0 makes Adam AdamW
    grad_clip: float = 1.0  # global L2 norm limit of each gradient
    # The expert acts at a step of a lane with probability beta_k at iteration k: from
    # beta_start to beta_end over beta_decay_iterations, then constant; "linear" in k, or
    # "exponential" (geometric, both ends > 0). beta = 1 throughout is behaviour cloning.
    beta_start: float = 1.0
    beta_end: float = 1.0
    beta_decay_iterations: int = 1
    beta_schedule: str = "linear"
    remat: bool = False  # encode one window step at a time in the update (policy.apply_sequence)
    seed: int = 0  # fixes the initial weights, the episode order and every draw
    ckpt_every: int = 500  # iterations between checkpoints of the whole state (and one at the end)
    log_every: int = 10  # iterations per log record (means over them)

    def __post_init__(self):
        for name in ("lanes", "window_steps", "iterations", "beta_decay_iterations", "ckpt_every", "log_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"LiveConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.warmup_iterations <= self.iterations:
            raise ValueError(f"LiveConfig.warmup_iterations must be in [0, iterations={self.iterations}], "
                             f"got {self.warmup_iterations}")
        if self.lr <= 0 or self.grad_clip <= 0 or self.weight_decay < 0:
            raise ValueError(f"LiveConfig needs lr > 0, grad_clip > 0, weight_decay >= 0; got {self.lr}, "
                             f"{self.grad_clip}, {self.weight_decay}")
        for name in ("beta_start", "beta_end"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"LiveConfig.{name} is a probability in [0, 1], got {getattr(self, name)}")
        if self.beta_schedule not in BETA_SCHEDULES:
            raise ValueError(f"LiveConfig.beta_schedule must be one of {BETA_SCHEDULES}, got {self.beta_schedule!r}")
        if self.beta_schedule == "exponential" and min(self.beta_start, self.beta_end) <= 0.0:
            raise ValueError("LiveConfig.beta_schedule 'exponential' needs beta_start and beta_end > 0")

    @property
    def timesteps_per_iteration(self) -> int:
        return self.lanes * self.window_steps

    def beta(self, iteration: jax.Array | int) -> jax.Array:
        """beta_k, the expert's probability of acting at iteration `iteration` (traceable)."""
        frac = jnp.minimum(jnp.asarray(iteration, jnp.float32) / self.beta_decay_iterations, 1.0)
        if self.beta_schedule == "linear":
            return jnp.float32(self.beta_start) + (self.beta_end - self.beta_start) * frac
        return self.beta_start * (self.beta_end / self.beta_start) ** frac

    def weights_fields(self) -> dict:
        """The fields the trained weights depend on (stored in, and checked against, checkpoints)."""
        return {k: v for k, v in dataclasses.asdict(self).items() if k not in CADENCE_FIELDS}


# -- the episode queue -------------------------------------------------------------------------


def pass_permutation(seed: int, pass_index: jax.Array, num_episodes: int) -> jax.Array:
    """The train episodes in the order pass `pass_index` of the queue runs them: a permutation
    of `range(num_episodes)` drawn from (seed, pass) alone (traceable)."""
    key = jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), _ORDER_STREAM), pass_index)
    return jax.random.permutation(key, num_episodes).astype(jnp.int32)


def episodes_at(seed: int, positions: jax.Array, num_episodes: int) -> jax.Array:
    """The episodes at queue `positions` (N,), which lie within N of the smallest (traceable):
    position q runs `pass_permutation(seed, q // E)[q % E]`. The passes they span are drawn
    once each."""
    first = jnp.min(positions) // num_episodes
    spans = (positions.shape[0] - 1) // num_episodes + 2
    orders = jax.vmap(lambda p: pass_permutation(seed, first + p, num_episodes))(jnp.arange(spans))
    return orders[positions // num_episodes - first, positions % num_episodes]


# -- state ---------------------------------------------------------------------------------------


class Lanes(NamedTuple):
    """The lanes, each field (N, ...): env states without their observation, the teacher's (the
    expert's unless a task names another) and the acting policy's carries (LSTM, intention
    predictor, latest predictions) and the queue position of each lane's episode."""

    env: State
    expert: Any
    policy: PolicyCarry
    position: jax.Array


class TrainState(NamedTuple):
    """Everything an iteration reads and writes: the weights, Adam's state, the lanes, `cursor`
    () the next queue position to hand out, `iteration` () the updates applied and `seed` () the
    run's LiveConfig.seed (an input of the compiled iteration, not a constant of it: the seeds
    of one configuration share one compiled program). `window_obs`: scratch, not state (never
    checkpointed, rewritten whole by every rollout): the window's observations (T, N, ...),
    which the rollout writes step by step in place. Carried from iteration to iteration (and
    donated), it is allocated once, not zero-filled and copied out of the scan each time."""

    params: dict
    opt_state: AdamState
    lanes: Lanes
    cursor: jax.Array
    iteration: jax.Array
    seed: jax.Array
    window_obs: dict


class Window(NamedTuple):
    """One iteration's steps, time-major (T, N, ...): the inputs the learner read, its panorama
    as its CNN reads it (policy.prepare_panorama) and predictions in place of the intentions
    they replace (a rollout of fewer stages keeps train.imitation.compact_obs's), the
    expert's label, `first` (an episode starts at this step: the LSTM is reset), `expert_acted`,
    the lane's episode, its queue position, the episode's step index and the robot's pose (x,
    y, yaw) before the step, and whether the episode ended with this step and reached the goal
    on it."""

    obs: dict
    label: jax.Array
    first: jax.Array
    expert_acted: jax.Array
    episode: jax.Array
    position: jax.Array
    t: jax.Array
    pose: jax.Array
    ended: jax.Array
    reached: jax.Array


class Live(NamedTuple):
    """`make_live`'s functions (pure; jit them with envs.rollout.jit_with_bank, which
    `make_iteration` does)."""

    init: Any  # (params) -> TrainState at iteration 0, its lanes waiting for their first episodes
    # (params, lanes, cursor, seed, key, beta, stages=3, window_obs=None) -> (lanes, cursor, Window);
    # fewer stages (ROLLOUT_STAGES) leave the later parts out (zero labels, the expert's
    # "actions" then); given a TrainState's window_obs, the Window's observations are written there
    rollout: Any
    update: Any  # (params, opt_state, start lstm, Window) -> (params, opt_state, end lstm, metrics)
    # (TrainState, key) -> (TrainState, metrics): scalars, and under STEPS the Window trained on
    # without its observations (T, N) (what each lane did: small beside the panoramas)
    iteration: Any
    source: str  # where the learner's intention inputs come from (envs.agents.base)


def _spread(actions: jax.Array) -> jax.Array:
    """The standard deviation of `actions (..., 2)` over every step, averaged over the two
    velocities."""
    return jnp.std(actions.reshape(-1, actions.shape[-1]), axis=0).mean()


def iteration_key(seed: int, iteration: int | jax.Array) -> jax.Array:
    """The key of iteration `iteration`: from (seed, iteration) alone."""
    return jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), _ITERATION_STREAM), iteration)


def iteration_keys(seeds: list[int], iteration: int | jax.Array) -> jax.Array:
    """The key argument of iteration `iteration` of the runs of `seeds`: one run's key alone, or
    the runs' keys stacked, as `make_iteration(..., seeds=len(seeds))`'s program takes them."""
    keys = [iteration_key(seed, iteration) for seed in seeds]
    return keys[0] if len(keys) == 1 else jnp.stack(keys)


def make_live(env: ConavEnv, policy_config: PolicyConfig, live: LiveConfig, intention=None, trajectory=None,
              expert_config: ExpertConfig = ExpertConfig(), seed_axis: str | None = None, teacher=None) -> Live:
    """The live imitation loop's pure functions for `env` (its train split), the learner
    `policy_config` and the predictors (envs.agents.predictors; none: the env's ground-truth
    intentions, privileged). `seed_axis`: the name of the vmapped axis over runs the iteration
    runs under (`train_live_seeds`), if any: the refill then skips its resets only when no lane
    of any run has ended, a choice every run shares (a cond, not both branches for each).
    `teacher`: `env -> StateAgent` labelling (and, with beta, acting) in place of the CoNav
    expert of `expert_config` (an ImitationTask's, e.g. the object-goal planner); it is handed
    each episode's start state for its carry and acts on the state alone (no key).
    ValueError for inputs that do not fit, in config-field names."""
    if policy_config.goal_image:
        raise ValueError("PolicyConfig.goal_image: live imitation trains the CoNav policy, which reads no goal image")
    pol = make_policy_step(policy_config, intention, trajectory)  # ValueError for a predictor missing beside another
    check_policy_env(env, policy_config, "the policy", pol.source)
    teacher = expert_agent(env, expert_config) if teacher is None else teacher(env)
    no_key = jax.random.PRNGKey(0)  # the teachers draw nothing

    def expert(state, carry):
        return teacher.act(state, carry, no_key)
    keys = policy_inputs(policy_config)
    n, num_episodes = live.lanes, env.num_episodes
    schedule = warmup_cosine(live.lr, live.warmup_iterations, live.iterations)
    optimizer = adam(schedule, weight_decay=live.weight_decay)

    def start(seed, positions):
        """Lanes on the episodes at queue `positions` of seed `seed`'s queue."""
        episodes = episodes_at(seed, positions, num_episodes)
        state = jax.vmap(lambda e: env.reset_to_episode(jax.random.PRNGKey(0), e, observe=False))(episodes)
        carries = jax.vmap(lambda s: (teacher.init(no_key, s), pol.init()))(state)
        return Lanes(state, *carries, positions)

    def refill(lanes: Lanes, cursor, seed):
        """Lanes whose episode has ended take the next queued ones, in lane order -> (lanes,
        cursor, first (N,))."""
        ended = lanes.env.done > 0
        # Lanes that keep their episode ask for `cursor`: the positions asked for then lie within
        # N of it (episodes_at draws the passes they span).
        positions = jnp.where(ended, cursor + jnp.cumsum(ended) - 1, cursor)
        any_ended = ended.any()
        if seed_axis is not None:
            any_ended = jax.lax.psum(any_ended.astype(jnp.int32), seed_axis) > 0
        lanes = jax.lax.cond(any_ended, lambda l: select_lanes(ended, start(seed, positions), l), lambda l: l, lanes)
        return lanes, cursor + ended.sum(), ended

    def init(params) -> TrainState:
        # Lanes of zeros marked ended: the first step of iteration 0 starts them (one compiled reset).
        shapes = jax.eval_shape(start, jnp.int32(0), jnp.arange(n, dtype=jnp.int32))
        lanes = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
        lanes = lanes._replace(env=lanes.env.replace(done=jnp.ones((n,), jnp.float32)))
        # One buffer per leaf: the iteration donates its state, and a buffer given twice is refused.
        cursor, iteration, seed = (jnp.full((), v, jnp.int32) for v in (0, 0, live.seed))
        # The window holds each step's recorded_obs, time first: one step's shapes, not a
        # trace of the whole rollout.
        step_obs = jax.eval_shape(lambda: recorded_obs(jax.vmap(pol.predict)(jax.vmap(env.observe)(lanes.env).obs,
                                                                            lanes.policy)[0]))
        window_obs = jax.tree.map(lambda s: jnp.zeros((live.window_steps, *s.shape), s.dtype), step_obs)
        return TrainState(params, optimizer.init(params), lanes, cursor, iteration, seed, window_obs)

    def recorded_obs(inputs):
        """What the window keeps of a step's policy inputs: the panorama as the policy's CNN reads
        it (policy.prepare_panorama: made once here, not on each of the update's passes over
        the window) and the other inputs, float32."""
        rest = {k: inputs[k].astype(jnp.float32) for k in keys if k not in PANORAMA_SOURCES}
        return {**policy.prepare_panorama(policy_config, inputs), **rest}

    def rollout(params, lanes: Lanes, cursor, seed, key, beta, stages: int = len(ROLLOUT_STAGES), window_obs=None):
        if window_obs is not None and stages < len(ROLLOUT_STAGES):
            raise ValueError("a rollout of fewer stages keeps compact observations, not a TrainState's window_obs")

        def step(carry, step_key):
            (lanes, cursor, buffer), t = carry
            # Named scopes label a profile's kernels by part of the step.
            with jax.named_scope("refill"):
                lanes, cursor, first = refill(lanes, cursor, seed)
            with jax.named_scope("observe"):
                obs = jax.vmap(env.observe)(lanes.env).obs
            inputs, pcarry = {k: obs[k] for k in keys if k in obs}, lanes.policy
            label, ecarry = jnp.zeros((n, 2)), lanes.expert
            if stages > ROLLOUT_STAGES.index("expert"):
                with jax.named_scope("expert"):
                    label, ecarry = jax.vmap(expert)(lanes.env, lanes.expert)
            expert_acts = jax.random.uniform(step_key, (n,)) < beta
            if stages <= ROLLOUT_STAGES.index("learner"):  # `live_throughput`'s parts of a step
                return step_out(lanes, cursor, buffer, t, first, im.compact_obs(inputs), label, ecarry, pcarry,
                                expert_acts, label)
            with jax.named_scope("predictors"):
                inputs, pcarry = jax.vmap(pol.predict)(obs, lanes.policy)  # the predictors follow every step
            with jax.named_scope("prepare"):
                prepared = recorded_obs(inputs)
                # Written into the buffer first, and read back from it by the learner: the
                # panorama is made straight into its slot (nothing else holds it whole).
                buffer, recorded = write(buffer, t, prepared)

            def mixed(operands):
                pcarry, buffer = operands
                step_obs = prepared if buffer is None else jax.tree.map(
                    lambda b: jax.lax.dynamic_index_in_dim(b, t, 0, keepdims=False), buffer)
                action, _, lstm = policy.apply(params, policy_config, step_obs, pcarry.lstm, reset=first)
                return jnp.where(expert_acts[:, None], label, action), pcarry._replace(lstm=lstm)

            # beta is one scalar for all lanes: with beta >= 1 the learner does not run here.
            with jax.named_scope("learner"):
                action, pcarry = jax.lax.cond(beta >= 1.0, lambda ops: (label, ops[0]), mixed, (pcarry, buffer))
            return step_out(lanes, cursor, buffer, t, first, recorded, label, ecarry, pcarry, expert_acts, action)

        def write(buffer, t, recorded):
            """(buffer, what the scan stacks): `recorded` written in place at step `t` of a
            TrainState's window buffer, else stacked by the scan."""
            if buffer is None:
                return buffer, recorded
            return jax.tree.map(lambda b, v: jax.lax.dynamic_update_index_in_dim(b, v, t, 0), buffer, recorded), {}

        def step_out(lanes, cursor, buffer, t, first, recorded, label, ecarry, pcarry, expert_acts, action):
            with jax.named_scope("env_step"):
                state = jax.vmap(functools.partial(env.step, observe=False))(lanes.env, action)
            ended = state.done > 0
            data = lanes.env.pipeline_state
            rec = Window(recorded, label, first, expert_acts, lanes.env.info["episode"],
                         lanes.position, data.userdata[:, UD["t"]].astype(jnp.int32), data.qpos, ended,
                         ended & (state.metrics["reached"] > 0))
            return ((Lanes(state, ecarry, pcarry, lanes.position), cursor, buffer), t + 1), rec

        carry = ((lanes, cursor, window_obs), jnp.int32(0))
        ((lanes, cursor, buffer), _), window = jax.lax.scan(step, carry, jax.random.split(key, live.window_steps))
        return lanes, cursor, window if buffer is None else window._replace(obs=buffer)

    def update(params, opt_state, lstm: LSTMState, window: Window):
        # Time-major as the rollout wrote it, and prepared (recorded_obs): the window's panoramas
        # are never transposed or widened here.
        batch = {"obs": window.obs, "label": window.label, "reset": window.first,
                 "mask": jnp.ones(window.first.shape, jnp.float32)}

        def loss_fn(p):
            loss, _, end, actions = im.sequence_loss(p, policy_config, batch, jax.lax.stop_gradient(lstm), live.remat,
                                                     time_major=True, prepare=None)
            return loss, (end, actions)

        (loss, (end, actions)), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        grads, grad_norm = clip_by_global_norm(grads, live.grad_clip)
        lr = schedule(opt_state.step)
        params, opt_state = optimizer.update(grads, opt_state, params)
        # A policy whose action spread stays far below the labels' has stopped reading its
        # inputs (the mean action), whatever its loss says.
        metrics = {"loss": loss, "grad_norm": grad_norm, "lr": lr, "action_spread": _spread(actions),
                   "label_spread": _spread(window.label)}
        return params, opt_state, jax.lax.stop_gradient(end), metrics

    def iteration(state: TrainState, key):
        beta = live.beta(state.iteration)
        with jax.named_scope("rollout"):
            lanes, cursor, window = rollout(state.params, state.lanes, state.cursor, state.seed, key, beta,
                                            window_obs=state.window_obs)
        # The window's LSTM starts from the carry the lanes had before it (state.lanes), and the
        # next one from where the update's pass (with the weights that acted) ended.
        with jax.named_scope("update"):
            params, opt_state, end, metrics = update(state.params, state.opt_state, state.lanes.policy.lstm, window)
        lanes = lanes._replace(policy=lanes.policy._replace(lstm=end))
        metrics = {**metrics, "beta": beta, "expert_share": window.expert_acted.mean(),
                   "episodes": window.ended.sum(), "reached": window.reached.sum(),
                   "label_v_lin": window.label[..., 0].mean(), STEPS: window._replace(obs={})}
        return TrainState(params, opt_state, lanes, cursor, state.iteration + 1, state.seed, window.obs), metrics

    return Live(init, rollout, update, iteration, pol.source)


def make_iteration(env: ConavEnv, policy_config: PolicyConfig, live: LiveConfig, intention=None, trajectory=None,
                   expert_config: ExpertConfig = ExpertConfig(), compiler_options: tuple = (), seeds: int = 1,
                   teacher=None):
    """(`Live`, the jitted iteration `(TrainState, key) -> (TrainState, metrics)`, the bank an
    argument of the compiled program), shared by runs of one process with the same inputs but
    for the cadences and the seed (a resumed run, and every seed of one configuration, reuse the
    compiled code: `init` takes the seed from `live`, the iteration from the TrainState).
    `compiler_options`: `jax.jit`'s, as sorted pairs. `seeds` > 1: the iteration of that many
    runs together (`train_live_seeds`), taking `stack_runs` of their states and their keys
    stacked; `init` stays one run's. `teacher`: make_live's."""
    if seeds < 1:
        raise ValueError(f"make_iteration.seeds must be at least 1, got {seeds}")
    shared = dataclasses.replace(live, seed=0, **{k: 1 for k in CADENCE_FIELDS})
    fns, iteration = _iteration(env, policy_config, shared, intention, trajectory, expert_config, compiler_options,
                                teacher=teacher)
    if seeds > 1:
        iteration = _iteration(env, policy_config, shared, intention, trajectory, expert_config, compiler_options,
                               seeds, teacher)[1]
    if live.seed != shared.seed:  # the same compiled iteration; an init of this seed
        fns = fns._replace(init=make_live(env, policy_config, live, intention, trajectory, expert_config,
                                          teacher=teacher).init)
    return fns, iteration


# The vmapped axis of `train_live_seeds`'s runs; what it maps: every TrainState field but the
# iteration, which the runs share (so beta, and the learner's cond on it, stay one scalar).
SEED_AXIS = "seed"
SEEDS_STATE_AXES = TrainState(params=0, opt_state=0, lanes=0, cursor=0, iteration=None, seed=0, window_obs=0)


@functools.lru_cache(maxsize=8)
def _iteration(env, policy_config, live, intention, trajectory, expert_config, compiler_options, seeds: int = 1,
               teacher=None):
    fns = make_live(env, policy_config, live, intention, trajectory, expert_config,
                    seed_axis=SEED_AXIS if seeds > 1 else None, teacher=teacher)
    iteration = fns.iteration
    if seeds > 1:
        iteration = jax.vmap(fns.iteration, in_axes=(SEEDS_STATE_AXES, 0), out_axes=(SEEDS_STATE_AXES, 0),
                             axis_name=SEED_AXIS, axis_size=seeds)
    donate = () if jax.default_backend() == "cpu" else (1,)  # the bank is argument 0
    return fns, jit_with_bank(env, iteration, compiler_options=dict(compiler_options) or None,
                              donate_argnums=donate)


# -- checkpoints ---------------------------------------------------------------------------------


def _state_tree(state: TrainState) -> tuple[dict, dict]:
    """(params, the checkpoint's "opt_state" member): Adam's state and the rest of the
    TrainState as a list of its leaves (the env state is a dataclass the checkpoint format does
    not hold; a template TrainState rebuilds it, `_from_tree`)."""
    rest = (state.lanes, state.cursor, state.iteration)
    return state.params, {"adam": state.opt_state, "live": jax.tree.leaves(rest)}


def _from_tree(template: TrainState, params, opt_state: dict) -> TrainState:
    """The TrainState of a checkpoint's members; its seed and scratch are the template's."""
    rest = jax.tree.unflatten(jax.tree.structure((template.lanes, template.cursor, template.iteration)),
                              opt_state["live"])
    return TrainState(params, opt_state["adam"], *rest, template.seed, template.window_obs)


def run_config(policy_config: PolicyConfig, live: LiveConfig, expert_config: ExpertConfig, env: ConavEnv,
               source: str, intention_run, trajectory_run, task: ImitationTask | None = None) -> dict:
    """The checkpoint's config: a "policy" run's keys (the PolicyConfig as "model", the
    predictor runs the agent reads), and what the weights depend on; with a `task`, its kind
    and what it records of its teacher (under "teacher") in place of the expert's config."""
    teacher = {"expert": dataclasses.asdict(expert_config)} if task is None else {"teacher": task.config}
    return {
        "kind": KIND if task is None else task.kind,
        "model": config_dict(policy_config),
        "live": live.weights_fields(),
        "imitation": {"train_intentions": PREDICTED if source == PREDICTED else GROUND_TRUTH},
        **teacher,
        "env": {"split": env.split.name, "episodes": int(env.num_episodes), "end_at_reach": env.config.end_at_reach},
        "materials": env.config.sensor.materials,  # what the training env renders (checked by the agent)
        "intention_source": source,
        "intention_run": None if intention_run is None else str(intention_run),
        "trajectory_run": None if trajectory_run is None else str(trajectory_run),
        PROVENANCE_KEY: provenance(**env_settings(env.config), encoder=encoder_name(policy_config),
                                   conv_dtype=policy_config.conv_dtype),
    }


# -- the run ---------------------------------------------------------------------------------------


class LiveResult(NamedTuple):
    state: TrainState
    policy_config: PolicyConfig
    env_steps: int  # control steps trained on, over the whole run
    episodes_started: int  # queue positions handed out
    run_dir: Path


def _predictor(given, load):
    """(predictor, its run dir or None): `given` is a run dir (loaded) or a predictor object."""
    if given is None or not isinstance(given, (str, Path)):
        return given, None
    return load(given), str(given)


def train_live(
    env: ConavEnv,
    policy_config: PolicyConfig,
    live: LiveConfig,
    out_dir: str | Path,
    intention=None,
    trajectory=None,
    expert_config: ExpertConfig = ExpertConfig(),
    progress: bool = True,
    compiler_options: dict | None = None,
    task: ImitationTask | None = None,
) -> LiveResult:
    """Train the CoNav policy by imitation from the live simulator `env` (its train split; build
    it with `end_at_reach=True`, as the other trainers do) into the run directory `out_dir`
    (give large panoramas a `policy_config` with `visual_norm=True`, as DEFAULT_POLICY),
    resuming bit for bit from its latest checkpoint if it has one (of the same configs, else
    ValueError naming the first difference; `LiveConfig.ckpt_every` and `log_every` may change).

    `intention`, `trajectory`: the predictors whose outputs the learner reads, each a run
    directory (recorded in the run: the CoNav agent loads them from there) or a predictor
    object (envs.agents.predictors); none: the env's ground-truth intentions (privileged).
    Logs every `live.log_every` iterations: loss, gradient norm, learning rate, beta, the
    expert's share of the actions, episodes finished (and reached), env timesteps, and the
    spread (standard deviation over the window's steps) of the learner's actions beside the
    labels': a policy that ignores its inputs shows an action spread near 0. The last
    checkpoint holds the weights and Adam's state alone: a finished run, run again, returns
    them with its lanes as a fresh run's.

    `task`: a goal-navigation baseline's (train.goalnav.objectnav_task): its teacher labels and
    acts in place of the expert, and the run is of its kind (loaded as that baseline's agent).
    A task whose policy reads a goal image is refused (live imitation renders none)."""
    return train_live_seeds(env, policy_config, [live], [out_dir], intention, trajectory, expert_config, progress,
                            compiler_options, task)[0]


def train_live_seeds(
    env: ConavEnv,
    policy_config: PolicyConfig,
    lives: list[LiveConfig],
    out_dirs: list[str | Path],
    intention=None,
    trajectory=None,
    expert_config: ExpertConfig = ExpertConfig(),
    progress: bool = True,
    compiler_options: dict | None = None,
    task: ImitationTask | None = None,
) -> list[LiveResult]:
    """`train_live` for several runs of one configuration that differ only in their
    `LiveConfig.seed` (and cadences), run `lives[i]` into `out_dirs[i]`, trained together: one
    compiled iteration steps every run's lanes and updates every run's weights (jax.vmap over
    the runs), so the runs share one compile and a GPU that one run's lanes leave partly idle.
    Each run's log and checkpoints are those `train_live` writes (it is this with one run), and
    each resumes as it does; the runs must stand at the same iteration (ValueError otherwise:
    train them one by one), and write logs and checkpoints at the first's cadences. Seed s's
    episode order and initial weights are its own, as alone; its updates differ from a lone
    run's only by rounding (a batched program may sum in another order), which, as between two
    runs of one seed on a GPU, grows over a run. ValueError for configs that differ in more
    than the seed, repeated seeds or directories. `task`: train_live's."""
    if task is not None and task.goal_obs is not None:
        raise ValueError(f"the {task.kind} task's policy reads a goal image, which live imitation does not render: "
                         "train it with its offline trainer (train.goalnav)")
    if not lives or len(lives) != len(out_dirs):
        raise ValueError(f"train_live_seeds needs one out_dir per LiveConfig, got {len(lives)} and {len(out_dirs)}")
    shared = dataclasses.replace(lives[0], seed=0, **{k: 1 for k in CADENCE_FIELDS})
    for live in lives:
        if dataclasses.replace(live, seed=0, **{k: 1 for k in CADENCE_FIELDS}) != shared:
            diff = [k for k in live.weights_fields() if k != "seed" and getattr(live, k) != getattr(lives[0], k)]
            raise ValueError(f"train_live_seeds: the LiveConfigs differ in {', '.join(diff)}, not only in seed")
    seeds, dirs = [live.seed for live in lives], [Path(d).resolve() for d in out_dirs]
    if len(set(seeds)) < len(seeds) or len(set(dirs)) < len(dirs):
        raise ValueError(f"train_live_seeds: repeated seeds {seeds} or out_dirs {[str(d) for d in out_dirs]}")
    intention, intention_run = _predictor(intention, lambda r: load_predictors(r, None)[0])
    trajectory, trajectory_run = _predictor(trajectory, lambda r: load_predictors(None, r)[1])
    k = len(lives)
    options = tuple(sorted((compiler_options or {}).items()))
    # A lone run's init (of seed 0: _initial_state sets each run's) beside the runs' iteration.
    teacher = None if task is None else task.teacher
    fns, iteration = make_iteration(env, policy_config, shared, intention, trajectory, expert_config, options, k,
                                    teacher)
    configs, states = [], []
    for live, run_dir in zip(lives, out_dirs):
        config = run_config(policy_config, live, expert_config, env, fns.source, intention_run, trajectory_run, task)
        configs.append(config)
        states.append(_initial_state(fns.init, policy_config, live, Path(run_dir), config))
    at = sorted({int(state.iteration) for state in states})
    if len(at) > 1:
        raise ValueError(f"train_live_seeds: the runs stand at different iterations {at}; train them one by one")
    start_it, per_iter, live = at[0], shared.timesteps_per_iteration, lives[0]
    state = states[0] if k == 1 else stack_runs(states)
    del states
    one = (lambda st, i: st) if k == 1 else _run_of
    log_paths = [Path(d) / runs.LOG_FILE for d in out_dirs]

    def save(it: int) -> None:
        for i, (run_dir, config) in enumerate(zip(out_dirs, configs)):
            _save(one(state, i), it, Path(run_dir), config, live.iterations, per_iter)

    bar = tqdm(total=live.iterations * per_iter * k, initial=start_it * per_iter * k, disable=not progress,
               unit="step", dynamic_ncols=True)
    pending: list = []
    t0 = time.perf_counter()
    try:
        for it in range(start_it + 1, live.iterations + 1):
            state, metrics = iteration(state, iteration_keys(seeds, it - 1))
            pending.append({name: v for name, v in metrics.items() if name != STEPS})
            last = it == live.iterations
            if it % live.log_every == 0 or last:
                seconds, host = time.perf_counter() - t0, jax.device_get(pending)
                cursors = np.atleast_1d(np.asarray(jax.device_get(state.cursor)))
                for i, log_path in enumerate(log_paths):
                    mine = host if k == 1 else [jax.tree.map(lambda x: x[i], m) for m in host]
                    record = _log_record(mine, it, per_iter, seconds, int(cursors[i]))
                    append_log(log_path, record)
                    if record["loss"] is None or record["grad_norm"] is None:  # not finite: nothing saved
                        raise FloatingPointError(f"non-finite loss or gradient by iteration {it}; see {log_path}")
                bar.set_postfix(loss=f"{record['loss']:.4g}", beta=f"{record['beta']:.3g}")
                bar.update(len(pending) * per_iter * k)
                pending, t0 = [], time.perf_counter()
            if it % live.ckpt_every == 0 or last:
                save(it)
    finally:
        bar.close()
    results = []
    for i, run_dir in enumerate(out_dirs):
        mine = one(state, i)
        results.append(LiveResult(mine, policy_config, int(mine.iteration) * per_iter, int(mine.cursor), Path(run_dir)))
    return results


def stack_runs(states: list[TrainState]) -> TrainState:
    """Runs' TrainStates, standing at one iteration, as the iteration of runs together takes them
    (`make_iteration(..., seeds=len(states))`): each field stacked on a leading axis
    (SEEDS_STATE_AXES) but the iteration they share. Each run's window scratch is dropped from
    `states` before the stacked one is made (the list is emptied: pass it, not a copy to keep)."""
    scratch = jax.tree.map(lambda x: jax.ShapeDtypeStruct((len(states), *x.shape), x.dtype), states[0].window_obs)
    iteration, names = states[0].iteration, [n for n in TrainState._fields if n not in ("iteration", "window_obs")]
    rest = [[getattr(st, name) for name in names] for st in states]
    states.clear()  # the runs' scratch buffers go now
    stacked = {name: jax.tree.map(lambda *xs: jnp.stack(xs), *fields) for name, fields in zip(names, zip(*rest))}
    del rest
    return TrainState(**stacked, iteration=iteration,
                      window_obs=jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), scratch))


def _run_of(state: TrainState, i: int) -> TrainState:
    """Run `i` of `train_live_seeds`'s stacked TrainState (the iteration is theirs together),
    without the window scratch (not state, and the largest of its fields: never copied out)."""
    return TrainState(*(field if name == "iteration" else {} if name == "window_obs" else
                        jax.tree.map(lambda x: x[i], field) for name, field in zip(TrainState._fields, state)))


def _initial_state(init, policy_config: PolicyConfig, live: LiveConfig, run_dir: Path, config: dict) -> TrainState:
    """A run's TrainState to start from: `init`'s (a `Live.init` of any seed: the state of seed
    `live.seed` differs only in its weights and seed field) or its latest checkpoint's in
    `run_dir` (runs.resume: ValueError for another config)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    state = init(policy.init(jax.random.PRNGKey(live.seed), policy_config))
    state = state._replace(seed=jnp.full((), live.seed, jnp.int32))
    # Shapes alone as the template: the state loads as a fresh one is placed, and reuses its compile.
    shapes = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), _state_tree(state))
    latest = latest_checkpoint(run_dir)
    finished = latest is not None and latest == checkpoint_path(run_dir, live.iterations)
    if finished:  # the last checkpoint keeps no lanes (`_save`)
        shapes = (shapes[0], {"adam": shapes[1]["adam"]})
    ckpt = runs.resume(run_dir, config, *shapes)
    if ckpt is not None and finished:
        return state._replace(params=ckpt.params, opt_state=ckpt.opt_state["adam"],
                              cursor=jnp.full((), ckpt.extra["episodes_started"], jnp.int32),
                              iteration=jnp.full((), live.iterations, jnp.int32))
    if ckpt is not None:
        return _from_tree(state, ckpt.params, ckpt.opt_state)
    return state


def _save(state: TrainState, it: int, run_dir: Path, config: dict, iterations: int, per_iter: int) -> None:
    params, opt_tree = _state_tree(state)
    if it == iterations:
        # A finished run keeps its weights and Adam's state, not the lanes' env states (most
        # of a checkpoint's bytes at many lanes): nothing resumes from them.
        opt_tree = {"adam": opt_tree["adam"]}
    save_checkpoint(checkpoint_path(run_dir, it), params=params, opt_state=opt_tree, config=config, step=it,
                    extra={"env_steps": it * per_iter, "episodes_started": int(state.cursor)})


def _log_record(pending: list[dict], it: int, per_iter: int, seconds: float, cursor: int) -> dict:
    """One log record: the means of the pending iterations' metrics, their episode counts summed."""
    host = jax.tree.map(lambda *xs: np.asarray(xs, np.float64), *jax.device_get(pending))
    episodes, reached = int(host.pop("episodes").sum()), int(host.pop("reached").sum())
    record = {"step": it, "split": "train", "env_steps": it * per_iter,
              **{k: finite_or_none(v.mean()) for k, v in host.items()},
              "episodes": episodes, "reach_rate": reached / episodes if episodes else None,
              "episodes_started": cursor, "steps_per_s": round(len(pending) * per_iter / seconds, 1)}
    return record


def train_live_from_data(data_dir: str | Path, out_dir: str | Path,
                         policy_config: PolicyConfig = DEFAULT_POLICY,
                         live: LiveConfig = LiveConfig(), intention_run=None, trajectory_run=None,
                         **kwargs) -> LiveResult:
    """`train_live` on the train split of the dataset `data_dir`, its env rendering the policy's
    resolution, episodes ending at the first reach (as every trainer runs them)."""
    from conav_jax.envs import EnvConfig, SensorConfig

    h, w = policy_config.resolution
    env = ConavEnv(str(data_dir), "train", EnvConfig(sensor=SensorConfig(resolution=(h, w)), end_at_reach=True))
    return train_live(env, policy_config, live, out_dir, intention_run, trajectory_run, **kwargs)


def train_live_seeds_from_data(data_dir: str | Path, out_dirs: list[str | Path],
                               policy_config: PolicyConfig = DEFAULT_POLICY,
                               lives: list[LiveConfig] = (LiveConfig(),), intention_run=None, trajectory_run=None,
                               **kwargs) -> list[LiveResult]:
    """`train_live_seeds` on the train split of the dataset `data_dir` (as `train_live_from_data`)."""
    from conav_jax.envs import EnvConfig, SensorConfig

    h, w = policy_config.resolution
    env = ConavEnv(str(data_dir), "train", EnvConfig(sensor=SensorConfig(resolution=(h, w)), end_at_reach=True))
    return train_live_seeds(env, policy_config, list(lives), list(out_dirs), intention_run, trajectory_run, **kwargs)
