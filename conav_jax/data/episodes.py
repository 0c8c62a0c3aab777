"""CoNav episodes: generation into array shards, and loading them back as a padded bank.

scene (scenegen, or the user's scene files) -> navigation fields -> activity pair (activities)
-> human path + motion (motion) -> robot start -> arrays. Each scene's episodes come from their
own seed, so the same dataset seed gives byte-identical shards whatever the number of worker
processes. Every file is written atomically and the manifest, written last, lists each file's
sha256 and a content hash over them: a directory without a manifest, or with a file that does
not match it, is an incomplete dataset.

Layout of a dataset directory:
    manifest.json
    scenes/<name>.json          the scene (conav_jax.data.scene format)
    scenes/<name>.nav.npz       occupancy grid and geodesic fields to every usable object
    train/shard_00000.npz ...   episode arrays (see EPISODE_ARRAYS)
    val/shard_00000.npz ...
    minival/shard_00000.npz ... (when the dataset has a minival split)
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import re
import warnings
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Mapping, NamedTuple, Sequence

import numpy as np

from conav_jax import motion as motion_lib
from conav_jax.config import SPLITS, DatasetConfig
from conav_jax.data import activities as activities_lib
from conav_jax.data.arrayio import load_npz, save_json, save_npz, sha256_file
from conav_jax.data.scene import Scene, load_scene, scene_from_json_dict
from conav_jax.data.scenegen import generate_scene

# The phase codes are stored in the episode arrays; the simulator and trainers import them from here.
from conav_jax.motion.phases import PHASE_DONE
from conav_jax.nav.navigation import (
    OccupancyGrid,
    descend,
    geodesic_field,
    largest_component,
    line_of_sight,
    occupancy_grid,
    smooth_path,
)

MANIFEST = "manifest.json"
DATASET_FORMAT = "conav-episodes"
DATASET_VERSION = 1
MIN_HUMAN_PATH_M = 2.0  # activity B's spot is at least this far (geodesic) from activity A's
SHARD_WRITERS = 8  # threads writing a split's shards at most (with `workers` > 1)

# name -> (per-step?, dtype, meaning). Per-step arrays are (N, T, ...), padded past t_end with
# the last frame (and PHASE_DONE); the others are (N, ...).
EPISODE_ARRAYS: dict[str, tuple[bool, str, str]] = {
    "scene_index": (False, "int32", "index into the manifest's scene list"),
    "activity_a": (False, "int32", "activity id of activity A"),
    "activity_b": (False, "int32", "activity id of activity B (the intention to infer)"),
    "object_a": (False, "int32", "category id of object A"),
    "object_b": (False, "int32", "category id of object B"),
    "instance_a": (False, "int32", "index of object A in the scene's objects"),
    "instance_b": (False, "int32", "index of object B in the scene's objects"),
    "field_a": (False, "int32", "index of the geodesic field to activity A's spot in the scene's nav"),
    "field_b": (False, "int32", "index of the geodesic field to the goal in the scene's nav"),
    "goal_xy": (False, "float32", "goal: activity B's standing point (m)"),
    "robot_start": (False, "float32", "robot start pose (x m, y m, yaw rad)"),
    "geodesic_start_goal_m": (False, "float32", "shortest robot path length start->goal (m), SPL's l"),
    "t_walk_start": (False, "int32", "first step of the human's walk"),
    "t_arrive": (False, "int32", "first step the human stands at the goal"),
    "t_end": (False, "int32", "last step of activity B (episode end)"),
    "root_xy": (True, "float32", "human root (pelvis) ground position (m)"),
    "root_yaw": (True, "float32", "human facing (rad)"),
    "joints_local": (True, "float16", "22 joints minus (root_x, root_y, 0) (m)"),
    "phase": (True, "int8", "0 activity A, 1 walk, 2 activity B, 3 after the end"),
}


class DatasetError(ValueError):
    """A dataset directory that is missing, incomplete or corrupt."""


class BlockedStandingPoint(UserWarning):
    """Scene objects left out of episode sampling because the robot cannot reach their standing
    point (an occupied cell, or outside the scene's main free region). One warning per scene,
    naming each object; silence it with
    `warnings.filterwarnings("ignore", category=BlockedStandingPoint)`."""


# -- navigation per scene ----------------------------------------------------------------------


@dataclass(frozen=True)
class SceneNav:
    """A scene's robot grid and geodesic fields to every usable object's standing point."""

    grid: OccupancyGrid
    fields: np.ndarray  # (K, ny, nx) float32 metres, inf where unreachable
    field_object: np.ndarray  # (K,) int32 object index of each field
    stand_poses: np.ndarray  # (K, 3) float32 standing (x, y, facing yaw) of each field's object

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {
            "free": self.grid.free,
            "origin": np.asarray(self.grid.origin, np.float64),
            "cell_m": np.asarray(self.grid.cell_m, np.float64),
            "fields": self.fields.astype(np.float16),
            "field_object": self.field_object,
            "stand_poses": self.stand_poses,
        }

    @staticmethod
    def from_arrays(a: dict[str, np.ndarray]) -> "SceneNav":
        grid = OccupancyGrid(a["free"].astype(bool), tuple(float(v) for v in a["origin"]), float(a["cell_m"]))
        return SceneNav(grid, a["fields"].astype(np.float32), a["field_object"], a["stand_poses"])


def scene_nav(scene: Scene, cfg: DatasetConfig) -> SceneNav:
    """Grid for the robot radius; a field for every object whose standing point the robot
    can reach within the apartment's main free region. Objects left out are named in one
    BlockedStandingPoint warning."""
    nav, blocked = _scene_nav(scene, cfg)
    _warn_blocked(scene, blocked)
    return nav


def _scene_nav(scene: Scene, cfg: DatasetConfig) -> tuple[SceneNav, list[tuple[int, str]]]:
    """scene_nav without the warning: the nav and (object index, why) of each object left out."""
    task = cfg.task
    grid = occupancy_grid(scene, task.robot_radius_m, cfg.nav.cell_m, task.robot_height_m)
    main = largest_component(grid)
    fields, objs, poses, blocked = [], [], [], []
    for i, o in enumerate(scene.objects):
        pose = o.standing_pose(cfg.scenes.standing_offset_m)
        cell = grid.to_cell(pose[:2])
        if not grid.is_free(pose[:2]):
            blocked.append((i, "not free for the robot"))
            continue
        if not main[cell]:
            blocked.append((i, "outside the main free region"))
            continue
        fields.append(geodesic_field(grid, pose[:2]))
        objs.append(i)
        poses.append(pose)
    ny, nx = grid.shape
    nav = SceneNav(
        grid,
        np.asarray(fields, np.float32).reshape(-1, ny, nx),
        np.asarray(objs, np.int32),
        np.asarray(poses, np.float32).reshape(-1, 3),
    )
    return nav, blocked


def _warn_blocked(scene: Scene, blocked: list[tuple[int, str]], stacklevel: int = 3) -> None:
    """One warning per scene; `stacklevel` 3 points at scene_nav's caller."""
    if not blocked:
        return
    listed = "; ".join(f"objects[{i}] ({scene.objects[i].category}) {why}" for i, why in blocked)
    warnings.warn(
        BlockedStandingPoint(
            f"scene {scene.name}: {len(blocked)} of {len(scene.objects)} objects dropped from episode sampling, "
            f"standing point blocked: {listed}"
        ),
        stacklevel=stacklevel,
    )


# -- one scene's episodes ----------------------------------------------------------------------


def _robot_start(rng: np.random.Generator, nav: SceneNav, human_xy, field_goal, cfg: DatasetConfig):
    """A free pose near the human, facing it, with a clear line of sight if one can be found."""
    task = cfg.task
    lo, hi = task.robot_start_distance_m
    fallback = None
    for attempt in range(200):
        r = rng.uniform(lo, hi)
        ang = rng.uniform(-math.pi, math.pi)
        xy = (human_xy[0] + r * math.cos(ang), human_xy[1] + r * math.sin(ang))
        cell = nav.grid.to_cell(xy)
        if not nav.grid.is_free(xy) or not np.isfinite(field_goal[cell]):
            continue
        if field_goal[cell] < task.success_radius_m + 1.0:
            continue
        yaw = math.atan2(human_xy[1] - xy[1], human_xy[0] - xy[0]) + rng.uniform(-0.25, 0.25)
        pose = (xy[0], xy[1], math.atan2(math.sin(yaw), math.cos(yaw)))
        if line_of_sight(nav.grid, xy, human_xy):
            return pose
        fallback = fallback or pose
    return fallback


def _episode(rng, scene: Scene, nav: SceneNav, graph, cfg: DatasetConfig):
    """One episode's arrays (per-step ones unpadded), or None if this draw does not work out."""
    counts: dict[str, int] = {}
    for k in nav.field_object:
        name = scene.objects[k].category
        counts[name] = counts.get(name, 0) + 1
    pair = activities_lib.sample_activity_pair(rng, graph, counts)
    if pair is None:
        return None
    act_a, act_b = graph.activity(pair[0]), graph.activity(pair[1])
    fa_choices = [k for k, o in enumerate(nav.field_object) if scene.objects[o].category == act_a.object]
    fb_choices = [k for k, o in enumerate(nav.field_object) if scene.objects[o].category == act_b.object]
    fa = fa_choices[int(rng.integers(len(fa_choices)))]
    fb = fb_choices[int(rng.integers(len(fb_choices)))]
    stand_a, stand_b = nav.stand_poses[fa], nav.stand_poses[fb]
    field_b = nav.fields[fb]
    if field_b[nav.grid.to_cell(stand_a[:2])] < MIN_HUMAN_PATH_M:
        return None
    cells = descend(nav.grid, field_b, stand_a[:2])
    path = smooth_path(nav.grid, np.concatenate([stand_a[None, :2], cells[1:-1], stand_b[None, :2]]))
    start = _robot_start(rng, nav, stand_a[:2], field_b, cfg)
    if start is None:
        return None
    hm = motion_lib.compose_episode_motion(
        rng,
        (act_a.id, act_a.primitive),
        (act_b.id, act_b.primitive),
        tuple(float(v) for v in stand_a),
        tuple(float(v) for v in stand_b),
        path,
        cfg.motion,
    )
    root3 = np.concatenate([hm.root_xy, np.zeros((len(hm.root_xy), 1), np.float32)], axis=-1)
    return {
        "activity_a": act_a.id,
        "activity_b": act_b.id,
        "object_a": act_a.object_index,
        "object_b": act_b.object_index,
        "instance_a": int(nav.field_object[fa]),
        "instance_b": int(nav.field_object[fb]),
        "field_a": fa,
        "field_b": fb,
        "goal_xy": np.asarray(stand_b[:2], np.float32),
        "robot_start": np.asarray(start, np.float32),
        "geodesic_start_goal_m": float(field_b[nav.grid.to_cell(start[:2])]),
        "t_walk_start": hm.t_walk_start,
        "t_arrive": hm.t_arrive,
        "t_end": hm.t_end,
        "root_xy": hm.root_xy.astype(np.float32),
        "root_yaw": hm.root_yaw.astype(np.float32),
        "joints_local": (hm.joints - root3[:, None, :]).astype(np.float16),
        "phase": hm.phase.astype(np.int8),
    }


def _scene_seed(seed: int, scene_index: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, scene_index]))


