"""An agent's weights as arguments of the compiled rollout rather than constants in it.

A learned agent's `init` and `act` close over its weights, so a rollout jitted around them holds
the weights as constants: each run (each training seed of one configuration) compiles a program
of its own, which the persistent compile cache never finds again. `lift_agent(env, agent)`
traces the agent's functions once, for one lane at the observation the rollout gives it, takes
every floating-point array they close over out as `params` (the weights, and any float table
the agent's code makes) and returns `agent_fn(params)`, the same agent computing from them (the
form envs.rollout.make_evaluator takes), with `key`, the program's structure: runs of one
configuration get equal keys, so they share one compiled evaluator and one compile-cache entry.
Integer and boolean arrays stay constants of the program and enter the key by value; an agent
that calls a Python function back on the host (jax.pure_callback, jax.debug) gets a key of its
own, as the program's text does not show the function.
"""

from __future__ import annotations

import hashlib
import itertools
from functools import partial
from typing import Any, Callable, Hashable, NamedTuple

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np

from conav_jax.envs.agents.base import Agent, StateAgent, sensing_agent

LANES = 2  # the batch the key's programs are traced at: vmapped, as the rollout runs the agent
_UNSHARED = itertools.count()  # keys of programs that call back to the host: one each


class Lifted(NamedTuple):
    """An agent with its weights taken out (`lift_agent`). `agent_fn(params)` is the agent acting
    with `params`; `key` is equal for agents whose rollouts are one program whatever their
    weights: the programs' structure for a lifted agent, the agent itself for one left as it is
    (a scripted StateAgent: no weights, `params` None)."""

    agent_fn: Callable[[Any], Agent | StateAgent]
    params: Any
    key: Hashable


def lift_agent(env, agent: Agent | StateAgent) -> Lifted:
    """`agent` as a function of its floating-point arrays, for the rollouts of `env` (module
    docstring): an observation-only Agent, or a StateAgent acting through an observation-only
    policy (envs.agents.base.sensing_agent), whose policy is lifted and whose privileged inputs
    are computed in the rollout as before. Any other StateAgent is returned as it is."""
    if isinstance(agent, StateAgent) and agent.policy is None:
        return Lifted(lambda _: agent, None, agent)
    if isinstance(agent, Agent):
        agent = agent.check()
        state = _one_lane(env, agent.reads)
        build, params, key = _lift_functions(agent, state.obs, state.obs)
        return Lifted(build, params, _digest(("agent", agent.reads, key)))
    state = _one_lane(env, agent.reads)
    sense_key, sensed = _sense_program(env, agent.sense, state)
    build, params, key = _lift_functions(agent.policy, state.obs, {**state.obs, **sensed})
    bare = agent._replace(init=None, act=None, policy=None)  # what agent_fn keeps: no weights

    def agent_fn(params):
        return sensing_agent(build(params), bare.sense, bare.name, bare.title, bare.privileged, bare.reads,
                             bare.intention_source)

    return Lifted(agent_fn, params, _digest(("sensing", agent.reads, key, sense_key)))


def _one_lane(env, reads: tuple[str, ...]):
    """The shapes of one lane's State at an episode's start as the rollout gives it to an agent
    (envs.rollout.agent_step): observing the keys `reads`."""
    key = jax.random.PRNGKey(0)
    return jax.eval_shape(lambda: env.observe(env.reset_to_episode(key, jnp.int32(0), observe=False), reads))


def _lift_functions(agent: Agent, init_obs: dict, act_obs: dict):
    """(build(params) -> Agent, params, key) for `agent`'s init and act, traced at one lane with
    these observations (init's and act's) and the carry init makes."""
    key = jax.random.PRNGKey(0)
    init, init_params, carry = _hoist(agent.init, key, init_obs)
    act, act_params, _ = _hoist(agent.act, carry, act_obs, key)
    bare = agent._replace(init=None, act=None)  # what build keeps: no weights

    def build(params):
        return bare._replace(init=partial(init, params[0]), act=partial(act, params[1]))

    programs = (_batched_program(init, init_params, (key, init_obs)),
                _batched_program(act, act_params, (carry, act_obs, key)))
    return build, (init_params, act_params), programs


