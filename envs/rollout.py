"""Batched rollouts: any agent through the env, `lax.scan` over time, `vmap` over episodes.

An `Agent` acts for ONE environment (the rollout vmaps it): `init(key, episode) -> carry` and
`act(state, carry, key) -> (action (2,), carry)`, where `state` is the env's brax State, so an
agent reads `state.obs` and, if it is privileged (an oracle baseline, the expert), the env's
constants through a closure and `state.pipeline_state` / `state.info`. Learned agents close over
their parameters. This module is what evaluation sweeps, DAgger and validation during training
all run on. With a device mesh (conav_jax.parallel), each batch of episodes is split over
the devices.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import State
from jax.sharding import Mesh

from conav_jax.parallel import replicate, round_up, shard_batch, to_host
from envs.conav_env import ConavEnv


class Agent(NamedTuple):
    name: str
    init: Callable[[jax.Array, jax.Array], Any]  # (key, episode index) -> carry
    act: Callable[[State, Any, jax.Array], tuple[jax.Array, Any]]  # (state, carry, key) -> (action, carry)


class Trace(NamedTuple):
    """Per-step records of a rollout, (B, T, ...)."""

    robot_pose: jax.Array  # (x, y, yaw) world
    action: jax.Array  # the agent's action in [-1, 1]
    reward: jax.Array
    done: jax.Array


def make_param_rollout(env: ConavEnv, agent_fn: Callable[[Any], Agent], num_steps: int, record: bool = False):
    """A jitted function (params, key, episodes (B,)) -> (final metrics dict of (B,), Trace | None)
    for the agent `agent_fn(params)` builds. The agent is built inside the trace, so new params
    of the same structure reuse the compiled rollout (an Agent closing over its params would
    compile once per set: training-time validation needs this form).

    Runs `num_steps` steps; episodes that end earlier stay frozen (the env's contract), so
    the final metrics are each episode's result at its end."""

    def one(params, key, episode):
        agent = agent_fn(params)
        k_init, k_run = jax.random.split(key)
        state = env.reset_to_episode(k_init, episode)
        carry = agent.init(k_init, episode)

        def body(c, k):
            state, carry = c
            action, carry = agent.act(state, carry, k)
            state = env.step(state, action)
            out = None
            if record:
                out = Trace(state.pipeline_state.qpos, action, state.reward, state.done)
            return (state, carry), out

        (state, _), trace = jax.lax.scan(body, (state, carry), jax.random.split(k_run, num_steps))
        return state.metrics, trace

    @jax.jit
    def run(params, key, episodes):
        keys = jax.random.split(key, episodes.shape[0])
        return jax.vmap(one, in_axes=(None, 0, 0))(params, keys, episodes)

    return run


def make_rollout(env: ConavEnv, agent: Agent, num_steps: int, record: bool = False):
    """A jitted function (key, episodes (B,)) -> (final metrics dict of (B,), Trace | None):
    `make_param_rollout` for an agent without parameters (or closing over its own)."""
    run = make_param_rollout(env, lambda _: agent, num_steps, record)
    return lambda key, episodes: run(None, key, episodes)


def map_episodes(
    fn: Callable[[jax.Array, jax.Array], Any],
    episodes: np.ndarray,
    batch: int,
    key: jax.Array,
    mesh: Mesh | None = None,
    progress: Callable | None = None,
) -> Any:
    """`fn(key, indices) -> pytree of (size, ...) arrays` over `episodes` in batches of `batch`
    -> host (numpy) pytree of `(len(episodes), ...)`.

    Batch `s` (starting at episode `s0`) gets `fold_in(key, s0)`. Each batch is padded by
    repeating its last episode to `size = batch` rounded up to a multiple of the mesh's device
    count (results of the padding are dropped), so one compiled function serves every batch;
    with a `mesh` its indices are split over the devices and the key replicated. Keys of a
    batch do not depend on the padding (jax's partitionable threefry), so results do not
    depend on the device count."""
    episodes = np.asarray(episodes)
    if episodes.ndim != 1 or len(episodes) == 0:
        raise ValueError("episodes must be a non-empty 1-D array of episode indices")
    batch = min(batch, len(episodes))
    size = round_up(batch, mesh)
    chunks = []
    starts = range(0, len(episodes), batch)
    for s0 in progress(starts) if progress else starts:
        idx = episodes[s0 : s0 + batch]
        n = len(idx)
        idx = np.concatenate([idx, np.full(size - n, idx[-1])]).astype(np.int32)
        k = jax.random.fold_in(key, s0)
        if mesh is None:
            out = fn(k, jnp.asarray(idx))
        else:
            out = fn(replicate(k, mesh), shard_batch(idx, mesh))
        chunks.append(jax.tree.map(lambda x: x[:n], to_host(out)))
    return jax.tree.map(lambda *xs: np.concatenate(xs), *chunks)


def evaluate(
    env: ConavEnv,
    agent: Agent,
    episodes: np.ndarray | None = None,
    batch: int = 256,
    seed: int = 0,
    progress: Callable | None = None,
    mesh: Mesh | None = None,
) -> dict[str, np.ndarray]:
    """Final metrics of every given episode (default: all of the bank, each exactly once).

    Episodes run in batches of `batch` (see `map_episodes` for padding and keys); with a
    `mesh` (conav_jax.parallel.make_mesh) each batch is split over its devices, with the same
    results as on one device."""
    return make_evaluator(env, lambda _: agent, batch, seed, mesh)(None, episodes, progress)


def make_evaluator(
    env: ConavEnv, agent_fn: Callable[[Any], Agent], batch: int = 256, seed: int = 0, mesh: Mesh | None = None
) -> Callable[..., dict[str, np.ndarray]]:
    """`evaluate` for agents built from parameters: `evaluator(params, episodes=None,
    progress=None) -> metrics` (as `evaluate` returns them). The rollout compiles on the first
    call; later params of the same structure reuse it (PPO validates every few iterations)."""
    run = make_param_rollout(env, agent_fn, num_steps=env.bank.max_steps)

    def evaluator(params, episodes: np.ndarray | None = None, progress: Callable | None = None):
        episodes = np.arange(env.num_episodes) if episodes is None else np.asarray(episodes)
        if episodes.ndim != 1 or len(episodes) == 0:
            raise ValueError("episodes must be a non-empty 1-D array of episode indices")
        if episodes.min() < 0 or episodes.max() >= env.num_episodes:
            raise ValueError(f"episode indices must be in [0, {env.num_episodes})")
        if mesh is not None and params is not None:
            params = replicate(params, mesh)
        out = map_episodes(lambda k, idx: run(params, k, idx)[0], episodes, batch, jax.random.PRNGKey(seed), mesh, progress)
        out["episode"] = episodes
        return out

    return evaluator
