"""`conav view`: one episode recorded as a rerun .rrd (conav_jax.eval.viewer.view_episode)."""

from __future__ import annotations

import argparse

from conav_jax.eval.cli.args import (
    INTENTION_FLAGS,
    agent_run_args,
    intention_kwargs,
    resolution_arg,
    translate_errors,
    use_pretrained,
)


def add(sub) -> None:
    from conav_jax.envs.agents.registry import AGENTS

    p = sub.add_parser("view", help="record one episode as a rerun .rrd (scene, human, robot, panorama, intentions)")
    p.add_argument("--data", required=True, help="dataset dir written by `conav generate`")
    p.add_argument("--split", default="val")
    p.add_argument("--episode", type=int, required=True, help="episode index within the split")
    p.add_argument("--agent", default="pioneer", help=f"who drives the robot: {', '.join(AGENTS)}")
    agent_run_args(p)
    resolution_arg(p, "(default with a trained run: the run's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="output .rrd file")
    p.add_argument("--spawn", action="store_true", help="also stream to a spawned rerun viewer")
    translate_errors(p, **INTENTION_FLAGS)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from conav_jax.eval.viewer import view_episode

    use_pretrained(args, (args.agent,))
    print(view_episode(args.data, args.split, args.episode, args.agent, args.out, args.checkpoint,
                       intention_kwargs(args), args.resolution, args.seed, args.spawn))
    return 0
