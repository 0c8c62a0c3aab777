"""The library's interface for a user's own agent: an env, an agent of two functions, a benchmark.

`make_env(data_dir, split, resolution, **config)` -> ConavEnv; an `Agent` (title, `init(key,
obs) -> carry`, `act(carry, obs, key) -> (carry, action)`, the observation keys it reads and the
privileged inputs it declares: envs.agents.base) -> `evaluate(env, agent)` runs every episode
once (envs.rollout.evaluate) -> `Results`: per-episode records, the summary with 95% intervals
(eval.report), and with `out_dir` the files `conav eval` writes, by its own writer
(eval.sweep.write_results: episodes CSV, map, metrics.json, report.md with the paper's Table 2
and what the row was given).
"""

from __future__ import annotations

import dataclasses
import weakref
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import numpy as np

from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
from conav_jax.envs.agents.base import Agent, StateAgent, describe
from conav_jax.envs.agents.lift import lift_agent
from conav_jax.envs.rollout import make_evaluator
from conav_jax.eval.report import summarize_with_ci
from conav_jax.eval.sweep import Row, episode_records, write_results


def make_env(data_dir: str | Path, split: str = "val", resolution: tuple[int, int] = (112, 448),
             max_episodes: int | None = None, **config_overrides: Any) -> ConavEnv:
    """The CoNav env over split `split` of the dataset at `data_dir` (written by `conav
    generate`), rendering panoramas of `resolution` (H, W). `config_overrides` are EnvConfig
    fields (e.g. `physics=PhysicsConfig(...)`, `end_at_reach=True`); a given `sensor` keeps its
    other fields and takes `resolution`. `max_episodes`: load only the split's first episodes.
    ValueError naming an unknown field."""
    fields = {f.name for f in dataclasses.fields(EnvConfig)}
    unknown = sorted(set(config_overrides) - fields)
    if unknown:
        raise ValueError(f"unknown EnvConfig fields {unknown}; known: {sorted(fields)}")
    h, w = resolution
    sensor = dataclasses.replace(config_overrides.pop("sensor", SensorConfig()), resolution=(int(h), int(w)))
    return ConavEnv(data_dir, split, EnvConfig(sensor=sensor, **config_overrides), max_episodes=max_episodes)


# Each env's evaluators by (program, batch, seed, mesh, traced): the same agent evaluated again
# (with `out_dir`, or on other episodes), or another with the same program and other weights,
# reuses its compiled rollout (envs.agents.lift).
_EVALUATORS: "weakref.WeakKeyDictionary[ConavEnv, dict]" = weakref.WeakKeyDictionary()


class Results(NamedTuple):
    """What `evaluate` returns. `summary`: {metric: {"value", "lo", "hi"}} (rates and SPLs in
    percent, AS in steps; 95% intervals as eval.report makes them); `records`: one dict per
    episode (the CSV rows of `conav eval`); `metrics`: the env's final metrics, arrays over
    episodes (with "episode", the bank index); `agent`: the row's description (title with its
    privileged inputs, intention source, observation keys read); `out_dir`: where the files
    went, or None."""

    summary: dict[str, dict[str, float]]
    records: list[dict]
    metrics: dict[str, np.ndarray]
    agent: dict
    out_dir: Path | None = None


def evaluate(env: ConavEnv, agent: Agent | StateAgent, batch: int = 256, seed: int = 0,
             episodes: int | Sequence[int] | None = None, out_dir: str | Path | None = None, mesh=None) -> Results:
    """Run `agent` once on each episode of `env` (all, the first `episodes` when an int, or the
    given indices) on `batch` parallel lanes, keys from `seed` and the episode alone (the
    numbers do not depend on the batch or device count; `mesh`: conav_jax.parallel.make_mesh),
    and summarise. With `out_dir`, write there the files `conav eval` writes, by the same
    writer (eval.sweep.write_results): `episodes_<name>.csv`, `map_<name>.png` (name through
    eval.sweep.file_stem), `success_over_time.png`, `metrics.json` and `report.md`. The agent's
    weights are the compiled rollout's arguments (envs.agents.lift): the same agent evaluated
    again on `env`, or one running the same program with other weights, reuses it. ValueError
    for an env whose episodes end at the first reach (the benchmark runs them to the human's
    end of activity B) or for an agent whose declarations do not hold."""
    if env.config.end_at_reach:
        raise ValueError("the benchmark runs episodes to t_end: build the env with end_at_reach=False")
    if not isinstance(agent, (Agent, StateAgent)):
        raise ValueError(f"evaluate needs a conav_jax.Agent, got {type(agent).__name__}")
    agent = agent.check()
    if isinstance(episodes, (int, np.integer)):
        episodes = np.arange(min(int(episodes), env.num_episodes))
    per_env = _EVALUATORS.setdefault(env, {})
    # With files to write, the longest episode's robot path (for the map) from the same compile;
    # without, no trace is recorded.
    traced = out_dir is not None
    lifted = lift_agent(env, agent)
    key = (lifted.key, batch, seed, mesh, traced)
    if key not in per_env:
        per_env[key] = make_evaluator(env, lifted.agent_fn, batch, seed, mesh, trace_first=traced)
    result = per_env[key](lifted.params, None if episodes is None else np.asarray(episodes))
    metrics = result[0] if traced else result
    given = describe(agent)
    summary = summarize_with_ci(metrics, seed=seed)
    out = None if out_dir is None else Path(out_dir)
    if out is not None:
        _, first, trace = result
        write_results(out, env, seed, batch, [Row(agent.name, given, metrics, summary, int(first), np.asarray(trace.robot_pose))])
    return Results(summary, episode_records(env.split, metrics, given), metrics, given, out)
