"""`conav generate`: the data stage's sub-command (registered by the `conav` dispatcher)."""

from __future__ import annotations

import argparse
import os
import time

from conav_jax.presets import PRESETS, preset


def add_generate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("generate", help="generate a CoNav episode dataset from a preset")
    p.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--seed", type=int, default=None, help="dataset seed (default: the preset's, 0)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    p.set_defaults(func=run_generate)


def run_generate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from conav_jax.episodes import generate_dataset

    cfg = preset(args.preset, args.seed)
    if args.workers < 1:
        raise SystemExit("--workers must be at least 1")
    n_scenes = cfg.train_scenes + cfg.val_scenes
    t0 = time.perf_counter()
    m = generate_dataset(
        cfg,
        args.out,
        workers=args.workers,
        progress=lambda it: tqdm(it, total=n_scenes, desc=f"generate {cfg.name}", unit="scene"),
    )
    dt = time.perf_counter() - t0
    for split, s in m["splits"].items():
        print(
            f"{split}: {s['episodes']} episodes in {len(s['scenes'])} scenes, "
            f"mean length {s['mean_length_steps']} steps (max {s['max_length_steps']})"
        )
    print(f"wrote {args.out} in {dt:.1f} s, content hash {m['content_hash'][:16]}")
    return 0
