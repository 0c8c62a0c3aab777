"""`conav reproduce`'s runners: a step run in this process, its time recorded, or several at once,
each in a process of its own on one GPU that runs the step by name (`main`: the plan made again
from the run's configuration stored under OUT), in the order of the plan's one dependency graph
(eval.cli.reproduce_progress prerequisites); the pack that carries a run's progress and the
checkpoints still needed to a fresh machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from conav_jax.eval.cli.reproduce_plan import ReproduceConfig, plan_stages
from conav_jax.runs import LOG_FILE
from conav_jax.eval.cli.reproduce_progress import (PROGRESS_FILE, by_dependents, expected_seconds, fits_in,
                                                   join_progress, prerequisites, read_progress, record_step,
                                                   write_progress)
from conav_jax.eval.cli.reproduce_steps import Stage, Step, joinable, run_step, run_together

# A pack's default size: what a fresh machine can be handed with the working tree.
PACK_LIMIT_BYTES = 60 * 2**20
# Under OUT: each run's ReproduceConfig (all but OUT), by digest, that its steps' processes plan
# from; runs of several variants on one OUT keep one each.
CONFIGS_DIR = "configs"


def run_here(step: Step, out: Path, progress: dict) -> None:
    """Run `step` in this process (`run_step`), its wall time recorded in `progress` (saved): as
    done when it returns, as cut when it raises (failed, interrupted: SIGTERM raised as
    KeyboardInterrupt), the exception then raised again."""
    t0, ended = time.perf_counter(), False
    try:
        run_step(step)
        ended = True
    finally:
        record_step(progress, step, time.perf_counter() - t0, ended)
        write_progress(out, progress)


# -- several steps at once, one process each ---------------------------------------------------------


def save_config(cfg: ReproduceConfig) -> str:
    """Store `cfg` but its OUT as OUT/configs/DIGEST.json, for the processes that run its steps
    by name (`child_command`); returns DIGEST, the first 16 hex digits of the record's sha256."""
    from conav_jax.data.arrayio import json_bytes, save_json

    record = {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg) if f.name != "out"}
    digest = hashlib.sha256(json_bytes(record)).hexdigest()[:16]
    path = Path(cfg.out) / CONFIGS_DIR / f"{digest}.json"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        save_json(path, record)
    return digest


def load_config(out: Path, digest: str) -> ReproduceConfig:
    """The ReproduceConfig `save_config` stored in OUT as `digest`."""
    path = Path(out) / CONFIGS_DIR / f"{digest}.json"
    if not path.is_file():
        raise FileNotFoundError(f"no run configuration {path}: `conav reproduce --gpus N` stores it before its first step")
    record = json.loads(path.read_text())
    return ReproduceConfig(out=Path(out), **{k: tuple(v) if isinstance(v, list) else v for k, v in record.items()})


def find_step(plan: list[Stage], name: str) -> Step:
    """The step of `plan` named `name`; ValueError naming one it has where there is none."""
    steps = {step.name: step for st in plan for step in st.steps}
    if name not in steps:
        raise ValueError(f"the plan has no step {name!r}; `conav reproduce --dry-run` lists them "
                         f"(e.g. {next(iter(steps))!r})")
    return steps[name]


def child_command(out: Path, digest: str, steps: list[Step], compile_cache: str | None = None) -> list[str]:
    """The process `run_parallel` runs `steps` in: `main`, the steps by name in the plan of the
    run's stored configuration `digest` (`save_config`), several as one call
    (reproduce_steps.run_together); `compile_cache` as `conav --compile-cache`. The process
    does not look in its working directory for modules (`-P`): started in a checkout of this
    repository, the source tree's `conav_jax/` would shadow the installed package."""
    cache = ["--compile-cache", compile_cache] if compile_cache else []
    names = [arg for step in steps for arg in ("--step", step.name)]
    return [sys.executable, "-P", "-m", "conav_jax.eval.cli.reproduce_run", "--out", str(out), "--config", digest, *cache,
            *names]


