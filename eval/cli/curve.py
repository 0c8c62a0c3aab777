"""`conav curve`: PPO learning curves (success against env steps) from run logs, as a PNG
(conav_jax.eval.plots.learning_curve)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add(sub) -> None:
    p = sub.add_parser("curve", help="PPO learning curve (success vs env steps) from run logs, as PNG")
    p.add_argument("runs", nargs="+", metavar="[TITLE=]RUN", help="`conav train rl` run dirs")
    p.add_argument("--out", required=True, help="output .png")
    p.add_argument("--window", type=int, default=None,
                   help="training iterations pooled per point (default: each run's reset cycle, else 4)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from conav_jax.eval.plots import learning_curve
    from conav_jax.runs import read_log

    if args.window is not None and args.window < 1:
        raise ValueError(f"--window must be at least 1, got {args.window}")
    logs = {}
    for spec in args.runs:
        title, _, run_dir = spec.rpartition("=")
        logs[title or Path(run_dir).name] = read_log(run_dir)
    print(f"wrote {learning_curve(logs, args.out, args.window)}")
    return 0