def _hoist(fn: Callable, *example) -> tuple[Callable, list, Any]:
    """(`converted(params, *args)`, params, the shapes `fn` returns): `fn` traced once at the
    shapes of `example`, its closed-over floating-point arrays taken out as `params`; its other
    constants stay in it. `converted` refuses arguments of other shapes (ValueError), as the
    trace holds for these alone."""
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*example)
    hoisted = [jnp.issubdtype(jax.typeof(c).dtype, jnp.inexact) for c in closed.consts]
    params = jax.device_put([c for c, h in zip(closed.consts, hoisted) if h])  # once, not every call
    fixed = [c for c, h in zip(closed.consts, hoisted) if not h]
    in_tree, out_tree = jax.tree.structure(example), jax.tree.structure(out_shape)
    in_types = [(a.shape, a.dtype) for a in closed.in_avals]
    # `converted` keeps the jaxpr and the constants that stay, not `fn` or the arrays taken out:
    # an evaluator shared by later runs does not keep the first run's weights alive.
    jaxpr, name = closed.jaxpr, getattr(fn, "__qualname__", "function")

    def converted(params, *args):
        flat, tree = jax.tree.flatten(args)
        types = [(jax.typeof(x).shape, jax.typeof(x).dtype) for x in flat]
        if tree != in_tree or types != in_types:
            raise ValueError(f"the lifted {name} was traced for arguments "
                             f"{in_tree} of {in_types}, got {tree} of {types}")
        given, kept = iter(params), iter(fixed)
        consts = [next(given) if h else next(kept) for h in hoisted]
        run = jax.extend.core.jaxpr_as_fun(jax.extend.core.ClosedJaxpr(jaxpr, consts))
        return jax.tree.unflatten(out_tree, run(*flat))

    return converted, params, out_shape


def _batched_program(converted: Callable, params: list, example: tuple) -> tuple:
    """The key of what `converted(params, *example)` runs under vmap over LANES lanes with
    `params` as arguments (`_identity`), with the params' shapes. A custom batching rule
    (jax.custom_batching) runs its own Python at vmap time: what it closes over shows here, by
    value, and never in a one-lane trace."""
    lanes = jax.tree.map(lambda x: jax.ShapeDtypeStruct((LANES, *x.shape), x.dtype), example)
    shapes = [jax.ShapeDtypeStruct(p.shape, p.dtype) for p in params]
    closed = jax.make_jaxpr(jax.vmap(converted, in_axes=(None,) + (0,) * len(example)))(shapes, *lanes)
    return _identity(closed), [(s.shape, str(s.dtype)) for s in shapes]


def _calls_back(jaxpr) -> bool:
    """Whether `jaxpr`, or one inside it, calls a Python function on the host."""
    return (any("callback" in eqn.params for eqn in jaxpr.eqns)
            or any(_calls_back(inner) for inner in jax.extend.core.subjaxprs(jaxpr)))


def _sense_program(env, sense: Callable, state) -> tuple[tuple, dict]:
    """(the key of `sense` at one lane (`_identity`), the shapes of what it returns): traced with
    the env's episode bank as an argument, as the rollout binds it (ConavEnv.bound_bank), so the
    key holds no episode data."""
    bank = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), env.bank)

    def bound(bank, state):
        with env.bound_bank(bank):
            return sense(state)

    closed, sensed = jax.make_jaxpr(bound, return_shape=True)(bank, state)
    return _identity(closed), sensed


def _identity(closed) -> tuple:
    """A traced program's part of a key: its jaxpr's text, the digest of its constants' values
    and, if it calls a Python function back on the host, a number of its own."""
    return str(closed.jaxpr), _fingerprint(closed.consts), next(_UNSHARED) if _calls_back(closed.jaxpr) else None


def _fingerprint(arrays) -> str:
    """A digest of these arrays' values, dtypes and shapes."""
    h = hashlib.sha256()
    for a in map(np.asarray, arrays):
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _digest(parts) -> str:
    """A digest of `parts` (strings, numbers and tuples of them)."""
    return hashlib.sha256(repr(parts).encode()).hexdigest()
