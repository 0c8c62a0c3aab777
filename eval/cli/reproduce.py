"""`conav reproduce`: the paper's Tables 2 and 3, every stage from data to tables, resumable;
the plan (conav_jax.eval.cli.reproduce_plan), its steps (eval.cli.reproduce_steps), progress
(eval.cli.reproduce_progress), runners and pack (eval.cli.reproduce_run) are the library's."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shlex
import signal
import sys
import time
import traceback
from pathlib import Path

from conav_jax.eval.cli.args import add_fields, as_flags, config_from_args, field_docs, parse_names, parse_resolution

def add(sub) -> None:
    from conav_jax.eval.cli.reproduce_plan import STAGES
    from conav_jax.eval.cli.reproduce_run import PACK_LIMIT_BYTES

    p = sub.add_parser(
        "reproduce", help="the paper's Tables 2 and 3: every stage from data to tables, resumable",
        description="Generate the data, train the predictors, the learned baselines (--baseline-seeds seeds "
        "each) and every CoNav row "
        "(Table 3's five intention ablations and DAgger, each for --seeds seeds), evaluate every agent on the "
        "val split and write results.json and tables.md. Stages already done are skipped; a stage cut short "
        "resumes where it stopped (every training run resumes from its checkpoints).")
    p.add_argument("--out", required=True, help="output directory (data, runs, eval, results.json, tables.md)")
    _config_args(p.add_argument_group("the run (ReproduceConfig)"))
    p.add_argument("--stage", choices=STAGES, default=None, action="append",
                   help="run only this stage (repeat for several, run in the plan's order; default: every stage not "
                   "done); a step whose runs are not trained yet waits, and the stage stays to run")
    p.add_argument("--seed", type=int, default=None, metavar="S",
                   help="run only training seed S's steps of the baselines, bc, dagger and eval stages (each BC run is "
                        "evaluated as soon as it has trained; an evaluation of a run not trained yet waits): a machine "
                        "with the time for one seed leaves it finished, and its pack small; a stage is done once "
                        "every seed's steps are")
    p.add_argument("--gpus", type=int, default=1, metavar="N",
                   help="run up to N steps at once, each in a process of its own on one GPU (the first N of "
                        "CUDA_VISIBLE_DEVICES, else 0..N-1), a step starting as soon as the runs it reads are made; "
                        "each logs to OUT/logs/ (default 1: one step at a time, in this process, on every visible "
                        "device)")
    p.add_argument("--steps-per-gpu", type=int, default=1, metavar="K",
                   help="with --gpus: run up to K steps at once on each GPU, each process taking GPU memory as it "
                        "needs it (one step leaves a GPU partly idle while it compiles or runs small batches; "
                        "default 1)")
    p.add_argument("--runs-per-process", type=int, default=1, metavar="K",
                   help="train up to K seeds of one live row in one process, as one program "
                        "(train.live.train_live_seeds: one compile, and the GPU's work of K runs per step; "
                        "their updates differ from lone runs' only by rounding), and evaluate up to K runs of "
                        "one agent in one process (one env load, shared compiled sweeps; default 1)")
    p.add_argument("--time-limit", type=float, default=None, metavar="SECONDS",
                   help="a sitting of SECONDS: start no step expected to end later (its expected time: the longest "
                        "this OUT has recorded of its configuration's other seeds, else of its kind, with the "
                        "evaluations of the run it trains; runs joined by --runs-per-process go by groups of "
                        "their size, else by their times added up; a kind never "
                        "run here starts while time is left), so a sitting cut by its machine's limit leaves "
                        "evaluated runs; steps already running finish (default: no limit)")
    p.add_argument("--unpack", action="append", default=None, metavar="PACK",
                   help="first unpack a pack.tar written by --stage pack (continuing on a fresh machine); given "
                        "again, or into an OUT with records, each pack's records join the OUT's (runs made on "
                        "several machines at once; the tables stage renders them all)")
    p.add_argument("--pack-limit-mib", type=float, default=None, metavar="MIB",
                   help="the pack stage's size limit: the records always, then the checkpoints of runs still to "
                        "be read while they fit (one left out trains again where the pack is unpacked; default "
                        f"{PACK_LIMIT_BYTES / 2**20:g})")
    p.add_argument("--dry-run", action="store_true",
                   help="print the stages and their steps (each a library function and its configs) with the steps "
                        "done and the time those left take at the times recorded, run nothing")
    p.set_defaults(func=run)


def _config_args(p) -> None:
    """ReproduceConfig's fields as flags, but --out (resolved by `run`) and the data seed (the
    preset's); their comments as help, with the values the presets' budgets give a None."""
    from conav_jax.eval.cli.reproduce_plan import (BUDGET_OVERRIDES, BUDGETS, EVAL_SPLITS, LARGE_PANORAMA_DAGGER_EPISODES,
                                                   TRAINERS, ReproduceConfig)
    from conav_jax.models.policy import ENCODERS

    docs = field_docs(ReproduceConfig)
    helps = {name: f"{docs[name]} (default: the preset's; {_presets(name)}); one OUT directory holds one budget"
             for name in BUDGET_OVERRIDES}
    metavars = {"dagger_beta": "P", "dagger_rounds": "N", "dagger_episodes": "N",
                **{name: "LR" if name.endswith("_lr") else "N" for name in BUDGET_OVERRIDES}}
    add_fields(p, ReproduceConfig, tuple(f.name for f in dataclasses.fields(ReproduceConfig)
                                         if f.name not in ("out", "data_seed")),
               defaults=ReproduceConfig(out=Path(), workers=min(ReproduceConfig.workers, os.cpu_count() or 1)),
               options={**{name: {"metavar": m} for name, m in metavars.items()},
                        "preset": {"choices": sorted(BUDGETS)}, "encoder": {"choices": sorted(ENCODERS)},
                        "trainer": {"choices": TRAINERS}, "eval_split": {"choices": EVAL_SPLITS},
                        "resolution": {"type": parse_resolution, "metavar": "HxW"},
                        "rows": {"type": parse_names, "metavar": "ROW,..."},
                        "baselines": {"type": parse_names, "metavar": "KIND,..."}},
               dagger_rounds=f"{docs['dagger_rounds']} (presets: {_presets('dagger_rounds')})",
               dagger_episodes=f"{docs['dagger_episodes']} (LARGE_PANORAMA_DAGGER_EPISODES: "
                               f"{LARGE_PANORAMA_DAGGER_EPISODES})", **helps)


def _presets(name: str) -> str:
    """Budget field `name` in every preset that sets it ("tiny 1, small 2, paper 2")."""
    from conav_jax.eval.cli.reproduce_plan import BUDGETS

    values = {preset: getattr(b, name) for preset, b in BUDGETS.items() if getattr(b, name) is not None}
    return ", ".join(f"{preset} {v:g}" for preset, v in values.items()) or "every preset: the trainer's own"


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

    cfg = config_from_args(rp.ReproduceConfig, args, out=Path(args.out).resolve())
    for flag in ("gpus", "steps_per_gpu", "runs_per_process"):
        if getattr(args, flag) < 1:
            print(f"conav reproduce: --{flag.replace('_', '-')} must be at least 1, got {getattr(args, flag)}",
                  file=sys.stderr)
            return 2
    for flag, unit in (("pack_limit_mib", ""), ("time_limit", " seconds")):
        value = getattr(args, flag)
        if value is not None and (value <= 0 or not math.isfinite(value)):
            print(f"conav reproduce: --{flag.replace('_', '-')} must be {'positive' if value <= 0 else 'finite'}{unit}, "
                  f"got {value:g}", file=sys.stderr)
            return 2
    started = time.monotonic()
    seconds_left = None if args.time_limit is None else (lambda: args.time_limit - (time.monotonic() - started))
    if args.seed is not None and not 0 <= args.seed < cfg.seeds:
        print(f"conav reproduce: --seed {args.seed} is not one of the run's seeds 0..{cfg.seeds - 1}", file=sys.stderr)
        return 2
    cfg.out.mkdir(parents=True, exist_ok=True)
    for pack in args.unpack or ():
        try:
            print(f"unpacked {len(rr.unpack(Path(pack), cfg.out))} files from {pack}")
        except (FileNotFoundError, ValueError) as e:
            print(f"conav reproduce: {e}", file=sys.stderr)
            return 2
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
    one = args.gpus == args.steps_per_gpu == args.runs_per_process == 1
    gpus = rr.visible_gpus() if one and not args.dry_run else None
    if gpus is not None and len(gpus) > 1:
        print(f"{len(gpus)} GPUs visible: each step runs on all of them as one device mesh; --gpus {len(gpus)} "
              "runs that many steps at once instead, one GPU each", flush=True)
    if (args.gpus > 1 or args.steps_per_gpu > 1 or args.runs_per_process > 1) and not args.dry_run:
        stages = _reproduce_parallel(args, cfg, plan, stages, progress, seconds_left)
        if isinstance(stages, int):
            return stages
    for st in stages:
        if args.dry_run:
            _print_stage(st, plan, progress)
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
            if seconds_left is not None and needs[step.name] & not_started:
                print(f"[{st.name}] not started, for want of time: {step.name} (its runs were not made)", flush=True)
                not_started.add(step.name)
                continue
            if seconds_left is not None and not rpp.fits_in([step], expected, seconds_left()):
                print(f"[{st.name}] {rpp.for_want_of_time(step, expected, seconds_left())}", flush=True)
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
            extra = {"preset": cfg.preset, "seeds": cfg.seeds, "baseline_seeds": cfg.baseline_seeds,
                     "resolution": rp.resolution_name(cfg),
                     "encoder": cfg.encoder, "trainer": cfg.trainer, "split": cfg.eval_split,
                     "commit": commit, "command": "conav " + shlex.join(sys.argv[1:] or ["reproduce"]),
                     "stage_seconds": rpp.stage_seconds(plan, progress), "command_seconds": progress["commands"],
                     "cut_seconds": progress.get("cut", {})}
            # FileNotFoundError without any evaluation
            results = rt.collect_results(cfg.out, cfg.seeds, extra, cfg.dagger, cfg.table3_rows, cfg.eval_dir,
                                         cfg.baseline_seeds)
            (cfg.out / cfg.results_file).write_text(json.dumps(results, indent=1) + "\n")
            (cfg.out / cfg.tables_file).write_text(rt.render_tables(results))
        if st.name == "pack":
            limit = None if args.pack_limit_mib is None else int(args.pack_limit_mib * 2**20)
            path, size, left_out = rr.write_pack(cfg, progress, limit)
            print(f"wrote {path} ({size / 2**20:.1f} MiB)")
            for ckpt, why in left_out:
                print(f"left out of the pack for want of room: {ckpt.relative_to(cfg.out)} ({why})")
        progress["stages"][st.name] = round(time.perf_counter() - t_stage, 1)
        rpp.write_progress(cfg.out, progress)
        print(f"[{st.name}] done in {progress['stages'][st.name]:.0f} s", flush=True)
    if args.dry_run:
        print(f"in all: {rpp.time_left_text(plan, progress, [step for st in stages for step in st.steps])}")
    if (cfg.out / cfg.tables_file).exists() and not args.dry_run:
        print((cfg.out / cfg.tables_file).read_text())
    return 0


def _shown(step) -> str:
    """A step for people: its name and its call."""
    from conav_jax.eval.cli.reproduce_steps import call_text

    return f"{step.name}: {call_text(step.call)}"


def _print_stage(st, plan: list, progress: dict) -> None:
    """--dry-run: the stage, whether it is done, how much is left, and each step."""
    from conav_jax.eval.cli import reproduce_progress as rpp

    todo = [step for step in st.steps if step.name not in progress["commands"]]
    print(f"[{st.name}] {'done' if st.name in progress['stages'] and not todo else 'to run'}"
          + (f" ({rpp.time_left_text(plan, progress, st.steps)})" if st.steps else ""))
    for step in st.steps:
        print(f"  {'(done) ' if step.name in progress['commands'] else ''}{_shown(step)}")


def _reproduce_parallel(args: argparse.Namespace, cfg, plan: list, stages: list, progress: dict,
                        seconds_left=None) -> list | int:
    """`--gpus N` (`--steps-per-gpu K`, `--runs-per-process K`): every step of `stages` not done (training seed `--seed`'s alone in the seeded
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
        gpus = rr.gpu_slots(args.gpus, args.steps_per_gpu)
    except ValueError as e:
        print(f"conav reproduce: {as_flags(str(e), args.field_flags)}", file=sys.stderr)
        return 2
    import jax

    jax.config.update("jax_platforms", "cpu")  # this process runs no program: its GPUs are the steps'
    todo = []
    for st in work:
        seed = rpp.stage_seed(st, args.seed)
        todo += [step for step in st.steps if step.name not in progress["commands"] and seed in (None, step.seed)]
    each = f" ({args.steps_per_gpu} each)" if args.steps_per_gpu > 1 else ""
    print(f"{len(todo)} step(s) to run, up to {len(gpus)} at once on GPU(s) {', '.join(dict.fromkeys(gpus))}{each}",
          flush=True)
    t0 = time.perf_counter()
    digest = rr.save_config(cfg)  # each step's process plans from it, and runs its step by name
    rc, waiting = rr.run_parallel(plan, todo, cfg.out, progress, gpus,
                                  lambda steps: rr.child_command(cfg.out, digest, steps, args.compile_cache),
                                  seconds_left=seconds_left, together=args.runs_per_process)
    done, needs = set(progress["commands"]), rpp.prerequisites(plan)
    expected = rpp.expected_seconds(plan, progress)
    for step in waiting:
        if rc or not needs[step.name] <= done or seconds_left is None:
            print(f"{'not started after the failure' if rc else 'waits for the runs it reads'}: {step.name}")
        else:
            print(rpp.for_want_of_time(step, expected, seconds_left()))
    for st in work:
        keys = [step.name for step in st.steps]
        if all(k in progress["commands"] for k in keys):
            progress["stages"][st.name] = round(sum(rpp.step_seconds(progress, k) for k in keys), 1)
    rpp.write_progress(cfg.out, progress)
    print(f"{len(todo) - len(waiting)} step(s) ended in {time.perf_counter() - t0:.0f} s", flush=True)
    if rc:
        print(f"conav reproduce: a step failed (exit {rc}); its log is named above", file=sys.stderr)
        return rc
    return [st for st in stages if st.name in ("tables", "pack")]

