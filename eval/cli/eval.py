"""`conav eval`: every episode of a split for each agent -> records, metrics with 95% intervals
and the Table 2/3 report (conav_jax.eval.sweep.run_eval: plan_eval, load_env, sweep)."""

from __future__ import annotations

import argparse
from pathlib import Path

from conav_jax.eval.cli.args import (
    INTENTION_FLAGS,
    agent_run_args,
    devices_arg,
    intention_kwargs,
    mesh,
    parse_checkpoints,
    resolution_arg,
    materials_arg,
    translate_errors,
    use_pretrained,
)


def add(sub) -> None:
    from conav_jax.envs.agents.registry import AGENTS

    p = sub.add_parser("eval", help="evaluate agents on a split: per-episode records, metrics with CIs, Table 2/3 report")
    p.add_argument("--data", required=True, help="dataset dir written by `conav generate`")
    p.add_argument("--split", default="val")
    p.add_argument("--agent", required=True,
                   help="comma-separated agent names: " + "; ".join(f"{k} ({s.summary})" for k, s in AGENTS.items())
                   + "; or package.module:factory for an agent of your own")
    agent_run_args(p, several=True)
    p.add_argument("--ablation-checkpoints", default=None, metavar="NAME=RUN,...",
                   help="conav runs for the Table 3 ablation; the names none, activity, object, "
                   "activity_object, all mark which intention inputs a run uses")
    p.add_argument("--episodes", type=int, default=None, help="evaluate only the first N episodes")
    p.add_argument("--batch", type=int, default=256, help="parallel lanes: episodes in flight at once")
    p.add_argument("--seed", type=int, default=0, help="rollout keys and bootstrap resampling")
    resolution_arg(p, "(default with a trained run: the run's)")
    materials_arg(p, "(default with trained runs: those they were trained on, else instance)")
    p.add_argument("--out", required=True, help="output directory")
    devices_arg(p)
    translate_errors(p, agents="--agent", agent_checkpoints="--checkpoint", ablations="--ablation-checkpoints",
                     **INTENTION_FLAGS)
    p.set_defaults(func=run)


def parse_ablations(text: str | None) -> tuple[tuple[str, str], ...]:
    """`name=RUN,...` -> ((name, run), ...)."""
    if not text:
        return ()
    out = []
    for item in text.split(","):
        name, sep, run = item.strip().partition("=")
        if not sep or not name or not run:
            raise ValueError(f"--ablation-checkpoints entries look like name=RUN_DIR, got {item!r}")
        out.append((name, run))
    return tuple(out)


def run(args: argparse.Namespace) -> int:
    from conav_jax.eval import sweep

    agents = tuple(n.strip() for n in args.agent.split(",") if n.strip())
    use_pretrained(args, agents)
    doc = sweep.run_eval(
        args.data, args.split, agents, args.out, progress=True,
        checkpoint=parse_checkpoints(args.checkpoint), intention_kwargs=intention_kwargs(args),
        ablations=parse_ablations(args.ablation_checkpoints), episodes=args.episodes, batch=args.batch,
        seed=args.seed, resolution=args.resolution, devices=args.devices, materials=args.materials,
    )
    print((Path(args.out) / "report.md").read_text().split("## Figures")[0].rstrip())
    print(f"wrote {Path(args.out)} ({len(doc['agents'])} agents, {len(doc['ablations'])} ablations, {doc['episodes']} "
          f"episodes, {mesh(args).size} device(s))")
    return 0