class _SceneJob(NamedTuple):
    """One scene to build: generated from its seed (`scene` None) or given (a scene file's)."""

    cfg: DatasetConfig
    scene_index: int  # position in the manifest's scene list; with the dataset seed, the scene's seed
    name: str
    n_episodes: int
    scene: Scene | None = None
    source: str = ""  # the given scene's file, for error messages


def _build_scene(job: _SceneJob):
    """Worker: the job's scene (generated, or the given one), its nav, its `n_episodes` episodes
    and the objects its nav leaves out (warned about by the caller, once, in the main process)."""
    cfg, scene_index, name, n_episodes = job.cfg, job.scene_index, job.name, job.n_episodes
    rng = _scene_seed(cfg.seed, scene_index)
    graph = activities_lib.load_activity_graph()
    if job.scene is None:
        for _ in range(20):  # a scene too cramped to host any activity pair is drawn again
            scene = generate_scene(rng, cfg.scenes, name)
            nav, blocked = _scene_nav(scene, cfg)
            probe = np.random.default_rng(0)
            if any(_episode(probe, scene, nav, graph, cfg) is not None for _ in range(5)):
                break
        else:
            raise RuntimeError(f"could not generate a usable scene {name}")
        where = f"scene {name}"
    else:
        scene = job.scene
        nav, blocked = _scene_nav(scene, cfg)
        where = f"{job.source}: scene {name}"
        usable = {}
        for k in nav.field_object:
            usable[scene.objects[k].category] = usable.get(scene.objects[k].category, 0) + 1
        if not activities_lib.available_links(graph, usable):
            raise ValueError(
                f"{where}: no activity link joins two of its reachable objects' categories, so it hosts no "
                f"episode (reachable: {', '.join(f'{c} x{n}' for c, n in sorted(usable.items())) or 'none'})"
            )
    episodes = []
    misses = 0
    while len(episodes) < n_episodes:
        ep = _episode(rng, scene, nav, graph, cfg)
        if ep is None:
            misses += 1
            if misses > 50 * (n_episodes + 1):
                # A given scene is the user's to fix (ValueError); a generated one is a generator bug.
                raise (RuntimeError if job.scene is None else ValueError)(
                    f"{where}: too few valid episodes ({len(episodes)}/{n_episodes}); activity B's spot must be "
                    f"at least {MIN_HUMAN_PATH_M} m (geodesic) from activity A's, with a free robot start near the human"
                )
            continue
        ep["scene_index"] = scene_index
        episodes.append(ep)
    return scene, nav, episodes, blocked


