"""The `conav` command: one dispatcher over every stage's sub-commands.

Each stage registers its own sub-commands; heavy modules are imported only by the sub-command
that runs, so `conav --help` stays instant.
"""

from __future__ import annotations

import argparse
import sys

from conav_jax import __version__
from conav_jax.cli import add_generate


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="conav", description="CoNav: batched human-centered collaborative navigation in MuJoCo MJX"
    )
    parser.add_argument("--version", action="version", version=f"conav_jax {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    add_generate(sub)
    bench = sub.add_parser("bench", help="throughput benchmarks (run them on the GPU machine)")
    bench_sub = bench.add_subparsers(dest="bench", metavar="WHAT", required=True)
    from envs.bench import add_bench_sim

    add_bench_sim(bench_sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError) as e:
        print(f"conav {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
