"""Batched rollouts: any agent through the env, `lax.scan` over time, `vmap` over episodes.

An agent (envs.agents.base) acts for ONE environment (the rollout vmaps it): an observation-only
`Agent` sees the observation keys it reads and nothing else; an internal `StateAgent` (an
oracle baseline, the expert) the env's brax State with those keys, and the env's constants
through a closure. Each step observes exactly what the agent reads (ConavEnv.observe), so what
no agent reads is never computed. Oracle movers step through ConavEnv.step_to_pose, every other
agent through ConavEnv.step. A learned agent's weights are the compiled rollout's arguments,
not its constants (envs.agents.lift), so runs of one configuration share a program. This module
is what evaluation sweeps, DAgger and validation during training all run on. With a device mesh
(conav_jax.parallel), each batch of episodes is split over the devices.
"""

from __future__ import annotations

from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import State
from jax.sharding import Mesh

from conav_jax.parallel import (
    constrain_batch,
    replicate,
    round_up,
    shard_batch,
    to_host,
    traced_under,
)
from conav_jax.envs.agents.base import MIXED_ACTION_SIZE, Agent, StateAgent, as_state_agent
from conav_jax.envs.agents.lift import lift_agent
from conav_jax.envs.conav_env import ConavEnv
from conav_jax.envs.mjcf import UD


class Trace(NamedTuple):
    """Per-step records of a rollout, (B, T, ...): enough to recompute every metric by hand
    (envs.metrics) beside the episode's constants."""

    robot_pose: jax.Array  # (x, y, yaw) world, after the step
    action: jax.Array  # the agent's action in [-1, 1]
    reward: jax.Array
    done: jax.Array
    human_contact: jax.Array  # 1 if the robot touched the human in this step
    wall_contact: jax.Array  # 1 if it touched a wall or furniture in this step


def trace_step(state: State, action: jax.Array) -> Trace:
    """The Trace entry of one step (of one env, or a batch of them): the state after it and the
    action that led there."""
    ud = state.pipeline_state.userdata
    return Trace(state.pipeline_state.qpos, action, state.reward, state.done, ud[..., UD["human_touch"]],
                 ud[..., UD["wall_touch"]])


def jit_with_bank(env: ConavEnv, fn: Callable, mesh: Mesh | None = None, **jit_kwargs) -> Callable:
    """`jax.jit(fn)`, called like `fn`, whose trace reads the env's episode bank as an argument
    (ConavEnv.bound_bank) rather than as constants: the compiled program holds no episode data,
    so it compiles in the same time for 6 episodes or 5,000, and a bigger split needs no new
    compile of anything but the shapes. Agents must read `env.bank` when they act (they do).
    `mesh`: the mesh the program's lanes are split over; it is traced under it, so the Pallas
    caster casts each device's lanes on that device (conav_jax.parallel.lanes_on_devices)."""

    def traced(bank, *args):
        with env.bound_bank(bank), traced_under(mesh):
            return fn(*args)

    jitted = jax.jit(traced, **jit_kwargs)

    def run(*args):
        return jitted(env.bank, *args)

    run.lower = lambda *args: jitted.lower(env.bank, *args)  # for inspecting the program
    return run


def make_param_rollout(env: ConavEnv, agent_fn: Callable[[Any], Agent | StateAgent], num_steps: int, record: bool = False,
                       compiler_options: dict | None = None, mesh: Mesh | None = None):
    """A jitted function (params, key, episodes (B,)) -> (final metrics dict of (B,), Trace | None)
    for the agent `agent_fn(params)` builds. The agent is built inside the trace, so new params
    of the same structure reuse the compiled rollout (an Agent closing over its params would
    compile once per set: training-time validation needs this form). `compiler_options` go to
    `jax.jit`; `mesh`: the one the episodes are split over (`jit_with_bank`).

    Runs `num_steps` steps; episodes that end earlier stay frozen (the env's contract), so
    the final metrics are each episode's result at its end."""

    def one(agent, start):
        state, carry, k_run = start

        def body(c, i):
            state, carry = c
            state, action, carry = agent_step(env, agent, state, carry, jax.random.fold_in(k_run, i))
            out = None
            if record:
                out = trace_step(state, action)
            return (state, carry), out

        (state, _), trace = jax.lax.scan(body, (state, carry), jnp.arange(num_steps))
        return state.metrics, trace

    def run(params, key, episodes):
        # The start on its own: every carry leaf then enters the scan batched (for a partly
        # unbatched carry, vmap batches the scan's body, the whole env step, again until the
        # batched leaves settle: seconds of compile time).
        agent = as_state_agent(agent_fn(params))
        start = jax.vmap(lambda episode: _start(env, agent, key, episode))(episodes)
        return jax.vmap(partial(one, agent))(start)

    return jit_with_bank(env, run, mesh=mesh, compiler_options=compiler_options)