def main(argv: list[str] | None = None) -> int:
    """One step of a `conav reproduce` run (or several joined), by name, in this process (what each process of
    `--gpus N` runs); it records nothing: the runner that started it does."""
    from conav_jax.compile_cache import enable_compile_cache

    parser = argparse.ArgumentParser(prog="python -m conav_jax.eval.cli.reproduce_run", description=main.__doc__)
    parser.add_argument("--out", required=True, help="the run's output directory")
    parser.add_argument("--config", required=True, metavar="DIGEST", help="the run's configuration, OUT/configs/DIGEST.json")
    parser.add_argument("--step", required=True, action="append", metavar="NAME",
                        help="the step, as progress.json names it (e.g. 'train policy runs/bc_all_s0'); several: run "
                        "as one call (live runs of one configuration but their seeds)")
    parser.add_argument("--compile-cache", default=None, metavar="DIR|off", help="as `conav --compile-cache`")
    args = parser.parse_args(argv)
    enable_compile_cache(args.compile_cache)
    plan = plan_stages(load_config(Path(args.out), args.config))
    run_together([find_step(plan, name) for name in args.step])
    return 0


def visible_gpus() -> list[str] | None:
    """The GPU ids a process started here may use: CUDA_VISIBLE_DEVICES's, else those `nvidia-smi -L`
    lists; None where neither says (no NVIDIA driver: a CPU machine)."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return [d.strip() for d in visible.split(",") if d.strip()]
    if shutil.which("nvidia-smi") is None:
        return None
    listed = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True).stdout
    return [str(i) for i, _ in enumerate(line for line in listed.splitlines() if line.startswith("GPU "))]


def gpu_slots(gpus: int, steps_per_gpu: int = 1) -> list[str]:
    """The GPU of each step that may run at once: the first `gpus` of `visible_gpus` (0..gpus-1
    on a machine without a driver, where the steps run on the CPU), each `steps_per_gpu` times
    (a GPU one step leaves partly idle, as while it compiles, runs another). ValueError when
    fewer are visible (a process given a GPU that does not exist would run on the CPU)."""
    if gpus < 1:
        raise ValueError(f"gpu_slots.gpus must be at least 1, got {gpus}")
    if steps_per_gpu < 1:
        raise ValueError(f"gpu_slots.steps_per_gpu must be at least 1, got {steps_per_gpu}")
    ids = visible_gpus()
    if ids is not None and len(ids) < gpus:
        raise ValueError(f"gpu_slots.gpus {gpus}: {len(ids)} GPU(s) visible ({', '.join(ids) or 'none'})")
    ids = ids[:gpus] if ids is not None else [str(i) for i in range(gpus)]
    return [gpu for _ in range(steps_per_gpu) for gpu in ids]


def _log_name(step: Step) -> str:
    return step.name.replace(" ", "_").replace("/", "_") + ".log"


def _tail(path: Path, lines: int = 15) -> str:
    text = path.read_text(errors="replace").splitlines() if path.exists() else []
    return "\n".join("    " + line for line in text[-lines:])


def run_parallel(plan: list[Stage], todo: list[Step], out: Path, progress: dict, gpus: list[str],
                 command: Callable[[list[Step]], list[str]], say=None, poll_seconds: float = 0.1,
                 seconds_left: Callable[[], float] | None = None, together: int = 1) -> tuple[int, list[Step]]:
    """Run `todo` (steps of `plan`) up to len(gpus) at once (`gpus`: a GPU id per step that may
    run at once, `gpu_slots`), each in a process of its own
    (`command(steps)`: the command line that runs those steps, by name: `child_command`) that
    sees one GPU (CUDA_VISIBLE_DEVICES), the least busy one free, and logs to OUT/logs/; where
    steps share a GPU, each process takes its memory as it needs it instead of most of the GPU
    at its start (XLA_PYTHON_CLIENT_PREALLOCATE=false, unless the environment sets JAX's memory
    variables; each such step's record says how many ran on its GPU at most: "shared"), a step starting once its
    `prerequisites` are done (in `by_dependents` order); copies run here. Each step's wall time
    goes into `progress` (saved) as it ends, a failed or stopped one's under "cut". After a
    failure no new step starts and those running finish. An interrupt (SIGTERM raised as
    KeyboardInterrupt) stops every process, records their time as cut and is raised again.
    With `seconds_left` (the sitting's time left), a step starts only while it `fits_in` it
    (its expected time, with its run's evaluations, from this OUT's records); those running
    finish. `together` > 1: a step starting takes with it up to `together` - 1 more that are
    ready and `joinable` with it (live runs of its configuration, other seeds; evaluations of one
    agent), while the group would fit the time left (as a group of its size took in this OUT,
    else run one by one), run as one call in its process (reproduce_steps.run_together), each
    recorded with the process's time and the group's size; the
    process logs to the first one's log, the others' say where. Returns (0 or the first
    failure's exit code, the steps not started: waiting for prerequisites not run here, or for
    want of time)."""
    say = say or (lambda message: print(message, flush=True))
    needs = prerequisites(plan)
    done = set(progress["commands"])
    pending, running, free, failed = by_dependents(todo, needs), {}, list(gpus), 0
    sharing = {}  # each running process's most processes on its GPU at once
    expected = expected_seconds(plan, progress) if seconds_left is not None else None
    (out / "logs").mkdir(parents=True, exist_ok=True)
    child_env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    shared = len(set(gpus)) < len(gpus)
    if shared and not any(k.startswith("XLA_PYTHON_CLIENT_") for k in os.environ):
        child_env["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"

    def busy(gpu: str) -> int:
        return sum(g == gpu for _, g, _, _ in running.values())

    def ready(step: Step) -> bool:
        return needs[step.name] <= done and (expected is None or fits_in([step], expected, seconds_left()))

    def group_fits(group: list[Step]) -> bool:
        """Whether the group fits the time left, as a group of its size took here before, else
        were its steps run one after another (the bound that never overruns)."""
        return expected is None or fits_in(group, expected, seconds_left())

    def record(step: Step, seconds: float, ok: bool, together: int = 1, shared: int = 1) -> None:
        record_step(progress, step, seconds, ok, together, shared)
        if ok:
            done.add(step.name)
        write_progress(out, progress)

    try:
        while pending or running:
            started = True
            while started and not failed:  # a copy done may let others start
                started = False
                for step in list(pending):
                    if step not in pending or (not step.is_copy and not free) or not ready(step):
                        continue
                    pending.remove(step)
                    started = True
                    if step.is_copy:
                        t0 = time.perf_counter()
                        run_step(step)
                        record(step, time.perf_counter() - t0, True)
                        say(f"{step.name} done (from {step.call.kwargs['source']})")
                        continue
                    gpu = min(free, key=lambda g: (busy(g), gpus.index(g)))
                    free.remove(gpu)
                    group = [step]
                    for other in list(pending):
                        if len(group) < together and joinable(step, other) and ready(other) \
                                and group_fits(group + [other]):
                            group.append(other)
                            pending.remove(other)
                    log = out / "logs" / _log_name(step)
                    argv = command(group)
                    for other in group[1:]:
                        with open(out / "logs" / _log_name(other), "a") as f:
                            f.write(f"# {other.name}\n# run with {step.name}, in one process: its log is {log.name}\n")
                    with open(log, "a") as f:
                        f.write("".join(f"# {s.name}\n" for s in group) + f"$ {shlex.join(argv)}\n")
                        f.flush()
                        proc = subprocess.Popen(argv, stdout=f,
                                                stderr=subprocess.STDOUT,
                                                env={**child_env, "CUDA_VISIBLE_DEVICES": gpu})
                    running[proc] = (group, gpu, log, time.perf_counter())
                    for other, (_, other_gpu, _, _) in running.items():  # its GPU's processes now share it
                        if other_gpu == gpu:
                            sharing[other] = max(sharing.get(other, 1), busy(gpu))
                    say(f"[gpu {gpu}] {' + '.join(s.name for s in group)} started (log {log})")
            if not running:
                break  # what is left waits for steps not run here
            ended = [proc for proc in running if proc.poll() is not None]
            if not ended:
                time.sleep(poll_seconds)
                continue
            for proc in ended:
                group, gpu, log, t0 = running.pop(proc)
                seconds = time.perf_counter() - t0
                shared = sharing.pop(proc, 1)
                for step in group:
                    record(step, seconds, proc.returncode == 0, len(group), shared)
                free = sorted(free + [gpu], key=gpus.index)
                names = " + ".join(step.name for step in group)
                if proc.returncode == 0:
                    say(f"[gpu {gpu}] {names} done in {seconds:.0f} s "
                        f"({len(done & set(needs))} done, {len(running)} running, {len(pending)} to run)")
                else:
                    failed = failed or proc.returncode
                    say(f"[gpu {gpu}] {names} failed (exit {proc.returncode}) after {seconds:.0f} s; "
                        f"no new step starts. The end of {log}:\n{_tail(log)}")
    except BaseException:
        for proc in running:
            proc.terminate()
        deadline = time.perf_counter() + 30.0
        for proc, (group, gpu, log, t0) in running.items():
            try:
                proc.wait(timeout=max(0.1, deadline - time.perf_counter()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            for step in group:
                record(step, time.perf_counter() - t0, False)
            say(f"[gpu {gpu}] {' + '.join(step.name for step in group)} stopped")
        raise
    return failed, pending


# -- pack ------------------------------------------------------------------------------------------


def _pending_runs(cfg: ReproduceConfig, progress: dict) -> tuple[set[Path], set[Path]]:
    """(the runs that steps still to run read, the runs they write); the data are regenerated."""
    out = Path(cfg.out)
    read, written = set(), set()
    for step in (x for st in plan_stages(cfg) for x in st.steps if x.name not in progress["commands"]):
        read.update(out / r for r in step.reads if r != "data")
        written.add(out / step.writes)
    written.discard(out / "data")
    return read, written


def _record_members(out: Path) -> list[Path]:
    """The progress record, every evaluation's outputs (val's, and minival's where made), results
    and tables, and the records of how each run went: every run's training log (a fresh
    machine that trains a run again drops its stale log: conav_jax.runs.resume) and every step's
    process log."""
    evals = sorted(d for d in out.glob("eval*") if d.is_dir())
    members = [out / PROGRESS_FILE] + [p for d in evals for p in sorted(d.rglob("*.json")) + sorted(d.rglob("*.md"))]
    members += sorted(out.glob("results*.json")) + sorted(out.glob("tables*.md"))
    members += sorted((out / "runs").rglob(LOG_FILE)) + sorted((out / "logs").glob("*.log"))
    return list(dict.fromkeys(p for p in members if p.exists()))


def _run_members(cfg: ReproduceConfig, progress: dict) -> dict[Path, list[Path]]:
    """Each run a step still to run reads, with a checkpoint: its latest checkpoint (its log is a
    record: `_record_members`)."""
    from conav_jax.checkpoints import latest_checkpoint

    found = {}
    for run in sorted(set.union(*_pending_runs(cfg, progress))):
        ckpt = latest_checkpoint(run)
        if ckpt is not None:
            found[run] = [ckpt]
    return found


def pack_members(cfg: ReproduceConfig, progress: dict) -> list[Path]:
    """What a fresh machine needs to continue: the progress record, every evaluation's outputs,
    results and tables, and the latest checkpoint of every run a stage still to run reads (the
    data are regenerated from their seed; a training round cut short restarts from the run's
    last finished round, or from `first_round_checkpoints`' when the pack carries them)."""
    return _record_members(Path(cfg.out)) + [p for files in _run_members(cfg, progress).values() for p in files]


def first_round_checkpoints(cfg: ReproduceConfig, progress: dict) -> list[tuple[Path, ...]]:
    """(the latest checkpoint within round 0, the run's and the round's logs) of every run still
    to train that has finished no round (a BC run cut short): on a fresh machine the run records
    round 0 again (the teacher's rollouts: same data, same records) and goes on from that update.
    A later round's checkpoints never travel: its data came from a policy that no longer exists."""
    from conav_jax.checkpoints import latest_checkpoint

    found = []
    for run in sorted(_pending_runs(cfg, progress)[1]):
        ckpt = latest_checkpoint(run / "round_0")
        if ckpt is not None and latest_checkpoint(run) is None:
            found.append((ckpt, *(p for p in (run / "log.jsonl", ckpt.parent / "log.jsonl") if p.exists())))
    return found


# Why a checkpoint was left out of a pack, for each kind.
TRAINS_AGAIN = "its run's record dropped from the pack: that run trains again from its start"
FIRST_ROUND_AGAIN = "continued from this pack, that run starts its first round again"


def write_pack(cfg: ReproduceConfig, progress: dict,
               limit_bytes: int | None = None) -> tuple[Path, int, list[tuple[Path, str]]]:
    """OUT/pack.tar (atomically), paths relative to OUT: the records (progress, evaluations,
    results, tables), then the checkpoints of the runs still read (`pack_members`), smallest
    first, and the runs cut in their first round (`first_round_checkpoints`), each while the pack
    stays within `limit_bytes` (default PACK_LIMIT_BYTES: a channel that carries less, a smaller
    one). A run read but left out (a policy trained, its evaluation not
    run) has its training record dropped from the packed progress, so a fresh machine trains it
    again instead of reading a run it lacks. Returns (the pack, its bytes, (each checkpoint left
    out, why)). ValueError when the records alone would exceed the limit, naming the largest."""
    import io
    import os
    import tarfile
    import tempfile

    limit = PACK_LIMIT_BYTES if limit_bytes is None else limit_bytes
    if limit <= 0:
        raise ValueError(f"write_pack.limit_bytes must be positive, got {limit}")
    out = Path(cfg.out)
    size = lambda files: sum(p.stat().st_size for p in files)  # noqa: E731
    members = _record_members(out)
    total = size(members)
    if total > limit:
        big = sorted(members, key=lambda p: -p.stat().st_size)[:5]
        raise ValueError(f"the pack would hold {total / 2**20:.1f} MiB (limit {limit / 2**20:.1f} MiB); "
                         "largest: " + ", ".join(f"{p.relative_to(out)} {p.stat().st_size / 2**20:.1f} MiB" for p in big))
    left_out, dropped = [], set()
    for run, files in sorted(_run_members(cfg, progress).items(), key=lambda item: (size(item[1]), str(item[0]))):
        if total + size(files) <= limit:
            members += files
            total += size(files)
        else:
            left_out.append((files[0], TRAINS_AGAIN))
            dropped.add(str(run.relative_to(out)))
    for files in first_round_checkpoints(cfg, progress):
        files = [p for p in files if p not in members]  # its logs are records, packed already
        if total + size(files) <= limit:
            members += files
            total += size(files)
        else:
            left_out.append((files[0], FIRST_ROUND_AGAIN))
    # The record as saved (write_progress merges every process's), less the runs left out.
    saved = out / PROGRESS_FILE
    packed = json.loads(saved.read_text()) if saved.exists() else json.loads(json.dumps(progress))
    for stage in plan_stages(cfg):
        for step in stage.steps:
            if step.writes in dropped:
                packed["commands"].pop(step.name, None)
                packed["stages"].pop(stage.name, None)
    record = json.dumps(packed, indent=1).encode()
    fd, tmp = tempfile.mkstemp(prefix=".pack.", suffix=".tmp", dir=out)
    os.close(fd)
    with tarfile.open(tmp, "w") as tar:
        info = tarfile.TarInfo(PROGRESS_FILE)
        info.size, info.mtime = len(record), int(time.time())
        tar.addfile(info, io.BytesIO(record))
        for p in members:
            if p != out / PROGRESS_FILE:
                tar.add(p, arcname=str(p.relative_to(out)))
    os.replace(tmp, out / "pack.tar")
    return out / "pack.tar", total, left_out


def unpack(pack: Path, out: Path) -> list[str]:
    """Unpack a pack into OUT (a fresh machine continuing a run); the member names. Into an OUT
    that holds records already (another pack unpacked, or steps run here), the pack's records
    join them (`join_progress`: runs made on several machines at once, one OUT again), its files
    OUT holds already stay OUT's (a predictor both machines trained: the one OUT's evaluations
    read), and its results and tables, which the `tables` stage makes from all of them, are left
    out. ValueError for a pack of another configuration (nothing is unpacked then)."""
    import tarfile

    out, pack = Path(out), Path(pack)
    if not pack.is_file():
        raise FileNotFoundError(f"no pack at {pack}")
    try:
        tar = tarfile.open(pack)
    except tarfile.TarError as e:
        raise ValueError(f"{pack} is not a pack written by `conav reproduce --stage pack`: {e}") from e
    out.mkdir(parents=True, exist_ok=True)
    with tar:
        names = tar.getnames()
        bad = [n for n in names if n.startswith("/") or ".." in Path(n).parts]
        if bad:
            raise ValueError(f"{pack}: unsafe member paths {bad[:3]}")
        if (out / PROGRESS_FILE).is_file() and PROGRESS_FILE in names:
            try:
                joined = join_progress(read_progress(out), json.load(tar.extractfile(PROGRESS_FILE)))
            except ValueError as e:
                raise ValueError(f"{pack} cannot join {out}: {e}") from e
            derived = lambda name: "/" not in name and name.startswith(("results", "tables"))  # noqa: E731
            members = [m for m in tar.getmembers()
                       if m.name != PROGRESS_FILE and not derived(m.name) and not (out / m.name).exists()]
            tar.extractall(out, members=members)
            write_progress(out, joined)
            return [m.name for m in members] + [PROGRESS_FILE]
        tar.extractall(out)
    return names


if __name__ == "__main__":
    sys.exit(main())
