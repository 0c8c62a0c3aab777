"""What a `conav reproduce` step is and how one runs: a Python call of a library function (the
one the matching `conav` command calls) with declared keyword arguments, the directories it reads
and writes under OUT, its training seed.

A plan (eval.cli.reproduce_plan) holds steps -> `run_step` imports the function of the step's kind
(STEP_KINDS), adds this process's device mesh where the function takes one, and calls it; the
runners (eval.cli.reproduce_run) call `run_step` in this process or in a process of a step's own.
"""

from __future__ import annotations

import dataclasses
import importlib
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

@dataclass(frozen=True)
class StepKind:
    """A kind of step: the library function its steps call ("module:function", imported when one
    runs), whether that takes this process's device mesh (every visible device; `--gpus`
    gives each process one) and, where several steps of the kind can run as one call, the
    function that runs them so (`together`: its keywords those of `function`, each of `per_step`
    (keyword, its list's keyword) given as the list of the steps' values)."""

    function: str
    mesh: bool = False
    together: str | None = None
    per_step: tuple[tuple[str, str], ...] = ()


# The kinds of step a plan holds, by the name a step's identity starts with.
STEP_KINDS = {
    "generate": StepKind("conav_jax.data.episodes:generate_dataset"),
    "train intention": StepKind("conav_jax.train.intention:train_intention_from_data", mesh=True),
    "train trajectory": StepKind("conav_jax.train.trajectory:train_trajectory_from_data", mesh=True),
    "train objectnav": StepKind("conav_jax.train.goalnav:train_objectnav_from_data", mesh=True),
    "train imagenav": StepKind("conav_jax.train.goalnav:train_imagenav_from_data", mesh=True),
    "train objectnav live": StepKind("conav_jax.train.goalnav:train_objectnav_live_from_data"),
    "train policy": StepKind("conav_jax.train.policy:train_policy_from_data", mesh=True),
    # Seeds of one live configuration train as one program; evaluations of one data, split and
    # agents run in one process, which loads the env once and shares compiled sweeps.
    "train live": StepKind("conav_jax.train.live:train_live_from_data",
                           together="conav_jax.train.live:train_live_seeds_from_data",
                           per_step=(("out_dir", "out_dirs"), ("live", "lives"))),
    "eval": StepKind("conav_jax.eval.sweep:run_eval", together="conav_jax.eval.sweep:run_evals",
                     per_step=(("out", "outs"), ("checkpoint", "checkpoints"))),
    "copy": StepKind("conav_jax.eval.cli.reproduce_steps:copy_run"),  # DAgger continues a copy of the BC run
}


@dataclass(frozen=True)
class Call:
    """A step's work: the library function of its `kind` (STEP_KINDS) called with `kwargs`, the
    function's keyword arguments: frozen config dataclasses, paths (str) and plain values (never
    changed once planned: steps compare by them)."""

    kind: str
    kwargs: dict

    def __post_init__(self):
        if self.kind not in STEP_KINDS:
            raise ValueError(f"unknown Call.kind {self.kind!r}; choose from {', '.join(STEP_KINDS)}")


@dataclass(frozen=True)
class Step:
    """One unit of work, declared: its `call`, the directory it `writes` and those it `reads`
    (relative to OUT), and the training `seed` it belongs to (None: every seed's)."""

    call: Call
    writes: str
    reads: tuple[str, ...] = ()
    seed: int | None = None

    @property
    def name(self) -> str:
        """The step's identity (in progress.json, for `--gpus` processes): its kind and the
        directory it writes, e.g. "train policy runs/bc_all_s0"."""
        return f"{self.call.kind} {self.writes}"

    @property
    def is_copy(self) -> bool:
        return self.call.kind == "copy"


@dataclass(frozen=True)
class Stage:
    """One stage: its steps, in order, and the files that show it is done."""

    name: str
    steps: tuple[Step, ...]
    outputs: tuple[Path, ...] = field(default=())


def step_function(kind: str) -> Callable:
    """The library function steps of `kind` call."""
    module, name = STEP_KINDS[kind].function.split(":")
    return getattr(importlib.import_module(module), name)