def _split_counts(total: int, parts: int) -> list[int]:
    base, extra = divmod(total, parts)
    return [base + (1 if i < extra else 0) for i in range(parts)]


def stack_episodes(episodes: list[dict], t_max: int | None = None) -> dict[str, np.ndarray]:
    """Stack per-episode dicts into arrays, padding per-step arrays to t_max with the last frame."""
    lengths = [int(e["t_end"]) + 1 for e in episodes]
    t_max = t_max or max(lengths)
    out = {}
    for name, (per_step, dtype, _) in EPISODE_ARRAYS.items():
        if not per_step:
            out[name] = np.asarray([e[name] for e in episodes], dtype)
            continue
        rows = []
        for e, n in zip(episodes, lengths):
            a = np.asarray(e[name], dtype)
            pad = np.repeat(a[-1:], t_max - n, axis=0)
            if name == "phase":
                pad = np.full_like(pad, PHASE_DONE)
            rows.append(np.concatenate([a, pad], axis=0))
        out[name] = np.stack(rows)
    return out


def dataset_content_hash(manifest: dict) -> str:
    """The dataset's content hash: sha256 of the sorted, concatenated sha256 digests of every
    file the manifest lists (scene JSON, scene nav, episode shards). The writer stores it in the
    manifest; the reader recomputes it, so an edited manifest does not pass for the dataset."""
    digests = sorted(
        [s["sha256_json"] for s in manifest["scenes"]]
        + [s["sha256_nav"] for s in manifest["scenes"]]
        + [sh["sha256"] for sp in manifest["splits"].values() for sh in sp["shards"]]
    )
    return hashlib.sha256("".join(digests).encode()).hexdigest()


