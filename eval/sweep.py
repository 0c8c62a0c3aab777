"""`conav eval`: every episode of a split for each agent -> per-episode records, metrics, report.

args -> validated plan (data, agents, checkpoints; nothing compiled yet) -> env -> per agent one
jitted evaluator (envs.rollout.make_evaluator: `batch` lanes, each taking the next episode when
its own ends; with trace_first, so the longest episode's robot path for its map comes from the
same compile), shared by the scripted agents and by runs of one configuration (their weights
its arguments: envs.agents.lift) -> write_results, which conav_jax.evaluate shares:
episodes_<agent>.csv, metrics.json (each metric with a 95% interval), report.md (the paper's
Table 2, and Table 3 for ablation checkpoints), success_over_time.png and map_<agent>.png, file
names from file_stem.
"""

from __future__ import annotations

import csv
import json
import re
import weakref
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from conav_jax.provenance import provenance
from conav_jax.envs.agents.registry import AGENTS, check_agent
from conav_jax.envs.config import env_settings

_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]+$")  # ablation names become file names
_UNSAFE_FILE_CHARS = re.compile(r"[^A-Za-z0-9_.-]+")


def file_stem(name: str) -> str:
    """The part of a row's file names (episodes_<stem>.csv, map_<stem>.png) its name gives:
    letters, digits, '.', '_' and '-' only, so the files open anywhere. A user's
    'package.module:factory' becomes 'package.module.factory'; any other run of characters
    outside the set becomes '_'. Different names can share a stem ('a.b:c' and 'a:b.c'):
    plan_eval refuses to evaluate them together (_check_stems)."""
    return _UNSAFE_FILE_CHARS.sub("_", name.replace(":", "."))


def _check_stems(keys: list[str]) -> None:
    """ValueError when two of an evaluation's rows (agent names, ablation_<name>) would write
    the same files; stems are compared ignoring case, as some file systems do."""
    seen: dict[str, str] = {}
    for key in keys:
        other = seen.setdefault(file_stem(key).casefold(), key)
        if other != key:
            raise ValueError(f"EvalPlan.agents: {other!r} and {key!r} would both write episodes_{file_stem(key)}.csv; "
                             "evaluate them separately")


def _learned(name: str) -> bool:
    """Whether agent `name` loads a trained run (an agent outside the registry, a user's
    `package.module:factory`, loads none here)."""
    return name in AGENTS and AGENTS[name].needs_checkpoint


def _reads_intentions(name: str) -> bool:
    """Whether agent `name` takes the intention keywords (predictor runs or ground truth)."""
    return name in AGENTS and AGENTS[name].takes_intentions
_INPUT_KEYS = ("use_activity", "use_object", "use_trajectory")


@dataclass(frozen=True)
class EvalPlan:
    """Everything `conav eval` will do, checked before anything is built or compiled."""

    data: Path
    split: str
    content_hash: str
    agents: tuple[str, ...]
    checkpoint: str | None  # the run of every learned agent not in agent_checkpoints
    agent_checkpoints: tuple[tuple[str, str], ...] = ()  # (agent, run): a learned agent's own run
    # intention_run / trajectory_run / ground_truth, for the agents that read intention inputs
    intention_kwargs: dict = field(default_factory=dict)
    ablations: tuple[tuple[str, str], ...] = ()  # (name, run dir)
    episodes: int | None = None  # the first N episodes, None for all
    batch: int = 256  # parallel lanes (envs.rollout.make_evaluator)
    seed: int = 0
    resolution: tuple[int, int] = (112, 448)  # the env's panorama (H, W): the trained runs' or SensorConfig's
    materials: str = "instance"  # SensorConfig.materials of the env: the trained runs' or SensorConfig's
    out: Path = Path("eval_out")
    devices: int | None = None  # devices the lanes are split over (None: all visible)

    def checkpoint_of(self, name: str) -> str | None:
        """The run agent `name` loads (None for agents without one)."""
        if not _learned(name):
            return None
        return dict(self.agent_checkpoints).get(name, self.checkpoint)


