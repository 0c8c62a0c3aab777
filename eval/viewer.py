"""`conav view`: one episode as a rerun recording (.rrd): scene, humanoid, robot, panorama, intentions.

The panorama comes with the object intention's saliency map (conav_jax.models.policy): each
pixel's category probability relative to the most likely one, what the CoNav policy reads.

A jitted rollout of the episode records per step the robot pose, the panorama and the intention
inputs (the agent's own predictions where its carry exposes them, else the ground truth,
labelled as such); logging to rerun happens afterwards from those arrays, so rendering never
slows the step. Everything time-varying shares the "step" timeline (one step = 0.1 s).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from conav_jax.geometry import to_world
from conav_jax.envs.agents.base import row_title
from conav_jax.envs.agents.registry import check_agent

# Carry entries a learned agent may expose (same names and shapes as the env's ground-truth
# observations): activity probs (107,), object probs (51,), future trajectory (5, 2) robot frame.
PREDICTION_KEYS = ("activity_probs", "object_probs", "future_traj")
TOP_K = 5


def agent_predictions(carry: Any) -> dict[str, Any]:
    """The PREDICTION_KEYS entries of an agent's carry: a mapping or an object (e.g. a NamedTuple)
    with those names, or with a `predicted` mapping of them (the CoNav policy's PolicyCarry).
    Empty for baselines."""
    if isinstance(carry, Mapping):
        return {k: carry[k] for k in PREDICTION_KEYS if k in carry}
    found = {k: getattr(carry, k) for k in PREDICTION_KEYS if hasattr(carry, k)}
    if isinstance(getattr(carry, "predicted", None), Mapping):
        found.update({k: v for k, v in carry.predicted.items() if k in PREDICTION_KEYS})
    return found


def record_episode(env, agent, episode: int, seed: int = 0) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Run one episode jitted to its end (t_end) and return (frames, sources).

    frames: "pose" (T+1, 3), "rgbd" (T+1, H, W, 4), "segmentation" (T+1, H, W), "done" (T+1,),
    "action" (T+1, 2) (the action
    taken from that frame), and each intention key available, frame t being the state after t
    steps. sources: intention key -> "predicted" (from the agent's carry) or "ground_truth"."""
    import jax
    import jax.numpy as jnp

    from conav_jax.envs.agents.base import as_state_agent
    from conav_jax.envs.rollout import apply_action, jit_with_bank

    steps = int(env.split.episodes["t_end"][episode])
    ep = jnp.int32(episode)
    agent = as_state_agent(agent)
    # The frame's panorama and segmentation are for the viewer; the agent sees its own keys.
    keys = tuple(dict.fromkeys(("rgbd", "segmentation") + env.default_observation_keys() + agent.reads))

    def seen(state):  # (the frame's observation, the agent's: the keys it reads only)
        full = env.observe(state, keys)
        return full, full.replace(obs={k: full.obs[k] for k in agent.reads})

    def start(key):
        state = env.reset_to_episode(key, ep, observe=False)
        return state, agent.init(key, seen(state)[1])

    carry_shape = jax.eval_shape(start, jax.random.PRNGKey(0))[1]
    predicted = set(agent_predictions(carry_shape))
    obs_keys = set(keys)
    sources = {k: "predicted" if k in predicted else "ground_truth" for k in PREDICTION_KEYS if k in predicted or k in obs_keys}

    def run(key):
        k_init, k_run = jax.random.split(key)

        def body(c, k):
            state, carry = c
            full, mine = seen(state)
            action, carry = agent.act(mine, carry, k)
            preds = agent_predictions(carry)
            frame = {"pose": state.pipeline_state.qpos, "rgbd": full.obs["rgbd"], "done": state.done, "action": action}
            frame["segmentation"] = full.obs["segmentation"]
            for name, src in sources.items():
                frame[name] = preds[name] if src == "predicted" else full.obs[name]
            return (apply_action(env, agent, state, action), carry), frame

        _, frames = jax.lax.scan(body, start(k_init), jax.random.split(k_run, steps + 1))
        return frames

    # The episode bank as an argument, not constants in the program (envs.rollout.jit_with_bank).
    frames = jax.tree.map(np.asarray, jit_with_bank(env, run)(jax.random.PRNGKey(seed)))
    return frames, sources


def _box_mesh(center, half, rgb):
    import trimesh

    m = trimesh.creation.box(extents=2.0 * np.asarray(half, np.float64))
    m.apply_translation(np.asarray(center, np.float64))
    m.visual.vertex_colors = np.append(np.asarray(rgb, np.uint8), 255)
    return m


def _mesh3d(mesh):
    import rerun as rr

    return rr.Mesh3D(
        vertex_positions=np.asarray(mesh.vertices, np.float32),
        triangle_indices=np.asarray(mesh.faces, np.uint32),
        vertex_normals=np.asarray(mesh.vertex_normals, np.float32),
        vertex_colors=np.asarray(mesh.visual.vertex_colors, np.uint8),
    )


def log_scene(rec, scene, robot_height_m: float) -> None:
    """Static geometry: floor, walls (one mesh), furniture (a mesh per object, category colours)
    and a label point above each object."""
    import rerun as rr
    import trimesh

    from conav_jax.data.categories import CATEGORY_NAMES, FLOOR_RGB, WALL_RGB
    from conav_jax.data.scene import STRUCTURE_WALL, scene_boxes

    x0, y0, x1, y1 = scene.bounds
    rec.log("world/scene/floor", _mesh3d(_box_mesh(((x0 + x1) / 2, (y0 + y1) / 2, -0.01), ((x1 - x0) / 2, (y1 - y0) / 2, 0.01), FLOOR_RGB)), static=True)
    boxes = scene_boxes(scene, robot_height_m)
    walls = [_box_mesh(boxes.center[i], boxes.half_extents[i], WALL_RGB) for i in np.flatnonzero(boxes.category == STRUCTURE_WALL)]
    if walls:
        rec.log("world/scene/walls", _mesh3d(trimesh.util.concatenate(walls)), static=True)
    tops, labels = [], []
    for i in np.flatnonzero(boxes.category != STRUCTURE_WALL):
        name = CATEGORY_NAMES[boxes.category[i]]
        rec.log(f"world/scene/furniture/{int(boxes.object_index[i]):03d}_{name}", _mesh3d(_box_mesh(boxes.center[i], boxes.half_extents[i], boxes.rgb[i])), static=True)
        tops.append(boxes.center[i] + np.array([0.0, 0.0, boxes.half_extents[i][2] + 0.05]))
        labels.append(name)
    if tops:
        rec.log("world/scene/labels", rr.Points3D(np.asarray(tops), radii=0.02, labels=labels, show_labels=True), static=True)


def _top_k_text(title: str, probs: np.ndarray, names, source: str) -> str:
    order = np.argsort(-probs, kind="stable")[:TOP_K]
    lines = [f"{title} ({source.replace('_', ' ')})", ""] + [f"{r + 1}. {names[i]}: {probs[i]:.2f}" for r, i in enumerate(order)]
    return "\n".join(lines)


def log_episode(rec, env, episode: int, frames: dict[str, np.ndarray], sources: dict[str, str], agent_name: str) -> None:
    """Everything of one recorded episode on the "step" timeline (plus the static scene)."""
    import rerun as rr

    from conav_jax.data.activities import load_activity_graph
    from conav_jax.data.categories import CATEGORY_NAMES
    from conav_jax.motion.skeleton import PARENTS

    split, task = env.split, env.task
    e = split.episodes
    scene = split.scenes[int(e["scene_index"][episode])]
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    log_scene(rec, scene, task.robot_height_m)

    goal = np.asarray(e["goal_xy"][episode], np.float64)
    ring = np.linspace(0.0, 2.0 * np.pi, 65)
    circle = np.stack([goal[0] + task.success_radius_m * np.cos(ring), goal[1] + task.success_radius_m * np.sin(ring), np.full_like(ring, 0.02)], -1)
    rec.log("world/goal", rr.Points3D([[goal[0], goal[1], 0.05]], radii=0.08, colors=[[30, 200, 60]], labels=["goal"]), static=True)
    rec.log("world/goal/success_radius", rr.LineStrips3D([circle], colors=[[30, 200, 60]], radii=0.01), static=True)

    t_end = int(e["t_end"][episode])
    joints = split.joints(episode)[: t_end + 1]  # (T, 22, 3) world
    root = np.asarray(e["root_xy"][episode][: t_end + 1])
    phase = np.asarray(e["phase"][episode][: t_end + 1])
    phase_rgb = np.array([[40, 110, 220], [240, 150, 30], [150, 60, 200], [120, 120, 120]], np.uint8)
    rec.log("world/human/path", rr.Points3D(np.c_[root, np.full(len(root), 0.02)], radii=0.015, colors=phase_rgb[np.clip(phase, 0, 3)]), static=True)
    bones = [(j, p) for j, p in enumerate(PARENTS) if p >= 0]

    r, h = task.robot_radius_m, task.robot_height_m
    rec.log("world/robot/body", rr.Cylinders3D(lengths=[h], radii=[r], centers=[[0.0, 0.0, h / 2]], colors=[[80, 80, 90]]), static=True)
    rec.log("world/robot/heading", rr.Arrows3D(origins=[[0.0, 0.0, h]], vectors=[[0.6, 0.0, 0.0]], colors=[[230, 40, 40]]), static=True)

    graph = load_activity_graph()
    activity_names = [a.name for a in graph.activities]
    saliency = None
    segmentation = frames.get("segmentation")
    if segmentation is not None:  # class 0: no object; category k is class k + 1
        rec.log("camera/segmentation", rr.AnnotationContext(
            [(0, "no object", (0, 0, 0))] + [(k + 1, name) for k, name in enumerate(CATEGORY_NAMES)]), static=True)
    if "object_probs" in sources and segmentation is not None:  # where the object intention points (what the policy reads)
        from conav_jax.models.policy import object_saliency

        saliency = (np.asarray(object_saliency(segmentation, frames["object_probs"])) * 255).astype(np.uint8)
    pose = frames["pose"]
    done = frames["done"] > 0.5
    ended = int(np.argmax(done)) if done.any() else len(done) - 1  # the frame the episode ended at
    for t in range(t_end + 1):
        rec.set_time("step", sequence=t)
        rec.log("world/human/joints", rr.Points3D(joints[t], radii=0.03, colors=[[220, 80, 60]]))
        rec.log("world/human/bones", rr.LineStrips3D([[joints[t, j], joints[t, p]] for j, p in bones], radii=0.015, colors=[[220, 80, 60]]))
        if t > ended:
            continue  # the robot's episode is over: its pose and sensors stay as they ended
        x, y, yaw = (float(v) for v in pose[t])
        rec.log("world/robot", rr.Transform3D(translation=[x, y, 0.0], rotation_axis_angle=rr.RotationAxisAngle(axis=[0.0, 0.0, 1.0], radians=yaw)))
        rec.log("world/robot_path", rr.LineStrips3D([np.c_[pose[: t + 1, :2], np.full(t + 1, 0.03)]], radii=0.02, colors=[[230, 40, 40]]))
        rgbd = frames["rgbd"][t]
        rec.log("camera/rgb", rr.Image((np.clip(rgbd[..., :3], 0.0, 1.0) * 255).astype(np.uint8)))
        rec.log("camera/depth", rr.DepthImage(rgbd[..., 3].astype(np.float32), meter=1.0))
        if segmentation is not None:
            rec.log("camera/segmentation", rr.SegmentationImage((segmentation[t] + 1).astype(np.uint8)))
        if saliency is not None:
            rec.log(f"camera/object_saliency/{sources['object_probs']}", rr.Image(saliency[t]))
        rec.log("metrics/distance_to_goal_m", rr.Scalars(float(np.hypot(x - goal[0], y - goal[1]))))
        for key, names, title in (("activity_probs", activity_names, "activity B"), ("object_probs", CATEGORY_NAMES, "object B")):
            if key in sources:
                probs = np.asarray(frames[key][t], np.float64)
                path = f"intention/{sources[key]}/{key.split('_')[0]}"
                rec.log(f"{path}/top5", rr.BarChart(np.sort(probs)[::-1][:TOP_K]))
                rec.log(f"{path}/text", rr.TextDocument(_top_k_text(title, probs, names, sources[key])))
        if "future_traj" in sources:
            future = np.asarray(to_world(np.asarray(frames["future_traj"][t]), pose[t]))
            strip = np.c_[np.vstack([root[min(t, len(root) - 1)], future]), np.full(len(future) + 1, 0.05)]
            rec.log(f"world/human/future_traj/{sources['future_traj']}", rr.LineStrips3D([strip], radii=0.02, colors=[[250, 200, 0]], labels=[f"5-step trajectory ({sources['future_traj'].replace('_', ' ')})"]))
    rec.log("info", rr.TextDocument(f"episode {episode} of {split.name} in {scene.name}; agent {agent_name}; robot episode ended at step {ended}"), static=True)


def view_episode(
    data: str | Path,
    split: str,
    episode: int,
    agent: str,
    out: str | Path,
    checkpoint: str | None = None,
    intention_kwargs: dict | None = None,
    resolution: tuple[int, int] | None = None,
    seed: int = 0,
    spawn: bool = False,
    materials: str | None = None,
) -> str:
    """Record `episode` of `split` driven by `agent` into the rerun file `out` (and stream it to
    a spawned viewer with `spawn`); returns a one-line summary. Inputs are checked before
    anything is built: ValueError naming the first problem. `resolution` None: the trained
    run's, else SensorConfig's default; `materials` (SensorConfig.materials) None: the trained
    run's (envs.config.run_materials), else SensorConfig's default."""
    from conav_jax.data.episodes import read_manifest
    from conav_jax.envs.agents.registry import run_resolution

    manifest = read_manifest(data)
    if split not in manifest["splits"]:
        raise ValueError(f"{data}: no split {split!r}; has {sorted(manifest['splits'])}")
    n = int(manifest["splits"][split]["episodes"])
    if not 0 <= episode < n:
        raise ValueError(f"view_episode.episode must be in [0, {n}) for split {split!r}, got {episode}")
    spec = check_agent(agent, checkpoint)
    predictors = dict(intention_kwargs or {})
    if predictors and not spec.takes_intentions:
        raise ValueError(f"agent {agent!r} reads no intention inputs (view_episode.intention_kwargs)")
    out = Path(out)
    if out.suffix != ".rrd":
        raise ValueError(f"view_episode.out must name a .rrd file, got {out}")
    h, w = run_resolution([(agent, checkpoint)] if spec.needs_checkpoint else [], resolution)
    out.parent.mkdir(parents=True, exist_ok=True)

    import rerun as rr

    from conav_jax.envs import ConavEnv, EnvConfig, SensorConfig
    from conav_jax.envs.agents.registry import make_agent

    from conav_jax.envs.config import run_materials

    if materials is None:
        materials = run_materials(checkpoint) if spec.needs_checkpoint and checkpoint else SensorConfig.materials
    sensor = SensorConfig(resolution=(h, w), materials=materials)
    env = ConavEnv(data, split, EnvConfig(sensor=sensor), max_episodes=episode + 1)
    built = make_agent(agent, env, checkpoint, **predictors)
    frames, sources = record_episode(env, built, episode, seed)

    rec = rr.RecordingStream("conav_view", recording_id=f"{split}-{episode}-{agent}")
    if spawn:
        rr.spawn(connect=False, recording=rec)
        rec.set_sinks(rr.FileSink(str(out)), rr.GrpcSink())
    else:
        rec.save(str(out))
    log_episode(rec, env, episode, frames, sources, row_title(built))
    rec.flush()
    rec.disconnect()
    return (f"wrote {out}: episode {episode} ({split}), agent {row_title(built)}, {len(frames['pose'])} steps, "
            f"panorama {h}x{w}; intentions: " + intentions_summary(sources, built.reads))


def intentions_summary(sources: dict[str, str], reads) -> str:
    """The recording's intention panels, each with its source, and for ground truth whether the
    agent read it or it is shown only (a debugging aid the agent never saw): "activity_probs
    ground_truth (shown, not read), ..." or "none"."""
    return ", ".join(f"{k} {src}" + ("" if src == "predicted" or k in reads else " (shown, not read)")
                     for k, src in sources.items()) or "none"
