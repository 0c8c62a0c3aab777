"""`conav demo`: the whole pipeline on the tiny preset, on CPU, in minutes.

generate -> train intention -> train trajectory -> train policy (BC + one DAgger round) ->
evaluate every agent (report, plots) -> one rerun recording. Each stage is the same `conav`
sub-command a user would run, so the demo doubles as a worked example of the command line;
the commands are printed as they run.
"""

from __future__ import annotations

import argparse
import shlex
import time
from pathlib import Path


def add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the whole pipeline on the tiny preset (CPU, minutes)")
    p.add_argument("--out", required=True, help="output directory (data, runs, eval, episode.rrd)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resolution", default="16x64", help="panorama HxW used throughout (small: CPU)")
    p.set_defaults(func=run_demo)


def demo_commands(out: Path, seed: int, resolution: str) -> list[list[str]]:
    data, runs = out / "data", out / "runs"
    quick = ["--log-every", "25", "--no-progress"]
    return [
        ["generate", "--preset", "tiny", "--out", str(data), "--seed", str(seed)],
        ["train", "intention", "--data", str(data), "--out", str(runs / "intention"), "--steps", "100",
         "--batch", "16", "--val-every", "100", "--ckpt-every", "100", "--seed", str(seed), *quick],
        ["train", "trajectory", "--data", str(data), "--out", str(runs / "trajectory"), "--steps", "200",
         "--batch", "64", "--val-every", "200", "--ckpt-every", "200", "--seed", str(seed), *quick],
        ["train", "policy", "--data", str(data), "--out", str(runs / "policy"), "--intention", str(runs / "intention"),
         "--trajectory", str(runs / "trajectory"), "--resolution", resolution, "--steps", "150", "--batch", "8",
         "--dagger-rounds", "1", "--dagger-steps", "100", "--val-every", "150", "--ckpt-every", "150",
         "--seed", str(seed), *quick],
        ["eval", "--data", str(data), "--split", "val", "--agent", "random,follower,objectgoal-planner,pioneer,expert,conav",
         "--checkpoint", str(runs / "policy"), "--resolution", resolution, "--seed", str(seed), "--out", str(out / "eval")],
        ["view", "--data", str(data), "--split", "val", "--episode", "0", "--agent", "conav", "--checkpoint",
         str(runs / "policy"), "--resolution", resolution, "--out", str(out / "episode0.rrd")],
    ]


def run_demo(args: argparse.Namespace) -> int:
    from eval.cli import main

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    for argv in demo_commands(out, args.seed, args.resolution):
        print(f"\n$ conav {shlex.join(argv)}", flush=True)
        t0 = time.perf_counter()
        rc = main(argv)
        if rc:
            print(f"conav demo: stage `{argv[0]}` failed (exit {rc})")
            return rc
        print(f"[{argv[0]} {argv[1] if argv[0] == 'train' else ''}] done in {time.perf_counter() - t0:.0f} s", flush=True)
    print(
        f"\ndemo finished in {time.perf_counter() - t_start:.0f} s: report {out / 'eval' / 'report.md'}, "
        f"recording {out / 'episode0.rrd'} (open with `rerun {out / 'episode0.rrd'}`)"
    )
    return 0
