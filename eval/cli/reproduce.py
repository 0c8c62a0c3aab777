"""`conav reproduce`: the paper's Tables 2 and 3, every stage from data to tables, resumable;
the plan (conav_jax.eval.cli.reproduce_plan), its steps (eval.cli.reproduce_steps), progress
(eval.cli.reproduce_progress), runners and pack (eval.cli.reproduce_run) are the library's."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
import signal
import sys
import time
import traceback
from pathlib import Path

from conav_jax.eval.cli.args import as_flags, flag, parse_resolution

def add(sub) -> None:
    from conav_jax.models.policy import ENCODERS
    from conav_jax.eval.cli.reproduce_plan import (BUDGETS, EVAL_SPLITS, GROUND_TRUTH_ROWS, LARGE_PANORAMA_DAGGER_EPISODES,
                                          STAGES, TRAINERS, ReproduceConfig)

    d = {f.name: f.default for f in dataclasses.fields(ReproduceConfig)}

    p = sub.add_parser(
        "reproduce", help="the paper's Tables 2 and 3: every stage from data to tables, resumable",
        description="Generate the data, train the predictors, the learned baselines and every CoNav row "
        "(Table 3's five intention ablations and DAgger, each for --seeds seeds), evaluate every agent on the "
        "val split and write results.json and tables.md. Stages already done are skipped; a stage cut short "
        "resumes where it stopped (every training run resumes from its checkpoints).")
    h, w = d["resolution"]
    p.add_argument("--preset", choices=sorted(BUDGETS), default=d["preset"])
    p.add_argument("--out", required=True, help="output directory (data, runs, eval, results.json, tables.md)")
    p.add_argument("--seeds", type=int, default=d["seeds"],
                   help=f"training seeds of every learned CoNav row (default {d['seeds']})")
    p.add_argument("--stage", choices=STAGES, default=None, action="append",
                   help="run only this stage (repeat for several, run in the plan's order; default: every stage not "
                   "done); a step whose runs are not trained yet waits, and the stage stays to run")
    p.add_argument("--resolution", type=parse_resolution, default=d["resolution"], metavar="HxW",
                   help=f"panorama HxW of every agent (default the paper's {h}x{w})")
    p.add_argument("--workers", type=int, default=min(d["workers"], os.cpu_count() or 1),
                   help="dataset generation processes")
    p.add_argument("--dagger-beta", type=float, default=d["dagger_beta"], metavar="P",
                   help="DAgger with the expert acting at a step of round r with probability P**r (`conav train "
                        "policy --dagger-beta`); 0 (default): the policy alone. Other values train and evaluate runs "
                        "of their own (runs/dagger_betaP_s*), and the tables show every DAgger variant evaluated")
    p.add_argument("--dagger-rounds", type=int, default=d["dagger_rounds"], metavar="N",
                   help="DAgger rounds after BC (default: the preset's, " +
                        ", ".join(f"{k} {b.dagger_rounds}" for k, b in BUDGETS.items()) +
                        "); another count trains and evaluates runs of its own (runs/dagger[_betaP]_roundsN_s*)")
    p.add_argument("--dagger-episodes", type=int, default=d["dagger_episodes"], metavar="N",
                   help="train episodes each DAgger round records (`conav train policy --dagger-episodes`; default: "
                        f"{LARGE_PANORAMA_DAGGER_EPISODES} at panoramas of 112x448 and more, else all the policy's); "
                        "another count trains and evaluates runs of its own (runs/dagger[...]_episodesN_s*)")
    p.add_argument("--encoder", choices=sorted(ENCODERS), default=d["encoder"],
                   help="the CoNav policy's panorama encoder in every BC and DAgger run (`conav train policy "
                        f"--encoder`; default {d['encoder']}, the published runs'; patch trains faster at large "
                        "panoramas, BENCHMARKS.md); one OUT directory holds one encoder")
    p.add_argument("--mirror", action="store_true",
                   help="train the intention predictor on frames mirrored half the time (`conav train intention --mirror`)")
    p.add_argument("--recolour", action="store_true",
                   help="train the intention predictor on frames whose colours are redrawn for every sample and "
                        "update (`conav train intention --recolour`)")
    p.add_argument("--seen-objects", action="store_true",
                   help="the intention predictor weighs activities by whether the robot's panoramas have shown their "
                   "object (`conav train intention --seen-objects`: oracle segmentation, listed as privileged)")
    p.add_argument("--trainer", choices=TRAINERS, default=d["trainer"],
                   help="how the CoNav rows are trained: offline (default; `conav train policy`: recorded windows of a "
                   "subset of the train episodes, BC then DAgger rounds) or live (`conav train live`: the live simulator "
                   "over every train episode; adds the ground-truth rows " + ", ".join(GROUND_TRUTH_ROWS) + " to Table 3, "
                   "and DAgger is beta falling from 1 to --dagger-beta); one OUT directory holds one trainer")
    b = BUDGETS["paper"]
    for name, kind, what, default in (("intention_steps", int, "updates", f"paper {b.intention_steps}"),
                                      ("intention_batch", int, "samples per update", "`conav train intention`'s"),
                                      ("intention_lr", float, "peak learning rate", "`conav train intention`'s")):
        p.add_argument(flag(name), type=kind, default=None, metavar="N" if kind is int else "LR",
                       help=f"the intention predictor's {what} (default: the preset's; {default}); one OUT "
                       "directory holds one budget")
    for name, kind, what in (("live_lanes", int, "lanes"), ("live_window_steps", int, "window steps"),
                             ("live_iterations", int, "updates"), ("live_lr", float, "peak learning rate")):
        p.add_argument(flag(name), type=kind, default=None, metavar="N" if kind is int else "LR",
                       help=f"with --trainer live: the runs' {what} (default: the preset's; paper "
                       f"{getattr(b, name):g}); one OUT directory holds one budget")
    p.add_argument("--eval-split", choices=EVAL_SPLITS, default=d["eval_split"],
                   help="the split every evaluation runs on: val (default; the reported numbers) or minival, where "
                   "budgets and variants are chosen (evaluations under OUT/eval_minival, results_minival.json, "
                   "tables_minival.md; the runs are shared)")
    p.add_argument("--rows", default="", metavar="ROW,...",
                   help="the Table 3 rows to train and evaluate (default: every one; the tables list the others as "
                   "not run)")
    p.add_argument("--seed", type=int, default=None, metavar="S",
                   help="run only training seed S's steps of the bc, dagger and eval stages (each BC run is "
                        "evaluated as soon as it has trained; an evaluation of a run not trained yet waits): a machine "
                        "with the time for one seed leaves it finished, and its pack small; a stage is done once "
                        "every seed's steps are")
    p.add_argument("--gpus", type=int, default=1, metavar="N",
                   help="run up to N steps at once, each in a process of its own on one GPU (the first N of "
                        "CUDA_VISIBLE_DEVICES, else 0..N-1), a step starting as soon as the runs it reads are made; "
                        "each logs to OUT/logs/ (default 1: one step at a time, in this process, on every visible "
                        "device)")
    p.add_argument("--time-limit", type=float, default=None, metavar="SECONDS",
                   help="a sitting of SECONDS: start no step expected to end later (its expected time: the longest "
                        "of its kind this OUT has recorded, with the evaluations of the run it trains; a kind never "
                        "run here starts while time is left), so a sitting cut by its machine's limit leaves "
                        "evaluated runs; steps already running finish (default: no limit)")
    p.add_argument("--unpack", default=None, metavar="PACK",
                   help="first unpack a pack.tar written by --stage pack (continuing on a fresh machine)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the stages and their steps (each a library function and its configs), run nothing")
    p.set_defaults(func=run)


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def run(args: argparse.Namespace) -> int:
    # `timeout` and batch schedulers stop a run with SIGTERM: raise, so the step it cut records its time.
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        return _reproduce_stages(args)
    finally:
        signal.signal(signal.SIGTERM, previous)


def _reproduce_stages(args: argparse.Namespace) -> int:
    from conav_jax.eval.cli import reproduce_plan as rp
    from conav_jax.eval.cli import reproduce_progress as rpp
    from conav_jax.eval.cli import reproduce_run as rr
    from conav_jax.provenance import git_state
    from conav_jax.eval.cli import reproduce_tables as rt

    cfg = rp.ReproduceConfig(out=Path(args.out).resolve(), preset=args.preset, seeds=args.seeds,
                             resolution=tuple(args.resolution), workers=args.workers, dagger_beta=args.dagger_beta,
                             dagger_rounds=args.dagger_rounds, dagger_episodes=args.dagger_episodes,
                             encoder=args.encoder, mirror=args.mirror, recolour=args.recolour,
                             seen_objects=args.seen_objects,
                             trainer=args.trainer, rows=tuple(r.strip() for r in args.rows.split(",") if r.strip()),
                             eval_split=args.eval_split,
                             **{name: getattr(args, name) for name in rp.BUDGET_OVERRIDES})
    if args.gpus < 1:
        print(f"conav reproduce: --gpus must be at least 1, got {args.gpus}", file=sys.stderr)
        return 2
    if args.time_limit is not None and args.time_limit <= 0:
        print(f"conav reproduce: --time-limit must be positive seconds, got {args.time_limit:g}", file=sys.stderr)
        return 2
    started = time.monotonic()
    seconds_left = None if args.time_limit is None else (lambda: args.time_limit - (time.monotonic() - started))
    if args.seed is not None and not 0 <= args.seed < cfg.seeds:
        print(f"conav reproduce: --seed {args.seed} is not one of the run's seeds 0..{cfg.seeds - 1}", file=sys.stderr)
        return 2
    cfg.out.mkdir(parents=True, exist_ok=True)
    if args.unpack:
        print(f"unpacked {len(rr.unpack(Path(args.unpack), cfg.out))} files from {args.unpack}")
    progress = rpp.read_progress(cfg.out)
    try:
        rpp.check_out(progress, cfg)
    except ValueError as e:
        print(f"conav reproduce: {as_flags(str(e), args.field_flags)}", file=sys.stderr)
        return 2
    plan = rp.plan_stages(cfg)
    older = progress.get("run_format", 1) < rpp.RUN_FORMAT
    try:  # an OUT made before steps had names: its records move to them
        dropped = rpp.upgrade_progress(progress, plan, cfg.out)
    except ValueError as e:
        print(f"conav reproduce: {e}", file=sys.stderr)
        return 2
    if older and not args.dry_run:
        rpp.write_progress(cfg.out, progress)
    if dropped:
        print(f"progress.json: {len(dropped)} record(s) of commands this plan does not hold were dropped (another "
              "variant's; its runs resume from their checkpoints when it is planned again)", flush=True)
    # Data are regenerated from their seed on a fresh machine (tables and pack read none: their
    # record of the data's making stays).
    asked = set(args.stage or ())
    reads_data = not asked or not asked <= {"tables", "pack"}
    if reads_data and not all(p.exists() for p in plan[0].outputs):
        progress["stages"].pop(plan[0].name, None)
        for step in plan[0].steps:
            progress["commands"].pop(step.name, None)
    stages = [st for st in plan if not asked or st.name in asked]
    if asked and reads_data and plan[0].name not in asked and plan[0].name not in progress["stages"]:
        # Stages asked for alone on a machine without the data (a fresh one, after --unpack) make them first.
        print(f"[{plan[0].name}] the data are missing: making them before [{', '.join(sorted(asked))}]")
        stages.insert(0, plan[0])
    commit = git_state()[0][:7]  # provenance's: CONAV_COMMIT names the commit of a copy of the tree
    gpus = rr.visible_gpus() if args.gpus == 1 and not args.dry_run else None
    if gpus is not None and len(gpus) > 1:
        print(f"{len(gpus)} GPUs visible: each step runs on all of them as one device mesh; --gpus {len(gpus)} "
              "runs that many steps at once instead, one GPU each", flush=True)
    if args.gpus > 1 and not args.dry_run:
        stages = _reproduce_parallel(args, cfg, plan, stages, progress, seconds_left)
        if isinstance(stages, int):
            return stages
    for st in stages:
        if args.dry_run:
            _print_stage(st, progress)
            continue
        # A stage asked for alone runs what it can: a step whose runs are not made yet waits (the
        # learned baselines' evaluations before their training, say) instead of failing.
        todo, waiting = rpp.ready_steps(plan, st, rpp.stage_seed(st, args.seed), set(progress["commands"]))
        for step in waiting:
            print(f"[{st.name}] waits for the runs it reads: {step.name}")
        if st.name in progress["stages"] and not todo and st.name not in ("tables", "pack"):  # those two are of now
            print(f"[{st.name}] done ({progress['stages'][st.name]:.0f} s), skipped")
            continue
        t_stage = time.perf_counter()
        expected, needs, not_started = rpp.expected_seconds(plan, progress), rpp.prerequisites(plan), set()
        for step in todo:
            if seconds_left is not None and (needs[step.name] & not_started or
                                             not rpp.fits_in(step, expected, seconds_left())):
                print(f"[{st.name}] not started, for want of time: {step.name}", flush=True)
                not_started.add(step.name)
                continue
            print(f"\n{_shown(step)}", flush=True)
            try:  # run_here counts the time of a step cut short (failed, interrupted, SIGTERM) as cut
                rr.run_here(step, cfg.out, progress)
            except Exception:
                traceback.print_exc()
                print(f"conav reproduce: stage {st.name} failed at {step.name}", flush=True)
                return 1
        left = [step for step in st.steps if step.name not in progress["commands"]]
        if left:  # steps waiting for their runs, or with --seed the other seeds' steps
            if args.seed is None:
                print(f"[{st.name}] {len(left)} of the stage's {len(st.steps)} steps wait for their runs: "
                      "the stage is not done", flush=True)
                continue
            mine = sum(step.seed == args.seed for step in left)
            print(f"[{st.name}] seed {args.seed}: " + (f"{mine} step(s) wait for their runs" if mine else
                  "its steps done") + f"; {len(left)} of the stage's {len(st.steps)} to run", flush=True)
            continue
        if st.name == "tables":
            extra = {"preset": cfg.preset, "seeds": cfg.seeds, "resolution": rp.resolution_name(cfg),
                     "encoder": cfg.encoder, "trainer": cfg.trainer, "split": cfg.eval_split,
                     "commit": commit, "command": "conav " + shlex.join(sys.argv[1:] or ["reproduce"]),
                     "stage_seconds": rpp.stage_seconds(plan, progress), "command_seconds": progress["commands"],
                     "cut_seconds": progress.get("cut", {})}
            # FileNotFoundError without any evaluation
            results = rt.collect_results(cfg.out, cfg.seeds, extra, cfg.dagger, cfg.table3_rows, cfg.eval_dir)
            (cfg.out / cfg.results_file).write_text(json.dumps(results, indent=1) + "\n")
            (cfg.out / cfg.tables_file).write_text(rt.render_tables(results))
        if st.name == "pack":
            path, size, left_out = rr.write_pack(cfg, progress)
            print(f"wrote {path} ({size / 2**20:.1f} MiB)")
            for ckpt, why in left_out:
                print(f"left out of the pack for want of room: {ckpt.relative_to(cfg.out)} ({why})")
        progress["stages"][st.name] = round(time.perf_counter() - t_stage, 1)
        rpp.write_progress(cfg.out, progress)
        print(f"[{st.name}] done in {progress['stages'][st.name]:.0f} s", flush=True)
    if (cfg.out / cfg.tables_file).exists() and not args.dry_run:
        print((cfg.out / cfg.tables_file).read_text())
    return 0


def _shown(step) -> str:
    """A step for people: its name and its call."""
    from conav_jax.eval.cli.reproduce_steps import call_text

    return f"{step.name}: {call_text(step.call)}"


def _print_stage(st, progress: dict) -> None:
    """--dry-run: the stage, whether it is done, and each step."""
    todo = [step for step in st.steps if step.name not in progress["commands"]]
    print(f"[{st.name}] {'done' if st.name in progress['stages'] and not todo else 'to run'}")
    for step in st.steps:
        print(f"  {'(done) ' if step.name in progress['commands'] else ''}{_shown(step)}")


def _reproduce_parallel(args: argparse.Namespace, cfg, plan: list, stages: list, progress: dict,
                        seconds_left=None) -> list | int:
    """`--gpus N`: every step of `stages` not done (training seed `--seed`'s alone in the seeded
    stages) runs through `reproduce.run_parallel` (starting only what fits in `seconds_left()`
    where given: `--time-limit`); stages whose steps are all done are marked so,
    with their steps' summed time. Returns the stages left to run here (tables, pack), or an
    exit code."""
    from conav_jax.eval.cli import reproduce_progress as rpp
    from conav_jax.eval.cli import reproduce_run as rr

    work = [st for st in stages if st.name not in ("tables", "pack")]
    if not work:
        return stages
    try:
        gpus = rr.gpu_slots(args.gpus)
    except ValueError as e:
        print(f"conav reproduce: {as_flags(str(e), args.field_flags)}", file=sys.stderr)
        return 2
    import jax

    jax.config.update("jax_platforms", "cpu")  # this process runs no program: its GPUs are the steps'
    todo = []
    for st in work:
        seed = rpp.stage_seed(st, args.seed)
        todo += [step for step in st.steps if step.name not in progress["commands"] and seed in (None, step.seed)]
    print(f"{len(todo)} step(s) to run, up to {len(gpus)} at once on GPU(s) {', '.join(gpus)}", flush=True)
    t0 = time.perf_counter()
    digest = rr.save_config(cfg)  # each step's process plans from it, and runs its step by name
    rc, waiting = rr.run_parallel(plan, todo, cfg.out, progress, gpus,
                                  lambda step: rr.child_command(cfg.out, digest, step, args.compile_cache),
                                  seconds_left=seconds_left)
    done, needs = set(progress["commands"]), rpp.prerequisites(plan)
    for step in waiting:
        why = ("not started after the failure" if rc else "waits for the runs it reads"
               if not needs[step.name] <= done else "not started, for want of time")
        print(f"{why}: {step.name}")
    for st in work:
        keys = [step.name for step in st.steps]
        if all(k in progress["commands"] for k in keys):
            progress["stages"][st.name] = round(sum(progress["commands"][k] for k in keys), 1)
    rpp.write_progress(cfg.out, progress)
    print(f"{len(todo) - len(waiting)} step(s) ended in {time.perf_counter() - t0:.0f} s", flush=True)
    if rc:
        print(f"conav reproduce: a step failed (exit {rc}); its log is named above", file=sys.stderr)
        return rc
    return [st for st in stages if st.name in ("tables", "pack")]