def _check_split_size(split: str, n_scenes: int, n_eps: int) -> None:
    if n_scenes < 1 or n_eps < n_scenes:
        raise ValueError(f"{split}: need at least one scene and one episode per scene, got {n_scenes}, {n_eps}")


def generate_dataset(
    cfg: DatasetConfig,
    out_dir: str | os.PathLike,
    workers: int = 1,
    progress: Callable[[Iterable], Iterable] | None = None,
) -> dict:
    """Generate the dataset `cfg` describes (procedural scenes) into `out_dir`; returns the
    manifest. Splits are built in SPLITS order, minival only when cfg has minival scenes."""
    jobs = []
    for split, (n_scenes, n_eps) in cfg.split_sizes().items():
        _check_split_size(split, n_scenes, n_eps)
        for k, n in enumerate(_split_counts(n_eps, n_scenes)):
            jobs.append((split, _SceneJob(cfg, len(jobs), f"{split}_{k:03d}", n)))
    return _write_dataset(cfg, jobs, out_dir, workers, progress, scene_source="procedural")


_SCENE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


def generate_from_scenes(
    scene_paths_by_split: Mapping[str, Sequence[str | os.PathLike]],
    episodes_per_split: Mapping[str, int],
    cfg: DatasetConfig,
    out_dir: str | os.PathLike,
    workers: int = 1,
    progress: Callable[[Iterable], Iterable] | None = None,
) -> dict:
    """A dataset from the user's own scene files (conav_jax.data.scene format) into `out_dir`;
    returns the manifest. Same layout, determinism and atomicity as `generate_dataset`.

    `scene_paths_by_split` maps split names (of SPLITS; any non-empty subset) to scene files,
    each file in one split only; `episodes_per_split` gives each split's episode count, spread
    over its scenes as evenly as possible. `cfg` supplies the seed, task, motion and navigation
    settings (its scene-generation settings are unused); the manifest records it with the split
    sizes replaced by the ones given. Scene seeds follow the order of SPLITS, then of the files
    in each split. ValueError for an unknown split, a file in two splits, two scenes of one
    name, a name unfit for a file name, or a scene that can host no episode; SceneFormatError
    (naming the file and field) for an invalid scene file."""
    unknown = sorted(set(scene_paths_by_split) - set(SPLITS))
    if unknown:
        raise ValueError(f"unknown split(s) {', '.join(map(repr, unknown))}; splits are {', '.join(SPLITS)}")
    if set(episodes_per_split) != set(scene_paths_by_split):
        raise ValueError(
            f"episodes_per_split names splits {sorted(episodes_per_split)}, scene_paths_by_split "
            f"{sorted(scene_paths_by_split)}: give an episode count for each split with scenes"
        )
    if not scene_paths_by_split:
        raise ValueError("no scene files given")
    seen_files: dict[Path, str] = {}
    seen_names: dict[str, str] = {}
    sizes: dict[str, int] = {}
    jobs = []
    for split in SPLITS:
        if split not in scene_paths_by_split:
            continue
        paths = [Path(p) for p in scene_paths_by_split[split]]
        n_eps = episodes_per_split[split]
        _check_split_size(split, len(paths), n_eps)
        sizes[f"{split}_scenes"], sizes[f"{split}_episodes"] = len(paths), n_eps
        for path, n in zip(paths, _split_counts(n_eps, len(paths))):
            key = path.resolve()
            if key in seen_files:
                raise ValueError(f"{path}: listed in split {seen_files[key]!r} and in {split!r}; splits must not share scenes")
            seen_files[key] = split
            # Through the JSON form the dataset stores, so the stored file is the scene used.
            scene = scene_from_json_dict(load_scene(path).to_json_dict(), source=str(path))
            if not _SCENE_NAME.fullmatch(scene.name):
                raise ValueError(
                    f"{path}: name: {scene.name!r} cannot name the dataset's scene files; "
                    "use letters, digits, '_', '.' and '-', starting with a letter or digit"
                )
            if scene.name in seen_names:
                raise ValueError(f"{path}: name: {scene.name!r} is also the name of {seen_names[scene.name]}")
            seen_names[scene.name] = str(path)
            jobs.append((split, _SceneJob(cfg, len(jobs), scene.name, n, scene, str(path))))
    sizes.update({f"{sp}_{what}": 0 for sp in SPLITS if sp not in scene_paths_by_split for what in ("scenes", "episodes")})
    cfg = dataclasses.replace(cfg, **sizes)
    jobs = [(split, job._replace(cfg=cfg)) for split, job in jobs]
    return _write_dataset(cfg, jobs, out_dir, workers, progress, scene_source="files")


