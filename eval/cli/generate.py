"""`conav generate`: a CoNav episode dataset from a preset or from the user's scene files
(conav_jax.data.episodes.generate_dataset / generate_from_scenes)."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
import warnings
from pathlib import Path

EPILOG = """\
scene source:
  procedural (default)   the preset's apartments: train, val and minival scenes of their own
  --scenes DIR           every DIR/*.json scene file (the conav_jax.data.scene format), split by name:
                         --val-scenes and --minival-scenes take comma-separated scene file names
                         without .json (e.g. --val-scenes apt_3,apt_7); every other file is train.
                         Each split gets --episodes-per-scene episodes per scene. --preset, when
                         given, supplies the task, motion and navigation settings (default: the
                         DatasetConfig defaults); its scene counts and scene generation are unused.

examples:
  conav generate --preset small --out data/small
  conav generate --scenes my_scenes --val-scenes flat_2 --minival-scenes flat_5 \\
      --episodes-per-scene 200 --out data/mine --seed 1
"""


def add(sub) -> None:
    from conav_jax.data.presets import PRESETS

    p = sub.add_parser(
        "generate",
        help="generate a CoNav episode dataset from a preset or from your own scene files",
        description="Generate a CoNav episode dataset (manifest, scene nav fields, episode shards); "
        "the same seed gives the same bytes.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--preset", choices=sorted(PRESETS), default=None,
                   help="dataset preset (default: tiny); with --scenes, only its task, motion and navigation settings")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=None, help="dataset seed (default: the preset's, 0)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    own = p.add_argument_group("own scenes")
    own.add_argument("--scenes", default=None, metavar="DIR", help="build episodes in DIR/*.json instead of generated apartments")
    own.add_argument("--episodes-per-scene", type=int, default=None, metavar="N", help="episodes per scene (needed with --scenes)")
    own.add_argument("--val-scenes", default="", metavar="NAME,...", help="scene files (names without .json) for val")
    own.add_argument("--minival-scenes", default="", metavar="NAME,...", help="scene files (names without .json) for minival")
    own.add_argument("--name", default=None, help="dataset name recorded in the manifest (default: DIR's name)")
    p.set_defaults(func=run)


def scene_split_from_args(scenes_dir: str | os.PathLike, val: str, minival: str) -> dict[str, list[Path]]:
    """split -> scene files: the named files to val and minival, the rest of DIR/*.json to train.
    ValueError for a name that is not a file in DIR or a file named twice."""
    directory = Path(scenes_dir)
    if not directory.is_dir():
        raise FileNotFoundError(f"--scenes: directory not found: {directory}")
    files = {p.stem: p for p in sorted(directory.glob("*.json"))}
    if not files:
        raise ValueError(f"--scenes: no *.json scene files in {directory}")
    named: dict[str, str] = {}
    split: dict[str, list[Path]] = {"train": [], "val": [], "minival": []}
    for which, spec in (("val", val), ("minival", minival)):
        for name in (n.strip() for n in spec.split(",")):
            if not name:
                continue
            name = name.removesuffix(".json")
            if name not in files:
                raise ValueError(f"--{which}-scenes: no scene file {name}.json in {directory}; has {', '.join(files)}")
            if name in named:
                raise ValueError(f"--{which}-scenes: {name} is already in {named[name]}; splits must not share scenes")
            named[name] = which
            split[which].append(files[name])
    split["train"] = [p for stem, p in files.items() if stem not in named]
    return {k: v for k, v in split.items() if v}


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from conav_jax.config import DatasetConfig
    from conav_jax.data.episodes import (
        BlockedStandingPoint,
        generate_dataset,
        generate_from_scenes,
    )
    from conav_jax.data.presets import preset

    if args.workers < 1:
        raise ValueError("--workers must be at least 1")
    own_flags = [f for f, v in (("--episodes-per-scene", args.episodes_per_scene), ("--val-scenes", args.val_scenes),
                                ("--minival-scenes", args.minival_scenes), ("--name", args.name)) if v]
    if args.scenes is None and own_flags:
        raise ValueError(f"{', '.join(own_flags)} only apply with --scenes DIR")

    def bar(total: int, name: str):
        return lambda it: tqdm(it, total=total, desc=f"generate {name}", unit="scene")

    t0 = time.perf_counter()
    # Scenes whose objects the robot cannot reach print one line each, after the progress bar.
    with warnings.catch_warnings(record=True) as caught:
        try:
            if args.scenes is None:
                cfg = preset(args.preset or "tiny", args.seed)
                n_scenes = sum(n for n, _ in cfg.split_sizes().values())
                m = generate_dataset(cfg, args.out, workers=args.workers, progress=bar(n_scenes, cfg.name))
            else:
                if args.episodes_per_scene is None or args.episodes_per_scene < 1:
                    raise ValueError("--scenes needs --episodes-per-scene N (N >= 1)")
                by_split = scene_split_from_args(args.scenes, args.val_scenes, args.minival_scenes)
                base = preset(args.preset, args.seed) if args.preset else DatasetConfig()
                name = args.name or Path(args.scenes).resolve().name
                cfg = dataclasses.replace(base, name=name, seed=base.seed if args.seed is None else args.seed)
                episodes = {split: args.episodes_per_scene * len(paths) for split, paths in by_split.items()}
                n_scenes = sum(len(v) for v in by_split.values())
                m = generate_from_scenes(by_split, episodes, cfg, args.out, workers=args.workers, progress=bar(n_scenes, name))
        finally:
            for w in caught:
                if issubclass(w.category, BlockedStandingPoint):
                    print(f"warning: {w.message}", file=sys.stderr)
                else:
                    warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    dt = time.perf_counter() - t0
    for split, s in m["splits"].items():
        print(f"{split}: {s['episodes']} episodes in {len(s['scenes'])} scenes, "
              f"mean length {s['mean_length_steps']} steps (max {s['max_length_steps']})")
    print(f"wrote {args.out} in {dt:.1f} s, content hash {m['content_hash'][:16]}")
    return 0

