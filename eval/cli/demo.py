"""`conav demo`: the whole pipeline on the demo preset, each stage (conav_jax.eval.demo) run in
this process as a fresh `conav` process would run it."""

from __future__ import annotations

import argparse
import shlex
import time
from pathlib import Path

from conav_jax.eval.cli.args import parse_resolution

def add(sub) -> None:
    p = sub.add_parser("demo", help="the shipped agent and the baselines on the demo preset; --train: the whole "
                       "pipeline (CPU, minutes)")
    p.add_argument("--out", required=True, help="output directory (data, runs, eval, episode.rrd)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--resolution", default="16x64", type=parse_resolution, metavar="HxW",
                   help="panorama HxW the demo trains at (small: CPU; default 16x64)")
    p.add_argument("--train", action="store_true",
                   help="also train the intention and trajectory predictors and a policy briefly (live imitation) "
                   "before evaluating: the whole pipeline, minutes longer")
    p.add_argument("--no-pretrained", dest="pretrained", action="store_false",
                   help="evaluate and record the demo's own briefly trained policy (at --resolution; implies --train) "
                   "instead of the shipped one (conav_jax/pretrained)")
    p.set_defaults(func=run)


def run_stage(argv) -> int:
    """One stage of `conav demo`, run in this process as a fresh `conav`
    process would run it: JAX's in-memory caches are cleared first. A later stage that reuses a
    function traced by an earlier one lowers to a program of the same computation but other
    function names, whose compile-cache key then misses on the next run (the demo's evaluation
    then compiles again on every run)."""
    import jax

    from conav_jax.eval import cli

    jax.clear_caches()
    return cli.main(list(argv), compile_cache=False)  # the compile cache was set up for the whole command


def run(args: argparse.Namespace) -> int:
    from conav_jax.eval.demo import demo_commands

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    for argv in demo_commands(out, args.seed, "x".join(map(str, args.resolution)), args.pretrained, args.train):
        print(f"\n$ conav {shlex.join(argv)}", flush=True)
        t0 = time.perf_counter()
        rc = run_stage(argv)
        if rc:
            print(f"conav demo: stage `{argv[0]}` failed (exit {rc})")
            return rc
        print(f"[{' '.join(argv[:2]) if argv[0] == 'train' else argv[0]}] done in {time.perf_counter() - t0:.0f} s",
              flush=True)
    print(f"\ndemo finished in {time.perf_counter() - t_start:.0f} s: report {out / 'eval' / 'report.md'}, "
          f"recording {out / 'episode0.rrd'} (open with `rerun {out / 'episode0.rrd'}`)")
    return 0