def agent_step(env: ConavEnv, agent: StateAgent, state: State, carry: Any, key: jax.Array):
    """One step of one env: `(state, agent carry, key) -> (state, action, carry)`, the states
    without their observation (ConavEnv.step's `observe=False`). The observation is made here,
    the keys the agent reads and no other, for the agent to act on, and not carried to the next
    step: what the agent does not read (an image, for most scripted agents) is never rendered,
    and an ended episode's image is not kept. Rollouts start from `_start`'s state, which has
    none either. An oracle mover's pose goes through ConavEnv.step_to_pose."""
    # Named scopes label a profile's kernels (SWEEP_PROFILE_SCOPES).
    with jax.named_scope("observe"):
        obs = env.observe(state, agent.reads)
    with jax.named_scope("agent"):
        action, carry = agent.act(obs, carry, key)
    with jax.named_scope("env_step"):
        state = apply_action(env, agent, state, action)
    return state, action, carry


# The parts of a rollout step a profile reports (conav_jax.profiling): refilling lanes, the
# agent's observation, its predictors and policy (the CoNav agent's), the rest of acting, the env step.
SWEEP_PROFILE_SCOPES = ("refill", "observe", "predictors", "policy", "agent", "env_step")


def apply_action(env: ConavEnv, agent: StateAgent, state: State, action: jax.Array) -> State:
    """`state` after `agent`'s `action`, without its observation: ConavEnv.step for velocities,
    ConavEnv.step_to_pose for an oracle mover's pose (or switch_agent's mixed form)."""
    if agent.action_size == 3:
        return env.step_to_pose(state, action, observe=False)
    if agent.action_size == MIXED_ACTION_SIZE:
        return env.step_to_pose(state, action[3:], observe=False, action=action[1:3], use_pose=action[0] > 0.5)
    return env.step(state, action, observe=False)


def _start(env: ConavEnv, agent: StateAgent, key: jax.Array, episode: jax.Array):
    """(state without its observation, agent carry, step key) of `episode`'s start. Keys come
    from (key, episode) alone, and the agent's key at step i is fold_in(step key, i): an
    episode's result does not depend on the batch it runs in, its place there, or the device
    count."""
    k_init, k_run = jax.random.split(jax.random.fold_in(key, episode))
    state = env.reset_to_episode(k_init, episode, observe=False)
    return state, agent.init(k_init, env.observe(state, agent.reads)), k_run


def make_rollout(env: ConavEnv, agent: Agent | StateAgent, num_steps: int, record: bool = False,
                 mesh: Mesh | None = None):
    """A jitted function (key, episodes (B,)) -> (final metrics dict of (B,), Trace | None):
    `make_param_rollout` of the agent with its weights taken out as the program's arguments
    (envs.agents.lift)."""
    lifted = lift_agent(env, agent)
    run = make_param_rollout(env, lifted.agent_fn, num_steps, record, mesh=mesh)
    params = lifted.params if mesh is None else replicate(lifted.params, mesh)
    return lambda key, episodes: run(params, key, episodes)


def map_episodes(
    fn: Callable[[jax.Array, jax.Array], Any],
    episodes: np.ndarray,
    batch: int,
    key: jax.Array,
    mesh: Mesh | None = None,
    progress: Callable | None = None,
    per_batch_keys: bool = True,
    host_fn: Callable[[Any], Any] | None = None,
) -> Any:
    """`fn(key, indices) -> pytree of (size, ...) arrays` over `episodes` in batches of `batch`
    -> host (numpy) pytree of `(len(episodes), ...)`; with `host_fn`, each batch's host pytree
    goes through it before the batches are concatenated (to shrink what the host keeps, e.g.
    records cut into training windows).

    Batch `s` (starting at episode `s0`) gets `fold_in(key, s0)` (`key` itself with
    `per_batch_keys=False`, for rollouts that key each episode by its index). Each batch is padded by
    repeating its last episode to `size = batch` rounded up to a multiple of the mesh's device
    count (results of the padding are dropped), so one compiled function serves every batch;
    with a `mesh` its indices are split over the devices and the key replicated. Keys of a
    batch do not depend on the padding (jax's partitionable threefry), so results do not
    depend on the device count."""
    chunks = []
    for _, n, k, idx in episode_batches(episodes, batch, key, mesh, progress, per_batch_keys):
        out = jax.tree.map(lambda x: x[:n], to_host(fn(k, idx)))
        chunks.append(out if host_fn is None else host_fn(out))
    return jax.tree.map(lambda *xs: np.concatenate(xs), *chunks)