def _write_dataset(
    cfg: DatasetConfig,
    jobs: list[tuple[str, _SceneJob]],
    out_dir: str | os.PathLike,
    workers: int,
    progress: Callable[[Iterable], Iterable] | None,
    scene_source: str,
) -> dict:
    """Build every (split, job) and write the dataset: scene files, nav, shards, then the
    manifest last. The one writer behind generate_dataset and generate_from_scenes."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if (out / MANIFEST).exists():
        (out / MANIFEST).unlink()  # the old dataset stops being valid before any file changes
    progress = progress or (lambda it: it)
    scene_jobs = [job for _, job in jobs]
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            results = list(progress(pool.map(_build_scene, scene_jobs)))
    else:
        results = list(progress(map(_build_scene, scene_jobs)))

    manifest: dict = {
        "format": DATASET_FORMAT,
        "version": DATASET_VERSION,
        "config": cfg.to_dict(),
        "scene_source": scene_source,
        "scenes": [],
        "splits": {},
        "arrays": {k: {"per_step": v[0], "dtype": v[1], "meaning": v[2]} for k, v in EPISODE_ARRAYS.items()},
    }
    by_split: dict[str, list[dict]] = {split: [] for split in SPLITS if any(sp == split for sp, _ in jobs)}
    for (scene, nav, eps, blocked), (split, _) in zip(results, jobs):
        _warn_blocked(scene, blocked, stacklevel=4)  # at the caller of generate_dataset / _from_scenes
        scene_file = f"scenes/{scene.name}.json"
        nav_file = f"scenes/{scene.name}.nav.npz"
        manifest["scenes"].append(
            {
                "name": scene.name,
                "split": split,
                "json": scene_file,
                "nav": nav_file,
                "sha256_json": save_json(out / scene_file, scene.to_json_dict()),
                "sha256_nav": save_npz(out / nav_file, nav.to_arrays()),
            }
        )
        by_split[split].extend(eps)
    for split, eps in by_split.items():
        chunks = {f"{split}/shard_{s0 // cfg.episodes_per_shard:05d}.npz": eps[s0 : s0 + cfg.episodes_per_shard]
                  for s0 in range(0, len(eps), cfg.episodes_per_shard)}
        # Shards are independent files: threads stack, hash and write them side by side (numpy's
        # copies, hashing and file writes release the GIL); each shard's bytes are those of a
        # serial write.
        with ThreadPoolExecutor(max(1, min(workers, SHARD_WRITERS))) as pool:
            digests = list(pool.map(lambda item: save_npz(out / item[0], stack_episodes(item[1])), chunks.items()))
        shards = [{"file": fname, "episodes": len(chunk), "sha256": digest}
                  for (fname, chunk), digest in zip(chunks.items(), digests)]
        lengths = np.asarray([e["t_end"] + 1 for e in eps])
        manifest["splits"][split] = {
            "episodes": len(eps),
            "scenes": [s["name"] for s in manifest["scenes"] if s["split"] == split],
            "shards": shards,
            "mean_length_steps": round(float(lengths.mean()), 2),
            "max_length_steps": int(lengths.max()),
        }
    manifest["content_hash"] = dataset_content_hash(manifest)
    save_json(out / MANIFEST, manifest)
    return manifest


# -- loading -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class EpisodeSplit:
    """One split loaded into memory: scenes, their nav data and the stacked episode arrays."""

    name: str
    manifest: dict
    scenes: tuple[Scene, ...]  # all scenes of the dataset, indexed by scene_index
    navs: tuple[SceneNav, ...]
    episodes: dict[str, np.ndarray]  # EPISODE_ARRAYS, (N, ...) / (N, T_max, ...)
    config: DatasetConfig
    data_dir: str | None = None  # the dataset directory it was loaded from (None: made by hand)

    @property
    def content_hash(self) -> str | None:
        """The dataset's content hash, from its manifest (None for a split made by hand): what
        runs trained on the split record of their data."""
        return self.manifest.get("content_hash")

    @property
    def num_episodes(self) -> int:
        return int(self.episodes["t_end"].shape[0])

    @property
    def max_steps(self) -> int:
        return int(self.episodes["phase"].shape[1])

    def joints(self, i: int) -> np.ndarray:
        """World joints (T, 22, 3) float32 of episode i."""
        root = self.episodes["root_xy"][i]
        j = self.episodes["joints_local"][i].astype(np.float32)
        j[..., 0] += root[:, None, 0]
        j[..., 1] += root[:, None, 1]
        return j


def read_manifest(data_dir: str | os.PathLike) -> dict:
    """The manifest of the dataset in `data_dir`, checked: format, version, and the content hash
    recomputed from the file digests it lists (DatasetError naming the directory otherwise).
    The files themselves are checked against those digests when load_split reads them."""
    import json

    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise DatasetError(f"dataset directory not found: {data_dir}")
    path = data_dir / MANIFEST
    if not path.is_file():
        raise DatasetError(f"{data_dir} has no {MANIFEST}: not a dataset, or its generation did not finish")
    try:
        m = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{path}: corrupt manifest ({e})") from e
    if not isinstance(m, dict) or m.get("format") != DATASET_FORMAT or m.get("version") != DATASET_VERSION:
        raise DatasetError(f"{path}: not a {DATASET_FORMAT} v{DATASET_VERSION} manifest")
    try:
        expected = dataset_content_hash(m)
    except (KeyError, TypeError, AttributeError) as e:
        raise DatasetError(f"{path}: corrupt manifest: malformed file list ({e!r})") from e
    if m.get("content_hash") != expected:
        raise DatasetError(
            f"{data_dir}: the manifest's content_hash {str(m.get('content_hash'))[:16]}... does not match the file "
            f"digests it lists ({expected[:16]}...): the manifest was edited or is corrupt"
        )
    return m


def load_split(
    data_dir: str | os.PathLike, split: str, max_episodes: int | None = None, verify: bool = True
) -> EpisodeSplit:
    """Load one split ("train", "val" or, when the dataset has it, "minival"); with `verify`,
    every file read is checked against the manifest's sha256. The split keeps the manifest and
    `data_dir` as given."""
    source, data_dir = str(data_dir), Path(data_dir)
    m = read_manifest(data_dir)
    if split not in m["splits"]:
        hint = ""
        if split == "minival":
            hint = " (generated without a minival split: DatasetConfig.minival_scenes was 0; generate it again to add one)"
        raise DatasetError(f"{data_dir}: no split {split!r}; has {sorted(m['splits'])}{hint}")

    def checked(rel: str, digest: str) -> Path:
        p = data_dir / rel
        if not p.is_file():
            raise DatasetError(f"{data_dir}: file {rel} listed in the manifest is missing")
        if verify and sha256_file(p) != digest:
            raise DatasetError(f"{data_dir}: file {rel} does not match the manifest (modified or partial)")
        return p

    scenes, navs = [], []
    for s in m["scenes"]:
        scenes.append(load_scene(checked(s["json"], s["sha256_json"])))
        navs.append(SceneNav.from_arrays(load_npz(checked(s["nav"], s["sha256_nav"]))))
    chunks = []
    total = 0
    for sh in m["splits"][split]["shards"]:
        if max_episodes is not None and total >= max_episodes:
            break
        chunks.append(load_npz(checked(sh["file"], sh["sha256"])))
        total += sh["episodes"]
    t_max = max(c["phase"].shape[1] for c in chunks)
    episodes = {}
    for name, (per_step, _, _) in EPISODE_ARRAYS.items():
        parts = []
        for c in chunks:
            a = c[name]
            if per_step and a.shape[1] < t_max:
                pad = np.repeat(a[:, -1:], t_max - a.shape[1], axis=1)
                if name == "phase":
                    pad = np.full_like(pad, PHASE_DONE)
                a = np.concatenate([a, pad], axis=1)
            parts.append(a)
        episodes[name] = np.concatenate(parts, axis=0)[:max_episodes]
    return EpisodeSplit(split, m, tuple(scenes), tuple(navs), episodes, DatasetConfig.from_dict(m["config"]), source)
