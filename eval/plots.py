"""Evaluation figures (matplotlib, Agg backend, PNG files): success over episode time, episode maps.

Per-episode results (t_reach, t_arrive, ...) -> cumulative success curves per agent against the
humans' arrival; a scene (conav_jax.data.scene.Scene) + one episode's arrays + a recorded robot path
-> a top-down map. Nothing here runs the simulator.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import matplotlib

matplotlib.use("Agg")  # files only: never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, Rectangle  # noqa: E402

from conav_jax.data.categories import CATEGORY_NAMES  # noqa: E402
from conav_jax.data.scene import STRUCTURE_WALL, Scene, scene_boxes  # noqa: E402
from conav_jax.motion.phases import PHASE_ACTIVITY_A, PHASE_ACTIVITY_B, PHASE_WALK  # noqa: E402
from conav_jax.envs.metrics import episode_outcomes  # noqa: E402

PHASE_STYLE = {PHASE_ACTIVITY_A: ("activity A", "tab:blue"), PHASE_WALK: ("walk", "tab:orange"), PHASE_ACTIVITY_B: ("activity B", "tab:purple")}


def _save_percent_plot(fig, ax, path: Path, xlabel: str, title: str) -> Path:
    """Label a plot of episode shares (%), write it as PNG, close it."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel("episodes (%)")
    ax.set_ylim(0, 100)
    ax.set_title(title)
    ax.legend(fontsize=7, loc="upper left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def success_over_time(results: Mapping[str, Mapping[str, np.ndarray]], path: str | Path) -> Path:
    """Share of episodes (%) successfully reached by each step, one curve per agent.

    `results`: title -> the env's final metrics over episodes. A success counts from its
    t_reach (the RASR rule: reached before the episode ended, no human contact before); the
    dashed curve is the share of episodes whose human has arrived by then, so an agent's curve
    above it at step t is ahead of the humans."""
    path = Path(path)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    horizon = 1
    for title, m in results.items():
        t_reach = np.asarray(m["t_reach"])
        ok = episode_outcomes(m)["RASR"] > 0.5
        horizon = max(horizon, int(np.max(m["t_end"])) + 1)
        steps = np.arange(horizon)
        curve = 100.0 * ((t_reach[None, :] <= steps[:, None]) & ok[None, :]).mean(axis=1)
        ax.step(steps, curve, where="post", label=title)
    first = next(iter(results.values()))
    steps = np.arange(horizon)
    arrived = 100.0 * (np.asarray(first["t_arrive"])[None, :] <= steps[:, None]).mean(axis=1)
    ax.step(steps, arrived, where="post", color="black", linestyle="--", label="human arrived")
    return _save_percent_plot(fig, ax, path, "episode step (0.1 s)", "Success by step")


def episode_map(
    scene: Scene,
    episode: Mapping[str, np.ndarray],
    robot_path: np.ndarray,
    path: str | Path,
    *,
    success_radius_m: float,
    robot_height_m: float,
    title: str = "",
) -> Path:
    """Top-down map of one episode.

    `episode`: that episode's arrays (root_xy (T, 2), phase (T,), goal_xy (2,), robot_start (3,),
    t_end); `robot_path` (steps, 2+) world x, y of the robot. Draws walls (grey), furniture in its
    category colours with names, the human's path coloured by phase, the robot's path from its
    start, the goal and the success circle."""
    path = Path(path)
    boxes = scene_boxes(scene, robot_height_m)
    fig, ax = plt.subplots(figsize=(8.5, 7))
    # Flat and low things first so taller furniture stays visible on top.
    for i in np.argsort(boxes.center[:, 2] + boxes.half_extents[:, 2], kind="stable"):
        (cx, cy, _), (hx, hy, _) = boxes.center[i], boxes.half_extents[i]
        wall = boxes.category[i] == STRUCTURE_WALL
        colour = "0.35" if wall else boxes.rgb[i] / 255.0
        ax.add_patch(Rectangle((cx - hx, cy - hy), 2 * hx, 2 * hy, facecolor=colour, edgecolor="0.2", linewidth=0.4, alpha=1.0 if wall else 0.8))
        if not wall:
            ax.text(cx, cy, CATEGORY_NAMES[boxes.category[i]], fontsize=5, ha="center", va="center")
    t_end = int(episode["t_end"]) + 1
    human = np.asarray(episode["root_xy"])[:t_end]
    phase = np.asarray(episode["phase"])[:t_end]
    for p, (label, colour) in PHASE_STYLE.items():
        sel = phase == p
        if sel.any():
            ax.scatter(human[sel, 0], human[sel, 1], s=4, color=colour, label=f"human: {label}", zorder=3)
    robot = np.asarray(robot_path)[:, :2]
    ax.plot(robot[:, 0], robot[:, 1], color="red", linewidth=1.5, label="robot", zorder=4)
    start = np.asarray(episode["robot_start"])
    ax.plot(start[0], start[1], "o", color="red", markersize=6, zorder=5)
    goal = np.asarray(episode["goal_xy"])
    ax.add_patch(Circle(goal, success_radius_m, fill=False, edgecolor="green", linestyle="--", linewidth=1.2, zorder=4))
    ax.plot(goal[0], goal[1], "*", color="green", markersize=14, label="goal", zorder=5)
    x0, y0, x1, y1 = scene.bounds
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or scene.name, fontsize=9)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def pooled_reach_rate(train: list[dict], window: int) -> tuple[np.ndarray, np.ndarray]:
    """(env steps at each block's end, share of the block's ended episodes that reached the
    goal) over blocks of `window` PPO training records. A shorter last block is dropped when
    there are full ones: a cut-off reset cycle has seen only its quick successes."""
    blocks = [train[i : i + window] for i in range(0, len(train), window)]
    if len(blocks) > 1 and len(blocks[-1]) < window:
        blocks = blocks[:-1]
    x = np.array([b[-1]["env_steps"] for b in blocks], float)
    reached = np.array([sum(r["reach_rate"] * r["episodes"] for r in b) for b in blocks])
    ended = np.array([sum(r["episodes"] for r in b) for b in blocks], float)
    return x, reached / np.maximum(ended, 1.0)


