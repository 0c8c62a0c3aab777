"""Where a compiled program's time goes: device time of each kernel, by named scope.

`profile_program(compiled, args, scopes, out_dir)` traces a few calls of a compiled program
with `jax.profiler` (a Perfetto trace under `out_dir`), reads each device kernel's duration and
attributes it to the HLO instruction that launched it, whose metadata names the JAX scopes it
was traced under (`jax.named_scope`, the transformations: "transpose(jvp(" for a gradient). A
kernel counts toward the first of `scopes` its op name holds, "backward" marked where it runs
in a gradient. No other imports from this repository.
"""

from __future__ import annotations

import collections
import glob
import gzip
import json
import os
import re
import tempfile
from typing import Any, Callable, Sequence

import jax

UNATTRIBUTED = "unattributed"  # kernels no instruction of the program names (library calls inside CUDA graphs)
_INSTRUCTION = re.compile(r"\s*(?:ROOT )?%?([\w.\-]+) = ")
_CALLS = re.compile(r"calls=%?([\w.\-]+)")
_OP_NAME = re.compile(r'op_name="([^"]*)"')
_COMPUTATION = re.compile(r"\s*(?:ENTRY )?%?([\w.\-]+) [^=]*\{\s*$")


def _key(name: str) -> str:
    """Kernel and instruction names compare with '.' and '-' read as '_' (kernels are named
    after the instruction, '_' for '.')."""
    return name.replace(".", "_").replace("-", "_")


def hlo_op_names(hlo_text: str) -> dict[str, str]:
    """Each instruction of a compiled program's HLO text -> the op name in its metadata; a
    fusion without one takes the most common of the instructions it calls."""
    names: dict[str, str] = {}
    calls: dict[str, str] = {}
    inside: dict[str, list[str]] = collections.defaultdict(list)
    computation = None
    for line in hlo_text.splitlines():
        inst = _INSTRUCTION.match(line)
        if inst is None:
            header = _COMPUTATION.match(line)
            if header:
                computation = header.group(1)
            continue
        called = _CALLS.search(line)
        if called:
            calls[_key(inst.group(1))] = called.group(1)
        op = _OP_NAME.search(line)
        if op:
            names[_key(inst.group(1))] = op.group(1)
            if computation:
                inside[computation].append(op.group(1))
    for inst, computation in calls.items():
        if inst not in names and inside.get(computation):
            names[inst] = collections.Counter(inside[computation]).most_common(1)[0][0]
    return names


def scope_of(op_name: str, scopes: Sequence[str]) -> str:
    """The first of `scopes` that is a component of `op_name`, bare or under transformations
    ("vmap(observe)"), "other" if none; " (backward)" added where the op runs in a gradient."""
    parts = op_name.split("/")
    scope = next((s for s in scopes if any(re.fullmatch(rf"(?:[\w]+\()*{re.escape(s)}\)*", p) for p in parts)),
                 "other")
    return scope + (" (backward)" if "transpose(jvp(" in op_name else "")


def _kernel_events(trace_dir: str) -> list[dict]:
    """The Perfetto trace's complete events on device timelines; where it has none (a CPU
    run), the host's XLA op events."""
    files = glob.glob(os.path.join(trace_dir, "**", "*perfetto_trace.json.gz"), recursive=True)
    if not files:
        raise FileNotFoundError(f"no Perfetto trace under {trace_dir}")
    with gzip.open(max(files, key=os.path.getmtime), "rt") as f:
        trace = json.load(f)
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    devices = {e["pid"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"
               and "/device:" in (e.get("args") or {}).get("name", "")}
    complete = [e for e in events if e.get("ph") == "X"]
    on_device = [e for e in complete if e.get("pid") in devices]
    # On the host, a loop's or branch's event spans the ops it runs: only the ops count.
    return on_device or [e for e in complete if "hlo_op" in (e.get("args") or {})
                         and not re.match(r"(while|conditional|call)\b", e["name"])]


def profile_program(compiled, args: Sequence[Any], scopes: Sequence[str], out_dir: str | None = None,
                    calls: int = 2, after: Callable[[Any], Any] | None = None, top: int = 25) -> dict:
    """Trace `calls` calls of `compiled` (a `jax.stages.Compiled`; `after(result)` maps one
    call's result to the next call's `args`, e.g. a carried state) and return milliseconds of
    device time per call: the total, by scope (`scope_of` of `scopes`; UNATTRIBUTED for
    kernels the program's text does not name), and the `top` kernels with their op names. The
    trace stays in `out_dir` (a temporary directory if None) for a trace viewer."""
    names = hlo_op_names(compiled.as_text())
    out_dir = out_dir or tempfile.mkdtemp(prefix="conav_profile_")
    result = None
    with jax.profiler.trace(out_dir, create_perfetto_trace=True):
        for i in range(calls):
            result = compiled(*args)
            if after is not None and i + 1 < calls:
                args = after(result)
        jax.block_until_ready(result)
    by_scope: collections.Counter = collections.Counter()
    by_kernel: collections.Counter = collections.Counter()
    op_of: dict[str, str] = {}
    for event in _kernel_events(out_dir):
        ms = event.get("dur", 0.0) / 1e3 / calls
        hlo_op = (event.get("args") or {}).get("hlo_op", "")
        op = names.get(_key(hlo_op)) or names.get(_key(event["name"]))
        by_scope[UNATTRIBUTED if op is None else scope_of(op, scopes)] += ms
        by_kernel[event["name"]] += ms
        op_of.setdefault(event["name"], op or "")
    return {
        "device_ms_per_call": round(sum(by_scope.values()), 2),
        "by_scope_ms": {k: round(v, 2) for k, v in by_scope.most_common()},
        "top_kernels_ms": [[name, round(ms, 2), op_of[name][-160:]] for name, ms in by_kernel.most_common(top)],
        "trace_dir": out_dir,
    }