def plan_eval(
    data: str | Path,
    split: str,
    agents: tuple[str, ...],
    out: str | Path,
    checkpoint: str | Mapping[str | None, str] | None = None,
    intention_kwargs: dict | None = None,
    ablations: tuple[tuple[str, str], ...] = (),
    episodes: int | None = None,
    batch: int = 256,
    seed: int = 0,
    resolution: tuple[int, int] | None = None,
    devices: int | None = None,
    materials: str | None = None,
) -> EvalPlan:
    """Check every input of an evaluation (dataset, split, agents, checkpoints, sizes) without
    building an env or compiling anything; ValueError naming the first problem. `checkpoint`:
    the run of every learned agent, or a mapping agent name -> its run (the key None: the run of
    learned agents not named), so one sweep evaluates several trained runs. `resolution` None:
    the trained runs' (every learned agent's run must agree), else SensorConfig's default; given,
    it must match every trained run's. `materials` None: those the trained runs' images were
    rendered with (every run must agree; envs.config.run_materials), else SensorConfig's default;
    given, the agents' loaders refuse a run of other materials."""
    from conav_jax.data.episodes import read_manifest
    from conav_jax.envs.agents.registry import run_resolution

    manifest = read_manifest(data)
    if split not in manifest["splits"]:
        raise ValueError(f"{data}: no split {split!r}; has {sorted(manifest['splits'])}")
    if not agents:
        raise ValueError("EvalPlan.agents needs at least one agent name")
    if len(set(agents)) != len(agents):
        raise ValueError(f"EvalPlan.agents lists an agent twice: {','.join(agents)}")
    own = dict(checkpoint) if isinstance(checkpoint, Mapping) else {None: checkpoint}
    default = own.pop(None, None)
    for name in agents:
        check_agent(name, own.get(name, default) if _learned(name) else default)
    for name in own:
        if name not in agents or not _learned(name):
            learned = [n for n in agents if _learned(n)]
            raise ValueError(f"EvalPlan.agent_checkpoints names a run for {name!r}, which is not a learned agent of this evaluation "
                             f"(learned agents: {', '.join(learned) or 'none'})")
    learned = dict(intention_kwargs or {})
    if learned and not ablations and not any(_reads_intentions(n) for n in agents):
        raise ValueError("EvalPlan.intention_kwargs only apply to agents that read "
                         "intention inputs (conav, ppo) and ablations")
    names = set()
    for name, run in ablations:
        if not _NAME_RE.match(name):
            raise ValueError(f"ablation name {name!r} may only hold letters, digits, '_', '.', '-'")
        if name in names:
            raise ValueError(f"ablation name {name!r} is given twice")
        names.add(name)
        check_agent("conav", run)
    _check_stems([*agents, *(f"ablation_{n}" for n, _ in ablations)])
    if episodes is not None and episodes < 1:
        raise ValueError(f"EvalPlan.episodes must be at least 1, got {episodes}")
    if batch < 1:
        raise ValueError(f"EvalPlan.batch must be at least 1, got {batch}")
    if devices is not None and devices < 1:
        raise ValueError(f"EvalPlan.devices must be at least 1, got {devices}")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"EvalPlan.out {out} exists and is not a directory")
    trained = [(name, own.get(name, default)) for name in agents if _learned(name)]
    trained += [("conav", run) for _, run in ablations]
    return EvalPlan(materials=_materials_of(trained, learned, materials),
        data=Path(data),
        split=split,
        content_hash=manifest["content_hash"],
        agents=tuple(agents),
        checkpoint=default,
        agent_checkpoints=tuple((name, str(run)) for name, run in own.items()),
        intention_kwargs=learned,
        ablations=tuple(ablations),
        episodes=episodes,
        batch=batch,
        seed=seed,
        resolution=run_resolution(trained, resolution),
        out=out,
        devices=devices,
    )