def learning_curve(runs: Mapping[str, list[dict]], path: str | Path, window: int | None = None) -> Path:
    """Success against env steps for PPO runs (`conav train rl`), one colour per run.

    `runs`: title -> the run's log.jsonl records. Lines: the share of training episodes that
    ended with the goal reached (`reach_rate` x `episodes`, %), pooled over blocks of `window`
    iterations (None: each run's reset cycle, `reset_every` in its records, else 4): PPO
    re-resets its batch every `reset_every` iterations and the episodes ending first after a
    reset are the quick successes, so a per-iteration rate swings with that cycle. Markers:
    the evaluation sweeps' FASR (circles) and RASR (squares), labelled with their split
    (minival while training; older runs: val). ValueError if a run has no PPO
    training records."""
    path = Path(path)
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for i, (title, records) in enumerate(runs.items()):
        train = [r for r in records if r.get("split") == "train" and "env_steps" in r and r.get("reach_rate") is not None]
        if not train:
            raise ValueError(f"run {title!r} has no PPO training records (env_steps, reach_rate) in its log")
        colour = f"C{i}"
        x, rate = pooled_reach_rate(train, window or train[-1].get("reset_every") or 4)
        ax.plot(x, 100.0 * rate, "-", color=colour, label=f"{title}: train episodes reached")
        val = [r for r in records if r.get("split") not in (None, "train") and "env_steps" in r and "FASR" in r]
        if val:
            vx, split = [r["env_steps"] for r in val], val[-1]["split"]
            ax.plot(vx, [r["FASR"] for r in val], "o", color=colour, label=f"{title}: {split} FASR")
            ax.plot(vx, [r["RASR"] for r in val], "s", color=colour, mfc="none", label=f"{title}: {split} RASR")
    return _save_percent_plot(fig, ax, path, "env steps", "PPO learning curve")

