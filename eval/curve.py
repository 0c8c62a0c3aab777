"""`conav curve`: the PPO learning-curve PNG from run logs (eval.plots.learning_curve)."""

from __future__ import annotations

from pathlib import Path


def add_curve(sub) -> None:
    """Register `conav curve`."""
    p = sub.add_parser("curve", help="PPO learning curve (success vs env steps) from run logs, as PNG")
    p.add_argument("runs", nargs="+", metavar="[TITLE=]RUN", help="`conav train rl` run dirs")
    p.add_argument("--out", required=True, help="output .png")
    p.add_argument("--window", type=int, default=None,
                   help="training iterations pooled per point (default: each run's reset cycle, else 4)")
    p.set_defaults(func=run_curve)


def run_curve(args) -> int:
    from eval.plots import learning_curve  # matplotlib and jax: only when the command runs
    from conav_jax.runs import LOG_FILE, read_log

    runs = {}
    for spec in args.runs:
        title, _, run = spec.rpartition("=")
        if not (Path(run) / LOG_FILE).is_file():
            raise FileNotFoundError(f"no {LOG_FILE} in {run}")
        runs[title or Path(run).name] = read_log(run)

    if args.window is not None and args.window < 1:
        raise ValueError(f"--window must be at least 1, got {args.window}")
    print(f"wrote {learning_curve(runs, args.out, args.window)}")
    return 0
