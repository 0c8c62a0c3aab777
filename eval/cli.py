"""The `conav` command: one dispatcher over every stage's sub-commands.

Each stage registers its own sub-commands; heavy modules are imported only by the sub-command
that runs, so `conav --help` stays instant. Commands with `--devices` (data-parallel) first join
a multi-host run if the environment describes one (conav_jax.parallel).
"""

from __future__ import annotations

import argparse
import sys

from conav_jax import __version__
from conav_jax.cli import add_generate


def build_parser() -> argparse.ArgumentParser:
    from envs.bench import add_bench_sim
    from eval.bench import add_bench_eval
    from eval.demo import add_demo
    from eval.curve import add_curve
    from eval.sweep import add_eval
    from eval.viewer import add_view
    from train.bench import add_bench_train
    from train.intention import add_train_intention
    from train.policy import add_train_policy
    from train.ppo import add_train_rl
    from train.trajectory import add_train_trajectory

    parser = argparse.ArgumentParser(
        prog="conav", description="CoNav: batched human-centered collaborative navigation in MuJoCo MJX"
    )
    parser.add_argument("--version", action="version", version=f"conav_jax {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    add_generate(sub)
    train = sub.add_parser("train", help="train the intention / trajectory predictors, the policy, PPO")
    train_sub = train.add_subparsers(dest="model", metavar="MODEL", required=True)
    for add in (add_train_intention, add_train_trajectory, add_train_policy, add_train_rl):
        add(train_sub)
    add_eval(sub)
    add_view(sub)
    add_demo(sub)
    add_curve(sub)
    bench = sub.add_parser("bench", help="throughput benchmarks (run them on the GPU machine)")
    bench_sub = bench.add_subparsers(dest="bench", metavar="WHAT", required=True)
    for add in (add_bench_sim, add_bench_train, add_bench_eval):
        add(bench_sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    try:
        if hasattr(args, "devices"):  # a data-parallel command: join a multi-host run first
            from conav_jax.parallel import maybe_initialize_distributed

            maybe_initialize_distributed()
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError) as e:
        print(f"conav {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