def episode_batches(
    episodes: np.ndarray,
    batch: int,
    key: jax.Array,
    mesh: Mesh | None = None,
    progress: Callable | None = None,
    per_batch_keys: bool = True,
):
    """`map_episodes`' batches, one at a time: `(s0, n, key, indices)` with the batch's first
    position in `episodes`, its count of real episodes, its key and its `(size,)` int32 indices
    on the device (padded, split over the mesh's devices, the key replicated), as `map_episodes`
    describes. ValueError for anything but a non-empty 1-D array of episodes."""
    episodes = np.asarray(episodes)
    if episodes.ndim != 1 or len(episodes) == 0:
        raise ValueError("episodes must be a non-empty 1-D array of episode indices")
    batch = min(batch, len(episodes))
    size = round_up(batch, mesh)
    starts = range(0, len(episodes), batch)
    for s0 in progress(starts) if progress else starts:
        idx = episodes[s0 : s0 + batch]
        n = len(idx)
        idx = np.concatenate([idx, np.full(size - n, idx[-1])]).astype(np.int32)
        k = jax.random.fold_in(key, s0) if per_batch_keys else key
        if mesh is None:
            yield s0, n, k, jnp.asarray(idx)
        else:
            yield s0, n, replicate(k, mesh), shard_batch(idx, mesh)


def select_lanes(mask: jax.Array, new, old):
    """Per lane, `new` where `mask (B,)` is True, else `old` (pytrees of (B, ...) arrays)."""
    return jax.tree.map(lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old)


class Lanes(NamedTuple):
    """The pool's parallel lanes, each (slots, ...): the env state, the agent's carry, the
    episode's step key and the step count within the episode."""

    state: State
    carry: Any
    key: jax.Array
    step: jax.Array


class Pool(NamedTuple):
    """The refilling evaluator's while-loop carry."""

    lanes: Lanes
    position: jax.Array  # (slots,) the queue position each lane runs
    active: jax.Array  # (slots,) bool: the lane runs an episode whose result is still to come
    results: dict  # final metrics by queue position, (Q,) each
    next_position: jax.Array  # () the next queue position to hand out
    trace: Trace  # queue[0]'s steps (trace_steps, ...)
    chunks: jax.Array  # () chunks of steps run so far