def together_function(kind: str) -> Callable:
    """The library function that runs several steps of `kind` as one call (StepKind.together)."""
    if STEP_KINDS[kind].together is None:
        raise ValueError(f"steps of kind {kind!r} run one at a time")
    module, name = STEP_KINDS[kind].together.split(":")
    return getattr(importlib.import_module(module), name)


def run_step(step: Step) -> Any:
    """Run `step` in this process: its kind's function called with its keywords (and with the
    mesh of every visible device where it takes one); what the function returns. JAX's
    in-memory caches are cleared first, as a fresh process would start: a step that reuses a
    function traced by an earlier one lowers to a program of other function names, whose
    compile-cache key then misses on the next run."""
    kind = STEP_KINDS[step.call.kind]
    extra = {}
    if not step.is_copy:
        import jax

        jax.clear_caches()
    if kind.mesh:
        from conav_jax.parallel import make_mesh

        extra["mesh"] = make_mesh()
    return step_function(step.call.kind)(**step.call.kwargs, **extra)


def alike(first: Step, other: Step) -> bool:
    """Whether two steps do the same work but for their seed: one kind, keywords equal but for its
    `per_step` ones (the directory each writes, its run), a config among those equal but for its
    seed (live runs: seeds of one configuration; evaluations: runs of one agent). What one's
    recorded time says of the other's."""
    kind = STEP_KINDS[first.call.kind]
    if first.call.kind != other.call.kind:
        return False
    a, b = dict(first.call.kwargs), dict(other.call.kwargs)
    if a.keys() != b.keys() or not {one for one, _ in kind.per_step} <= a.keys():
        return False
    for one, _ in kind.per_step:
        x, y = a.pop(one), b.pop(one)
        if dataclasses.is_dataclass(x):  # a config: the same but for its seed
            unseeded = [dataclasses.replace(c, seed=0) if hasattr(c, "seed") else c for c in (x, y)]
            if unseeded[0] != unseeded[1]:
                return False
    return a == b


def joinable(first: Step, other: Step) -> bool:
    """Whether `other` can run in one call with `first` (`run_together`): two `alike` steps of a
    kind with a `together` function, each writing a directory of its own."""
    return STEP_KINDS[first.call.kind].together is not None and first.writes != other.writes and alike(first, other)


def run_together(steps: list[Step]) -> Any:
    """Run `steps` in this process: one alone as `run_step` does; several `joinable` ones as one
    call of their kind's `together` function (live runs of one configuration but their seeds:
    train.live.train_live_seeds, one compiled program; evaluations: eval.sweep.run_evals, one
    env and shared compiled sweeps). ValueError for steps that cannot be joined."""
    if len(steps) == 1:
        return run_step(steps[0])
    if not steps or not all(joinable(steps[0], step) for step in steps[1:]):
        raise ValueError(f"steps that differ in more than their runs cannot run as one call: "
                         f"{', '.join(step.name for step in steps)}")
    import jax

    jax.clear_caches()  # as run_step
    per_step = dict(STEP_KINDS[steps[0].call.kind].per_step)
    kwargs = {k: v for k, v in steps[0].call.kwargs.items() if k not in per_step}
    per_step = {many: [step.call.kwargs[one] for step in steps] for one, many in per_step.items()}
    return together_function(steps[0].call.kind)(**kwargs, **per_step)


def copy_run(source: str, target: str) -> None:
    """A copy step: the run directory `source` copied to `target`, unless the target exists."""
    if not Path(target).exists():
        shutil.copytree(source, target)


def call_text(call: Call) -> str:
    """`call` as Python, for people: the function and its keywords, each config by the fields
    that differ from their defaults."""
    args = ", ".join(f"{k}={_value_text(v)}" for k, v in call.kwargs.items())
    return f"{STEP_KINDS[call.kind].function.split(':')[1]}({args})"


def _value_text(value) -> str:
    if not dataclasses.is_dataclass(value):
        return repr(value)
    changed = [f"{f.name}={_value_text(getattr(value, f.name))}" for f in dataclasses.fields(value)
               if f.default is dataclasses.MISSING or getattr(value, f.name) != f.default]
    return f"{type(value).__name__}({', '.join(changed)})"
