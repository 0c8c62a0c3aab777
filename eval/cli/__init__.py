"""The `conav` command: a thin client over the library, at the top of the dependency graph.

argv -> argparse (one module per command: generate, train, eval, view, curve, demo, reproduce,
bench; shared flags in `args`) -> frozen configs -> the stage's plain function
(conav_jax.data.episodes, train.*, eval.*, envs.bench) -> a summary on stdout. A library error
names config fields; `main` writes those a flag sets as the flag. Stage modules are imported
only by the command that runs, so `conav --help` stays quick. Before any command runs, JAX's
persistent compilation cache is switched on (`--compile-cache`), so a second run of a command
recompiles nothing. Data-parallel commands (`--devices`) first join a multi-host run if the
environment describes one (conav_jax.parallel).
"""

from __future__ import annotations

import argparse
import os
import sys

from conav_jax import __version__
from conav_jax.compile_cache import COMPILE_CACHE_ENV, default_compile_cache_dir, enable_compile_cache
from conav_jax.eval.cli import bench, curve, demo, eval, generate, reproduce, train, view
from conav_jax.eval.cli.args import as_flags, leaf_flags, parse_checkpoints, parse_physics_override, use_pretrained
from conav_jax.eval.cli.train import imitation_config, network_base, policy_model
from conav_jax.eval.cli.args import train_config

__all__ = ["build_parser", "main", "enable_compile_cache", "default_compile_cache_dir", "parse_checkpoints",
           "parse_physics_override", "use_pretrained", "imitation_config", "network_base", "policy_model",
           "train_config"]

COMMANDS = (generate, train, eval, view, demo, curve, reproduce, bench)
_use_pretrained = use_pretrained  # the name an earlier release exported


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="conav", description="CoNav: batched human-centered collaborative navigation in MuJoCo MJX")
    parser.add_argument("--version", action="version", version=f"conav_jax {__version__}")
    parser.add_argument("--compile-cache", default=None, metavar="DIR|off",
                        help=f"keep compiled programs in DIR between runs (default: ${COMPILE_CACHE_ENV}, else "
                        f"{default_compile_cache_dir()}); off: compile every time")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in COMMANDS:
        command.add(sub)
    leaf_flags(parser)
    return parser


def main(argv: list[str] | None = None, compile_cache: bool = True) -> int:
    """Run one `conav` command; its exit code. `compile_cache=False` leaves JAX's cache as it is
    (the demo's stages run inside one command)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    try:
        if compile_cache:
            enable_compile_cache(args.compile_cache)
        if hasattr(args, "devices"):  # a data-parallel command: join a multi-host run first
            from conav_jax.parallel import maybe_initialize_distributed

            maybe_initialize_distributed()
        rc = int(args.func(args) or 0)
        sys.stdout.flush()  # here, where a closed pipe is caught, not at exit
        return rc
    except (ValueError, FileNotFoundError) as e:
        print(f"conav {args.command}: error: {as_flags(str(e), args.field_flags)}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader of our output stopped (`conav ... | head`): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # so the exit's flush cannot fail again
        return 1
