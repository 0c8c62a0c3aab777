"""What `conav reproduce` has done and what it runs next: progress.json (each step's record by
its identity, `Step.name`; the OUT directory's one configuration) and the plan's one dependency
graph (`prerequisites`, from the steps' declared reads and writes), which the command line's
runner in this process and `eval.cli.reproduce_run`'s processes share.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Callable

from conav_jax.eval.cli.reproduce_plan import BUDGET_OVERRIDES, ReproduceConfig, resolution_name
from conav_jax.eval.cli.reproduce_steps import Stage, Step, alike


# The steps (by name, under "commands") and stages done, with their wall times (s), under "cut"
# the time of attempts cut short (a step's summed over its attempts; it counts in its stage's
# time), under "joined" how many steps ran in the process of each step that ran with others
# (its time under "commands" is that process's), and under "shared" the most processes that ran
# at once on the GPU of each step that shared its GPU (`--steps-per-gpu`: its time is not a lone
# process's, so plans go by it only where no lone time exists).
PROGRESS_FILE = "progress.json"
# The layout of progress.json. 1 (unmarked): records keyed by the command line, OUT written as
# "OUT"; 2: keyed by step name, its kind and the directory it writes (`upgrade_progress` maps
# the one onto the other).
RUN_FORMAT = 2


def read_progress(out: Path) -> dict:
    path = Path(out) / PROGRESS_FILE
    if path.is_file():
        return json.loads(path.read_text())
    return {"run_format": RUN_FORMAT, "commands": {}, "stages": {}}


def upgrade_progress(progress: dict, plan: list[Stage], out: Path) -> list[str]:
    """Bring `progress` of an OUT made before RUN_FORMAT 2 (records keyed by command lines) to
    step names, in place: each record moves to its command's step name (`command_step_name`)
    where a planned step has it. Returns the old records no planned step matches (dropped: a
    variant not planned now; its runs resume from their checkpoints when it is planned again).
    ValueError for a directory written by a newer format."""
    made = progress.get("run_format", 1)
    if made > RUN_FORMAT:
        raise ValueError(f"{out}: progress.json has run format {made}, newer than this version's {RUN_FORMAT}: "
                         "continue it with the version that made it, or use another output directory")
    if made == RUN_FORMAT:
        return []
    planned = {s.name for st in plan for s in st.steps}
    dropped = []
    for record in ("commands", "cut"):
        entries = progress.get(record, {})
        names = {k: command_step_name(k) for k in entries}
        dropped += [k for k, name in names.items() if name not in planned]
        progress[record] = {name: entries[k] for k, name in names.items() if name in planned}
    progress["run_format"] = RUN_FORMAT
    return dropped


def command_step_name(command: str) -> str | None:
    """The step name of a RUN_FORMAT 1 record's key, a `conav` command line with OUT written as
    "OUT": its command words ("train policy", "eval", ...; "@copy SRC DST" a copy) and the
    directory it writes, after `--out` (a copy's DST), relative to OUT; None for another line."""
    words = command.split(" ")
    if words[0] == "@copy" and len(words) == 3:
        kind, target = "copy", words[2]
    elif "--out" in words[:-1]:
        kind, target = " ".join(words[:2]) if words[0] == "train" else words[0], words[words.index("--out") + 1]
    else:
        return None
    return f"{kind} {target.removeprefix('OUT/')}" if target.startswith("OUT/") else None


# What one OUT directory holds one of: its runs and evaluations are of these (progress.json
# keeps them from the first run on; directories made before it kept them are not checked).
OUT_FIELDS = ("preset", "resolution", "encoder", "mirror", "seen_objects", "trainer") + BUDGET_OVERRIDES  # not `rows`
# Fields a directory's record may lack, made before they existed: they were off then.
_OUT_FIELDS_ADDED = {"mirror": False, "seen_objects": False, "trainer": "offline",
                     **{name: None for name in BUDGET_OVERRIDES}}


def check_out(progress: dict, cfg: ReproduceConfig) -> None:
    """Record `cfg`'s OUT_FIELDS in `progress`, or ValueError naming each that differs from what
    the directory was made with (a run of another resolution or encoder would fail later, at
    its first resumed run, or mix two configurations in one table)."""
    mine = {k: resolution_name(cfg) if k == "resolution" else getattr(cfg, k) for k in OUT_FIELDS}
    made = progress.setdefault("config", mine)
    for k, before in _OUT_FIELDS_ADDED.items():
        made.setdefault(k, before)
    shown = lambda v: {True: "on", False: "off"}.get(v, v) if isinstance(v, bool) else v  # noqa: E731
    differ = [f"ReproduceConfig.{k} {shown(made[k])} (given {shown(mine[k])})"
              for k in OUT_FIELDS if k in made and made[k] != mine[k]]
    if differ:
        raise ValueError(f"{cfg.out} was made with {', '.join(differ)}: give those, or another --out")


# What write_progress merges: each process's own records laid over the file's.
PROGRESS_RECORDS = ("commands", "cut", "stages", "joined", "shared")


def write_progress(out: Path, progress: dict) -> None:
    """Save `progress` as OUT/progress.json, merged with what the file holds now: several
    `conav reproduce` processes on one OUT (another DAgger variant beside a run, say) each keep
    the others' records. `progress` takes the merged records (the file is read and written under
    a lock; an entry this process recorded wins)."""
    import fcntl

    from conav_jax.data.arrayio import save_json

    out = Path(out)
    with open(out / ".progress.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            now = read_progress(out)
            if now.get("run_format", 1) != RUN_FORMAT:  # records `upgrade_progress` has moved
                now = {}
            for record in PROGRESS_RECORDS:
                progress[record] = {**now.get(record, {}), **progress.get(record, {})}
            progress["run_format"] = RUN_FORMAT
            save_json(out / PROGRESS_FILE, progress)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def join_progress(mine: dict, theirs: dict) -> dict:
    """The records of two OUTs of one configuration made apart (on two machines at once, say) as
    one: each record's entries from both, `mine`'s where both hold one. ValueError when they were
    made with different run formats or OUT_FIELDS."""
    formats = mine.get("run_format", 1), theirs.get("run_format", 1)
    if formats[0] != formats[1]:
        raise ValueError(f"the records are of run formats {formats[0]} and {formats[1]}: continue the older "
                         "with `conav reproduce` once before joining them")
    made = mine.get("config") or {}, theirs.get("config") or {}
    differ = [f"{k} {made[0][k]} and {made[1][k]}" for k in OUT_FIELDS
              if k in made[0] and k in made[1] and made[0][k] != made[1][k]]
    if differ:
        raise ValueError(f"the records are of different runs: {', '.join(differ)}")
    joined = {**theirs, **mine}
    for record in PROGRESS_RECORDS:
        joined[record] = {**theirs.get(record, {}), **mine.get(record, {})}
    return joined


def record_step(progress: dict, step: Step, seconds: float, ended: bool, together: int = 1,
                shared: int = 1) -> None:
    """`step`'s wall time into `progress`: under "commands" when it `ended` (with, under "joined",
    the `together` steps its process ran where more than one, and under "shared" the `shared`
    processes its GPU ran at most at once where more than one), else (failed, stopped) added to
    its time under "cut"."""
    if ended:
        progress["commands"][step.name] = round(seconds, 1)
        if together > 1:
            progress.setdefault("joined", {})[step.name] = together
        if shared > 1:
            progress.setdefault("shared", {})[step.name] = shared
    else:
        cut = progress.setdefault("cut", {})
        cut[step.name] = round(cut.get(step.name, 0.0) + seconds, 1)


def step_seconds(progress: dict, name: str) -> float:
    """A finished step's share of the process time it was recorded with: the whole for a step
    that ran alone, a group's time over its size for one joined with others."""
    return progress["commands"][name] / progress.get("joined", {}).get(name, 1)


def stage_seconds(plan: list["Stage"], progress: dict) -> dict[str, float]:
    """Each stage's time: the sum of its steps' recorded wall times (`step_seconds`: a joined
    group's process counted once), with the time of their attempts cut short ("cut": failed,
    interrupted; a stage run over several calls or machines counts every part once); a stage
    without steps, its own record."""
    seconds = {}
    for st in plan:
        keys = [s.name for s in st.steps]
        done = [step_seconds(progress, k) for k in keys if k in progress["commands"]]
        done += [progress["cut"][k] for k in keys if k in progress.get("cut", {})]
        if done:
            seconds[st.name] = round(sum(done), 1)
        elif st.name in progress["stages"]:
            seconds[st.name] = progress["stages"][st.name]
    return seconds


def stage_seed(stage: Stage, seed: int | None) -> int | None:
    """The training seed whose steps `--seed` selects in `stage`: None (every step) in a stage
    without seeded steps (generate, predictors)."""
    return seed if seed is not None and any(s.seed is not None for s in stage.steps) else None


def ready_steps(plan: list[Stage], stage: Stage, seed: int | None, done: set[str]) -> tuple[list[Step], list[Step]]:
    """`stage`'s steps of training seed `seed` (every step for None) not in `done` (step names),
    split into those ready to run in order and those waiting: a step waits while one of its
    `prerequisites` is neither done nor ready before it (a DAgger run's evaluation before the
    DAgger run, a baseline's before its training)."""
    needs = prerequisites(plan)
    ready, waiting, coming = [], [], set(done)
    for st in stage.steps:
        if (seed is not None and st.seed != seed) or st.name in done:
            continue
        if needs[st.name] <= coming:
            ready.append(st)
            coming.add(st.name)
        else:
            waiting.append(st)
    return ready, waiting


# -- the dependency graph ------------------------------------------------------------------------


def prerequisites(plan: list[Stage]) -> dict[str, set[str]]:
    """The one dependency graph of the plan: each step's (by name) prerequisites, the steps before
    it in the plan that write a directory it reads or the directory it writes itself (a DAgger run
    trains in the copy of its BC run; a run cut short and its copy never run at once)."""
    found, made = {}, []  # made: (directory, name) of the steps so far, in plan order
    for st in (x for stage in plan for x in stage.steps):
        needs = {*st.reads, st.writes}
        found[st.name] = {name for d, name in made if d in needs}
        made.append((st.writes, st.name))
    return found


def by_dependents(todo: list[Step], needs: dict[str, set[str]]) -> list[Step]:
    """`todo` in the order `run_parallel` starts what is ready: the steps every seed shares (data,
    predictors, the scripted agents' evaluation) first, then seed by seed (a learned baseline's
    seed s with the CoNav rows' seed s); within those, the most steps of `todo`
    waiting on it (directly or not) first, then plan order. A BC run that a DAgger run and two
    evaluations wait for starts before a run only its evaluation waits for, and a seed's
    evaluations before the next seed's training: a sitting cut short leaves whole seeds,
    evaluated, rather than trained runs and no evaluation."""
    keys = {st.name for st in todo}
    below = {k: set() for k in keys}  # the steps of todo waiting on k
    for k in keys:
        stack = [n for n in needs[k] if n in keys]
        while stack:
            n = stack.pop()
            if k not in below[n]:
                below[n].add(k)
                stack += [m for m in needs[n] if m in keys]
    index = {st.name: i for i, st in enumerate(todo)}
    return sorted(todo, key=lambda st: (-1 if st.seed is None else st.seed, -len(below[st.name]), index[st.name]))


def expected_seconds(plan: list[Stage], progress: dict) -> Callable[..., float | None]:
    """The expected wall time of steps run as one process (one step, or `joinable` ones joined),
    to plan a sitting of limited time: the longest recorded time of finished steps `alike` the
    first (its configuration's other seeds) that ran as many to a process, on a GPU of its own
    where any did (a process that shared its GPU takes longer: "shared"), plus that of the
    evaluations that read the runs they write, reckoned the same way (a run trained and not
    evaluated is of no use to a sitting that ends, and too large to carry:
    eval.cli.reproduce_run.write_pack), read from the records as they are when asked; asked
    with `with_evaluations=False`, the steps' own time alone (to add up the steps left). One step
    with no such record goes by its alike steps however they ran (a process of several takes
    longer), else by its kind (`call.kind`: "train live", "eval", ...); a group of several with
    no record of its size, by its configuration's lone time scaled as groups of that size of
    another configuration of its kind took against that one's lone steps (the largest such
    ratio: two seeds of `all` by how a pair of `none` took against a lone `none`), else by its
    steps' times added up (the bound that never overruns). None when a step's kind has no
    finished step in this OUT (nothing to go by: it may start)."""
    by_name = {st.name: st for stage in plan for st in stage.steps}
    readers: dict[str, list[Step]] = {}
    for st in by_name.values():
        if st.call.kind == "eval":
            for run in st.reads:
                readers.setdefault(run, []).append(st)

    @functools.lru_cache(maxsize=None)  # the plan is fixed; a runner asks again at every poll
    def similar(name: str, other: str) -> bool:
        return alike(by_name[name], by_name[other])

    def lone(step: Step, recorded: list[tuple[Step, float, int, bool]]) -> float | None:
        """The longest time of `step`'s configuration's steps that ran alone, each on a GPU of its own."""
        return max((s for other, s, n, alone in recorded
                    if n == 1 and alone and other.call.kind == step.call.kind and similar(step.name, other.name)),
                   default=None)

    def longest(step: Step, together: int, recorded: list[tuple[Step, float, int, bool]]) -> float | None:
        of_kind = [(other, s, n, alone) for other, s, n, alone in recorded if other.call.kind == step.call.kind]
        like = [(s, n, alone) for other, s, n, alone in of_kind if similar(step.name, other.name)]
        if together > 1:
            sized = [(s, alone) for s, n, alone in like if n == together]
            return max([s for s, alone in sized if alone] or [s for s, _ in sized], default=None)
        alone_time = lone(step, recorded)
        if alone_time is not None:
            return alone_time
        return max([s for s, n, _ in like if n == 1] or [s for s, _, _ in like] or [s for _, s, _, _ in of_kind],
                   default=None)

    def scaled(steps: list[Step], recorded: list[tuple[Step, float, int, bool]]) -> float | None:
        """A group's time from its configuration's lone time and other configurations' groups of its size."""
        own = lone(steps[0], recorded)
        ratios = [s / base for other, s, n, alone in recorded
                  if n == len(steps) and alone and other.call.kind == steps[0].call.kind
                  and (base := lone(other, recorded))]
        return None if own is None or not ratios else own * max(ratios)

    def expected(steps: list[Step], with_evaluations: bool = True) -> float | None:
        # read at each call: the records grow as steps end
        joined, shared = progress.get("joined", {}), progress.get("shared", {})
        recorded = [(by_name[name], float(s), joined.get(name, 1), shared.get(name, 1) == 1)
                    for name, s in progress["commands"].items() if name in by_name]
        own = longest(steps[0], len(steps), recorded)
        if own is None and len(steps) > 1:
            own = scaled(steps, recorded)
        if own is None:
            if len(steps) == 1:
                return None
            alone = [expected([st], with_evaluations) for st in steps]
            return None if None in alone else sum(alone)
        if not with_evaluations:
            return own
        evals = [longest(st, 1, recorded) or 0.0 for step in steps for st in readers.get(step.writes, ())
                 if st.name not in progress["commands"]]
        return own + sum(evals)

    return expected


def time_left_text(plan: list[Stage], progress: dict, steps: list[Step]) -> str:
    """How much work `steps` still hold, for people planning sittings: how many are not done and
    their expected times added up (`expected_seconds`' own times, one process per step: the
    minutes of one device they need, one after another), with the count that has nothing to go
    by yet."""
    expected = expected_seconds(plan, progress)
    left = [step for step in steps if step.name not in progress["commands"]]
    times = [expected([step], with_evaluations=False) for step in left]
    known = [t for t in times if t is not None]
    text = f"{len(steps) - len(left)} of {len(steps)} steps done"
    if known:
        text += (f"; the {len(left)} left: about {sum(known) / 60:.0f} min one after another, at the times "
                 "recorded" + (f", {len(left) - len(known)} of them with no time to go by" if len(known) < len(left)
                               else ""))
    elif left:
        text += f"; the {len(left)} left have no time to go by"
    return text


def for_want_of_time(step: Step, expected: Callable[[list[Step]], float | None], seconds_left: float) -> str:
    """The line that says `step` was not started for want of time, with its expected and the
    time left."""
    need = expected([step])
    shown = "no time to go by" if need is None else f"expected {need:.0f} s with its run's evaluations"
    return f"not started, for want of time: {step.name} ({shown}, {max(seconds_left, 0.0):.0f} s left)"


def fits_in(steps: list[Step], expected: Callable[[list[Step]], float | None], seconds_left: float | None) -> bool:
    """Whether `steps` (one, or several joined in one process) may start with `seconds_left` of a
    sitting's time (None: no limit): when their `expected` time (with their runs' evaluations) is
    unknown or no more than what is left."""
    if seconds_left is None:
        return True
    need = expected(steps)
    return seconds_left > 0 and (need is None or need <= seconds_left)