def _materials_of(trained: list[tuple[str, str | None]], intention_kwargs: dict, given: str | None) -> str:
    """The materials an evaluation's env renders: `given`, else the one the trained agents' and
    predictors' runs were rendered with (ValueError when they differ), else SensorConfig's."""
    from conav_jax.envs.config import MATERIALS, SensorConfig, run_materials

    if given is not None:
        if given not in MATERIALS:
            raise ValueError(f"EvalPlan.materials must be one of {MATERIALS}, got {given!r}")
        return given
    runs = [run for _, run in trained if run is not None]
    runs += [intention_kwargs[k] for k in ("intention_run", "trajectory_run") if intention_kwargs.get(k)]
    found = {}
    for run in runs:
        try:
            found[str(run)] = run_materials(run)
        except FileNotFoundError:
            continue  # the agent's own loader names the missing run
    kinds = set(found.values()) - {None}
    if len(kinds) > 1:
        raise ValueError("EvalPlan.materials: the runs were trained on different materials "
                         f"({', '.join(f'{r}: {m}' for r, m in found.items())}); evaluate them separately")
    return kinds.pop() if kinds else SensorConfig.materials


# -- running -------------------------------------------------------------------------------------

# A process keeps its last env and each agent's compiled rollout: evaluating the same agents on
# the same data again (tests, notebooks) skips the minute-long compile of the env step.
_ENV_CACHE: dict[tuple, Any] = {}
_EVALUATORS: "weakref.WeakKeyDictionary[Any, dict]" = weakref.WeakKeyDictionary()


def load_env(plan: EvalPlan):
    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig

    key = (str(plan.data.resolve()), plan.split, plan.content_hash, plan.resolution, plan.materials, plan.episodes)
    if key not in _ENV_CACHE:
        _ENV_CACHE.clear()
        h, w = plan.resolution
        sensor = SensorConfig(resolution=(h, w), materials=plan.materials)
        _ENV_CACHE[key] = ConavEnv(plan.data, plan.split, EnvConfig(sensor=sensor), max_episodes=plan.episodes)
    return _ENV_CACHE[key]


def build_evaluators(env, runs: list[tuple[str, str | None, dict]], batch: int, seed: int, mesh=None) -> list:
    """[(agent, evaluate(episodes) -> (metrics, traced episode, its robot poses))] for the
    (name, checkpoint, agent keywords) of `runs`: every agent is built (checkpoints loaded)
    before anything compiles, so a bad run fails fast. The scripted agents share one compiled
    evaluator, the agent chosen as data (envs.agents.base.switch_agent): one compile of the
    env's rollout instead of one per agent. Every other agent's weights are its evaluator's
    arguments (envs.agents.lift): runs of one configuration (training seeds, predictor runs)
    share one compiled evaluator, and the persistent compile cache finds it in a later process.
    Evaluators are kept per env, program, batch, seed and mesh: evaluating the same agents on
    the same data again (tests, notebooks) skips the compile. Keys per episode (envs.rollout),
    so the numbers do not depend on the batch."""
    import jax.numpy as jnp

    from conav_jax.envs.agents.base import StateAgent, switch_agent
    from conav_jax.envs.agents.lift import lift_agent
    from conav_jax.envs.agents.registry import make_agent
    from conav_jax.envs.rollout import make_evaluator

    per_env = _EVALUATORS.setdefault(env, {})
    agents = [make_agent(name, env, ckpt, **kw) for name, ckpt, kw in runs]
    # The scripted agents share one evaluator, the pioneer's poses and the others' velocities
    # alike (envs.agents.base.switch_agent).
    scripted = [j for j, (name, _, _) in enumerate(runs) if not _learned(name)]
    out = []
    for k, (agent, (name, ckpt, kw)) in enumerate(zip(agents, runs)):
        if k in scripted and len(scripted) > 1:
            key = ("scripted", tuple(runs[j][0] for j in scripted), batch, seed, mesh)
            if key not in per_env:
                group = [agents[j] for j in scripted]
                per_env[key] = make_evaluator(env, lambda which, group=group: switch_agent(group, which), batch, seed,
                                              mesh, trace_first=True)
            params = jnp.int32(scripted.index(k))
        elif k in scripted and isinstance(agent, StateAgent):  # no weights to take out: kept by name
            key = (name, batch, seed, mesh, tuple(sorted(kw.items())))
            if key not in per_env:
                per_env[key] = make_evaluator(env, lambda _, a=agent: a, batch, seed, mesh, trace_first=True)
            params = None
        else:
            lifted = lift_agent(env, agent)
            key = (lifted.key, batch, seed, mesh)
            if key not in per_env:
                per_env[key] = make_evaluator(env, lifted.agent_fn, batch, seed, mesh, trace_first=True)
            params = lifted.params
        out.append((agent, _evaluate_with(per_env[key], params)))
    return out