def make_pool_rollout(
    env: ConavEnv,
    agent_fn: Callable[[Any], Agent | StateAgent],
    slots: int,
    chunk: int = 16,
    mesh: Mesh | None = None,
    trace_steps: int = 0,
    compiler_options: dict | None = None,
):
    """A jitted `(params, key, queue (Q,) int32, n (), max_chunks () = None) -> final metrics
    dict of (Q,)` that runs episodes `queue[:n]` on `slots` parallel lanes, refilling a lane with the next queued
    episode as soon as its episode has ended (checked every `chunk` steps), until every
    episode has run to its end. Work is the sum of the episodes' lengths (plus under `chunk`
    idle steps each, and the tail), not `batches x the longest episode` as in fixed batches:
    about half on the paper preset's val split (mean 568 steps, longest 1,087).

    Keys as `make_param_rollout` (from (key, episode) alone), so the metrics equal its
    full-length rollout's, episode by episode. With a `mesh` the lanes are split over its
    devices (`slots` must divide by the device count). Entries `queue[n:]` are padding.

    With `trace_steps > 0` it returns `(metrics, Trace)` where the Trace (`trace_steps`, ...)
    follows `queue[0]`'s episode (lane 0's first) step by step, as `make_param_rollout(...,
    record=True)` records it (steps past the run are zeros): a map of one episode costs no
    second compile. `compiler_options` go to `jax.jit`.

    `max_chunks`, an argument, stops the loop after that many chunks, ended episodes or not:
    the evaluator passes no limit (the largest int32), and a profile the same program with a
    few chunks (the first one fills every lane)."""
    if chunk < 1 or slots < 1 or trace_steps < 0:
        raise ValueError("slots and chunk must be at least 1, trace_steps at least 0")

    def run(params, key, queue, n, max_chunks=None):
        agent = as_state_agent(agent_fn(params))
        q = queue.shape[0]

        def start(episodes):
            state, carry, k_run = jax.vmap(lambda ep: _start(env, agent, key, ep))(episodes)
            return Lanes(state, carry, k_run, jnp.zeros(episodes.shape, jnp.int32))

        # The lanes start empty and the loop's refill fills them on its first pass: the reset
        # (and its first render) is compiled once, inside the loop, not a second time outside.
        lanes = jnp.arange(slots)
        shapes = jax.eval_shape(start, lanes)
        empty = constrain_batch(jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes), mesh)
        out = jax.tree.map(lambda m: jnp.zeros((q,) + m.shape[1:], m.dtype), shapes.state.metrics)
        trace = jax.tree.map(lambda x: jnp.zeros((trace_steps,) + x.shape[1:], x.dtype),
                             jax.eval_shape(lambda l: trace_step(l.state, jnp.zeros((slots, agent.action_size))), shapes))

        def one_step(c, _):
            lane, trace, tracing = c
            keys = jax.vmap(jax.random.fold_in)(lane.key, lane.step)
            state, action, carry = jax.vmap(partial(agent_step, env, agent))(lane.state, lane.carry, keys)
            if trace_steps:  # lane 0 while it runs queue[0]; other steps write out of range (dropped)
                at = jnp.where(tracing, lane.step[0], trace_steps)
                now = jax.tree.map(lambda x: x[0], trace_step(state, action))
                trace = jax.tree.map(lambda buf, x: buf.at[at].set(x.astype(buf.dtype), mode="drop"), trace, now)
            return (Lanes(state, carry, lane.key, lane.step + 1), trace, tracing), None

        def body(c: Pool) -> Pool:
            # Free lanes take the next queued episodes, in lane order.
            free = ~c.active
            new_pos = c.next_position + jnp.cumsum(free) - 1
            take = free & (new_pos < n)
            refill = lambda lane: select_lanes(take, start(queue[jnp.clip(new_pos, 0, q - 1)]), lane)
            with jax.named_scope("refill"):
                lane = constrain_batch(jax.lax.cond(take.any(), refill, lambda lane: lane, c.lanes), mesh)
            position, active = jnp.where(take, new_pos, c.position), c.active | take
            (lane, trace, _), _ = jax.lax.scan(one_step, (lane, c.trace, position[0] == 0), None, length=chunk)
            finished = active & (lane.state.done > 0)
            out = jax.tree.map(lambda o, m: o.at[jnp.where(finished, position, q)].set(m, mode="drop"),
                               c.results, lane.state.metrics)
            return Pool(lane, position, active & ~finished, out, c.next_position + take.sum(), trace, c.chunks + 1)

        def running(c: Pool) -> jax.Array:
            busy = c.active.any() | (c.next_position < n)
            return busy if max_chunks is None else busy & (c.chunks < max_chunks)

        c = Pool(empty, lanes, jnp.zeros(slots, bool), out, jnp.int32(0), trace, jnp.int32(0))
        c = jax.lax.while_loop(running, body, c)
        return (c.results, c.trace) if trace_steps else c.results

    return jit_with_bank(env, run, mesh=mesh, compiler_options=compiler_options)


def evaluate(
    env: ConavEnv,
    agent: Agent | StateAgent,
    episodes: np.ndarray | None = None,
    batch: int = 256,
    seed: int = 0,
    mesh: Mesh | None = None,
    compiler_options: dict | None = None,
) -> dict[str, np.ndarray]:
    """Final metrics of every given episode (default: all of the bank, each exactly once), on
    `batch` parallel lanes refilled as episodes end (`make_pool_rollout`); with a `mesh`
    (conav_jax.parallel.make_mesh) the lanes are split over its devices, with the same results
    as on one device. `compiler_options` go to `jax.jit` for the rollout, which takes the agent's
    weights as arguments (envs.agents.lift)."""
    lifted = lift_agent(env, agent)
    evaluator = make_evaluator(env, lifted.agent_fn, batch, seed, mesh, compiler_options=compiler_options)
    return evaluator(lifted.params, episodes)


NO_CHUNK_LIMIT = 2**31 - 1  # make_pool_rollout's max_chunks for a whole sweep


def make_evaluator(
    env: ConavEnv,
    agent_fn: Callable[[Any], Agent | StateAgent],
    batch: int = 256,
    seed: int = 0,
    mesh: Mesh | None = None,
    trace_first: bool = False,
    compiler_options: dict | None = None,
) -> Callable[..., dict[str, np.ndarray]]:
    """`evaluate` for agents built from parameters: `evaluator(params, episodes=None) -> metrics`
    (as `evaluate` returns them). `batch` lanes run the episodes, longest first, each lane
    taking the next episode when its own ends (`make_pool_rollout`); when the episodes fit in
    the lanes, one full-length batch (`make_param_rollout`) instead. The rollout compiles on the
    first call; later params of the same structure and episode count reuse it (PPO validates
    every few iterations).

    With `trace_first` the evaluator returns `(metrics, episode, Trace)`: the Trace (host,
    (steps, ...) up to the episode's end) of `episode`, the longest of those given (the first
    one the lanes take). `compiler_options` go to `jax.jit` for the rollouts."""
    runs: dict = {}
    t_end = np.asarray(env.bank.t_end)
    steps = env.bank.max_steps if trace_first else 0

    def pool(slots: int, params, key, queue: np.ndarray):
        """(the refilling rollout of `slots` lanes, compiled on its first call, and its arguments
        for running `queue`)."""
        if slots not in runs:
            runs[slots] = make_pool_rollout(env, agent_fn, slots, mesh=mesh, trace_steps=steps,
                                           compiler_options=compiler_options)
        args = (params, key, jnp.asarray(queue), jnp.int32(len(queue)), jnp.int32(NO_CHUNK_LIMIT))
        return runs[slots], args if mesh is None else replicate(args, mesh)

    def queue_of(episodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the order the lanes take `episodes` in, longest first: the shortest fill the tail;
        the queue of episodes in that order)."""
        order = np.argsort(-t_end[episodes], kind="stable")
        return order, episodes[order].astype(np.int32)

    def evaluator(params, episodes: np.ndarray | None = None):
        episodes = np.arange(env.num_episodes) if episodes is None else np.asarray(episodes)
        if episodes.ndim != 1 or len(episodes) == 0:
            raise ValueError("episodes must be a non-empty 1-D array of episode indices")
        if episodes.min() < 0 or episodes.max() >= env.num_episodes:
            raise ValueError(f"episode indices must be in [0, {env.num_episodes})")
        n = len(episodes)
        slots = round_up(min(batch, n), mesh)
        order, queue = queue_of(episodes)
        key = jax.random.PRNGKey(seed)
        if slots >= n:
            # Every episode has a lane from the start: one full-length batch, the same results
            # for half the compile time of the refilling loop (measured on CPU and GPU).
            if ("batch", slots) not in runs:
                runs["batch", slots] = make_param_rollout(env, agent_fn, env.bank.max_steps, record=trace_first,
                                                        compiler_options=compiler_options, mesh=mesh)
            run = runs["batch", slots]
            if mesh is not None and params is not None:
                params = replicate(params, mesh)

            def first_trace(k, idx):  # only queue[0]'s trace comes back to the host
                metrics, trace = run(params, k, idx)
                return metrics, None if trace is None else jax.tree.map(lambda x: x[:1], trace)

            metrics, trace = map_episodes(first_trace, queue, slots, key, mesh, per_batch_keys=False)
            trace = None if trace is None else jax.tree.map(lambda x: x[0], trace)
        else:
            run, args = pool(slots, params, key, queue)
            result = to_host(run(*args))
            metrics, trace = result if trace_first else (result, None)
        out = {k: np.empty_like(v) for k, v in metrics.items()}
        for k, v in metrics.items():
            out[k][order] = v
        out["episode"] = episodes
        if not trace_first:
            return out
        done = trace.done > 0.5
        end = int(np.argmax(done)) + 1 if done.any() else len(done)
        return out, int(episodes[order[0]]), jax.tree.map(lambda x: x[:end], trace)

    def pool_program(params, episodes: np.ndarray, max_chunks: int | None = None):
        """(the refilling rollout `evaluator(params, episodes)` runs, the arguments it runs it
        with): the very program and call, for a profile (ValueError when the episodes fit in
        the lanes: that call runs one full-length batch instead). `max_chunks`: the same
        program stopped after that many chunks of steps (a whole sweep's trace is too big
        to keep)."""
        episodes = np.asarray(episodes)
        slots = round_up(min(batch, len(episodes)), mesh)
        if slots >= len(episodes):
            raise ValueError(f"{len(episodes)} episodes fit in {slots} lanes: the evaluator runs no refilling rollout")
        if max_chunks is not None and max_chunks < 1:
            raise ValueError(f"max_chunks must be at least 1, not {max_chunks}")
        run, args = pool(slots, params, jax.random.PRNGKey(seed), queue_of(episodes)[1])
        if max_chunks is not None:
            args = (*args[:4], jnp.int32(max_chunks))
        return run, args

    evaluator.pool_program = pool_program
    return evaluator