def _evaluate_with(evaluator: Callable, params) -> Callable:
    def run(episodes: np.ndarray) -> tuple[dict, int, np.ndarray]:
        metrics, first, trace = evaluator(params, np.asarray(episodes))
        return metrics, first, np.asarray(trace.robot_pose)

    return run


def trained_with(run: str | Path) -> dict:
    """What an evaluated agent's weights were trained with, from its run's latest checkpoint: the
    run, the checkpoint's step and the run's provenance (its commit, dirty state, device, encoder,
    materials, ...: conav_jax.provenance), so an evaluation names the code of its weights as well
    as its own. A run without a checkpoint records the path alone."""
    from conav_jax.checkpoints import latest_checkpoint, read_checkpoint_meta
    from conav_jax.provenance import PROVENANCE_KEY

    found = latest_checkpoint(run)
    if found is None:
        return {"run": str(run)}
    meta = read_checkpoint_meta(found)
    return {"run": str(run), "step": meta.get("step"), PROVENANCE_KEY: (meta.get("config") or {}).get(PROVENANCE_KEY)}


def episode_records(split, metrics: dict, given: dict) -> list[dict]:
    """One CSV row per episode: what the agent was given (`given`: envs.agents.base.describe),
    the episode's identity, human timing, robot outcome (envs.metrics rules)."""
    from conav_jax.data.activities import load_activity_graph
    from conav_jax.data.categories import CATEGORY_NAMES
    from conav_jax.envs.metrics import episode_outcomes

    graph = load_activity_graph()
    e = split.episodes
    out = episode_outcomes(metrics)
    rows = []
    privileged = ";".join(given["privileged"])
    for j, i in enumerate(np.asarray(metrics["episode"])):
        row = {
            "agent": given["agent"],
            "intention_source": given["intention_source"],
            "privileged": privileged,
            "episode": int(i),
            "scene": split.scenes[int(e["scene_index"][i])].name,
            "activity_a": graph.activity(int(e["activity_a"][i])).name,
            "activity_b": graph.activity(int(e["activity_b"][i])).name,
            "object_b": CATEGORY_NAMES[int(e["object_b"][i])],
            "t_arrive": int(metrics["t_arrive"][j]),
            "t_end": int(metrics["t_end"][j]),
            "t_reach": int(metrics["t_reach"][j]),
            "shortest_path_steps": int(metrics["shortest_path_steps"][j]),
            "geodesic_start_goal_m": f"{float(metrics['geodesic_start_goal_m'][j]):.4f}",
            "path_length_m": f"{float(metrics['path_length_m'][j]):.4f}",
            "FASR": int(out["FASR"][j]),
            "RASR": int(out["RASR"][j]),
            "FASPL": f"{out['FASPL'][j]:.4f}",
            "RASPL": f"{out['RASPL'][j]:.4f}",
            "FASPL_m": f"{out['FASPL_m'][j]:.4f}",
            "RASPL_m": f"{out['RASPL_m'][j]:.4f}",
            "collided_before_reach": int(metrics["collided_before_reach"][j] > 0.5),
            "collided": int(out["CR"][j]),
            "AS": int(out["AS"][j]),
        }
        if "CR_full" in out:
            row["collided_full"] = int(out["CR_full"][j])
        rows.append(row)
    return rows


def write_csv(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def ablation_flags(name: str, run: str) -> tuple[bool | None, bool | None, bool | None]:
    """(activity, object, trajectory) intention inputs of an ablation: from its name when it is
    one of the policy's ABLATIONS, else from the run's model config, else unknown."""
    from conav_jax import runs
    from conav_jax.models.policy import ABLATIONS

    if name in ABLATIONS:
        return ABLATIONS[name]
    try:
        model = runs.run_config(run, runs.POLICY).get("model", {})
    except (FileNotFoundError, ValueError):
        model = {}  # unreadable: the marks stay unknown, the evaluation itself will complain
    return tuple(model.get(k) if isinstance(model.get(k), bool) else None for k in _INPUT_KEYS)


def _rounded(summary: dict) -> dict:
    return {m: {k: round(v, 4) for k, v in entry.items()} for m, entry in summary.items()}


class Row(NamedTuple):
    """One evaluated row of a report. `key` names it in metrics.json (an agent name, or
    ablation_<name>) and, through file_stem, its files; `given`: what it was given
    (envs.agents.base.describe, with a trained agent's `trained` and an ablation's `run` and
    `inputs`); `metrics`: the env's final metrics over episodes; `summary`: summarize_with_ci's;
    `first`: the episode its map draws (the longest); `path`: the robot's poses (steps, 3) in it."""

    key: str
    given: dict
    metrics: dict
    summary: dict
    first: int
    path: np.ndarray


def write_results(out: Path, env, seed: int, batch: int, agents: Sequence[Row], ablations: Sequence[Row] = ()) -> dict:
    """Every file of an evaluation on `env` (rollout keys from `seed`, `batch` lanes), written
    the same way for `conav eval` (sweep) and conav_jax.evaluate, so one agent gets one document
    from either: per row episodes_<stem>.csv and map_<stem>.png (file_stem), success_over_time.png,
    metrics.json (the data, its content hash, the setting, the env's provenance, each row's
    description and metrics with exact 95% bounds) and report.md (Table 2 of `agents`, Table 3
    of `ablations`, what each row was given). Returns the metrics.json content."""
    from conav_jax.eval import plots
    from conav_jax.eval.report import report_markdown

    out.mkdir(parents=True, exist_ok=True)
    rows = [*agents, *ablations]
    maps = []
    for row in rows:
        write_csv(out / f"episodes_{file_stem(row.key)}.csv", episode_records(env.split, row.metrics, row.given))
        maps.append((row.given["title"], _draw_map(out, env, row)))
    plots.success_over_time({row.given["title"]: row.metrics for row in rows}, out / "success_over_time.png")
    h, w = env.config.sensor.resolution
    doc = {
        "data": env.split.data_dir,
        "content_hash": env.split.content_hash,
        "split": env.split.name,
        "episodes": len(rows[0].metrics["episode"]),
        "seed": seed,
        "batch": batch,
        "resolution": f"{h}x{w}",
        "materials": env.config.sensor.materials,
        "provenance": provenance(**env_settings(env.config)),
        "agents": {row.key: {**row.given, "metrics": _rounded(row.summary)} for row in agents},
        "ablations": {row.key: {**row.given, "metrics": _rounded(row.summary)} for row in ablations},
    }
    (out / "metrics.json").write_text(json.dumps(doc, indent=1) + "\n")
    (out / "report.md").write_text(report_markdown(doc, agents, ablations, maps))
    return doc


def _draw_map(out: Path, env, row: Row) -> str:
    """map_<stem>.png in `out`: the robot's path in `row`'s drawn episode over its scene, the
    human's walk and the goal; returns the file's name."""
    from conav_jax.eval import plots

    i = row.first
    j = int(np.flatnonzero(row.metrics["episode"] == i)[0])
    ep = {k: env.split.episodes[k][i] for k in ("root_xy", "phase", "goal_xy", "robot_start", "t_end")}
    png = f"map_{file_stem(row.key)}.png"
    plots.episode_map(
        env.split.scenes[int(env.split.episodes["scene_index"][i])],
        ep,
        np.concatenate([np.asarray(ep["robot_start"])[None], row.path]),
        out / png,
        success_radius_m=env.task.success_radius_m,
        robot_height_m=env.task.robot_height_m,
        title=f"{row.given['title']}: episode {i}, t_reach {int(row.metrics['t_reach'][j])}, "
              f"human arrives {int(row.metrics['t_arrive'][j])}",
    )
    return png


def run_eval(data: str | Path, split: str, agents: tuple[str, ...], out: str | Path, progress: bool = False,
             **plan) -> dict:
    """What `conav eval` runs: `plan_eval` of these arguments and the keywords `plan`, its env
    (`load_env`) and `sweep`, the lanes split over the plan's devices (None: all visible).
    Returns the metrics.json content."""
    from conav_jax.parallel import make_mesh

    checked = plan_eval(data, split, agents, out, **plan)
    return sweep(checked, load_env(checked), progress=progress, mesh=make_mesh(checked.devices))


def run_evals(data: str | Path, split: str, agents: tuple[str, ...], outs: list[str | Path],
              checkpoints: list[str | Path | None], **plan) -> list[dict]:
    """`run_eval` of each (out, checkpoint) pair in turn, in this process: evaluations of one data,
    split and agents (training seeds of a row, say) load the env once and share a compiled sweep
    (`load_env`, `build_evaluators` keep them). Returns their metrics.json contents."""
    if len(outs) != len(checkpoints):
        raise ValueError(f"run_evals needs a checkpoint (or None) per out, got {len(outs)} and {len(checkpoints)}")
    return [run_eval(data, split, agents, out, checkpoint=checkpoint, **plan)
            for out, checkpoint in zip(outs, checkpoints)]


def sweep(plan: EvalPlan, env, progress: bool = False, mesh=None) -> dict:
    """Evaluate every agent and ablation of `plan` on `env` and write all outputs to plan.out
    (write_results), the lanes split over the devices of `mesh` (conav_jax.parallel.make_mesh;
    None: one device), with a progress bar over the agents if `progress`. Returns the
    metrics.json content."""
    from tqdm import tqdm

    from conav_jax.envs.agents.base import describe
    from conav_jax.eval.report import summarize_with_ci

    if env.config.end_at_reach:
        raise ValueError("the benchmark runs episodes to t_end: build the env with EnvConfig(end_at_reach=False)")
    episodes = np.arange(env.num_episodes)
    runs = [(name, name, plan.checkpoint_of(name)) for name in plan.agents]
    runs += [(f"ablation_{n}", "conav", run) for n, run in plan.ablations]
    built = build_evaluators(env, [(name, ckpt, plan.intention_kwargs if _reads_intentions(name) else {})
                                   for _, name, ckpt in runs], plan.batch, plan.seed, mesh)
    rows = {}
    # A run listed twice (Table 3's all-inputs row is usually the agent itself) is swept once:
    # keys are per episode, so a second sweep would give the same numbers.
    swept = {}
    bar = tqdm(total=len(runs), desc="eval", unit="agent", disable=not progress, dynamic_ncols=True)
    for (key, name, ckpt), (agent, evaluator) in zip(runs, built):
        same = (name, None if ckpt is None else str(Path(ckpt).resolve()))
        bar.set_postfix_str(f"{key} ({len(episodes)} episodes, {'as swept above' if same in swept else 'compile + run'})")
        if same not in swept:
            swept[same] = evaluator(episodes)
        metrics, first, path = swept[same]
        bar.update(1)
        given = describe(agent)
        if ckpt is not None:
            given["trained"] = trained_with(ckpt)
        rows[key] = Row(key, given, metrics, summarize_with_ci(metrics, seed=plan.seed), int(first), path)
    bar.close()
    for name, run in plan.ablations:
        given = rows[f"ablation_{name}"].given
        given["title"] = f"{name}: {given['title']}"
        given["run"] = run
        given["inputs"] = dict(zip(("activity", "object", "trajectory"), ablation_flags(name, run)))
    return write_results(plan.out, env, plan.seed, plan.batch, [rows[k] for k in plan.agents],
                         [rows[f"ablation_{n}"] for n, _ in plan.ablations])
