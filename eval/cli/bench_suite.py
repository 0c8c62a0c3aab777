"""`conav bench suite`: the benchmarks BENCHMARKS.md leads with, run in turn at one commit, each as
the `conav bench` command that makes its figure, in a process of its own; their JSON lines are
appended to one file with the command and the commit beside each. A benchmark already in the file
is not run again, so a suite cut short (a machine's time limit) continues where it stopped; one
that failed is tried again.
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

# name -> the command's arguments after `conav --compile-cache off`, with the datasets it reads
# by name: SMALL, PAPER, DEMO (`conav generate --preset small|paper|demo`).
SUITE: dict[str, str] = {
    "sim_112x448": "bench sim --data {SMALL} --split val --json --steps 10 --repeats 3 --resolution 112x448 "
                   "--batch 16384",
    "sim_32x128": "bench sim --data {SMALL} --split val --json --steps 10 --repeats 3 --resolution 32x128 "
                  "--batch 32768",
    "sweep_pioneer_drive": "bench eval --data {PAPER} --split val --resolution 112x448 --repeats 2 --json "
                           "--agent pioneer-drive --batch 3072",
    "sweep_conav_untrained": "bench eval --data {PAPER} --split val --resolution 112x448 --repeats 2 --json "
                             "--agent conav --untrained --batch 3072",
    "policy_update_patch": "bench train --model policy --resolution 112x448 --batch 1024 --steps 5 --repeats 5 "
                           "--remat --conv-dtype bfloat16 --encoder patch --json",
    "policy_update_conv": "bench train --model policy --resolution 112x448 --batch 1024 --steps 5 --repeats 5 "
                          "--remat --conv-dtype bfloat16 --encoder conv --json",
    "live_gt_all": "bench live --data {DEMO} --resolution 112x448 --lanes 8192 --window-steps 4 --beta 1 "
                   "--ground-truth-intentions --parts update --repeats 6",
}
DATASETS = ("SMALL", "PAPER", "DEMO")

# (arguments after `conav`) -> (exit status, stdout, stderr)
Runner = Callable[[list[str]], tuple[int, str, str]]


def suite_command(name: str, data: dict[str, str]) -> list[str]:
    """Benchmark `name`'s arguments after `conav`, its datasets filled in from `data` (DATASETS
    -> directory). ValueError naming an unknown benchmark or a dataset it needs and `data` lacks."""
    if name not in SUITE:
        raise ValueError(f"no benchmark {name!r} in the suite; it has {', '.join(SUITE)}")
    needs = [d for d in DATASETS if "{" + d + "}" in SUITE[name]]
    missing = [d for d in needs if not data.get(d)]
    if missing:
        raise ValueError(f"benchmark {name} reads the {', '.join(missing)} dataset(s): give "
                         + ", ".join(f"--{d.lower()} DIR" for d in missing))
    given = {d: data.get(d) or "" for d in DATASETS}
    return ["--compile-cache", "off", *(token.format(**given) for token in shlex.split(SUITE[name]))]


def run_in_process_of_its_own(argv: list[str]) -> tuple[int, str, str]:
    """`conav ARGV` in a fresh Python process (each benchmark gets the device to itself), which
    does not look in its working directory for modules (`-P`: a checkout's source tree would
    shadow the installed package)."""
    done = subprocess.run([sys.executable, "-P", "-m", "conav_jax.eval.cli", *argv], capture_output=True, text=True)
    return done.returncode, done.stdout, done.stderr


def finished(out: Path) -> set[str]:
    """The benchmarks `out` holds a result of (a failure record does not count)."""
    if not out.is_file():
        return set()
    records = [json.loads(line) for line in out.read_text().splitlines() if line.strip()]
    return {r["suite"] for r in records if "error" not in r}


def run_suite(names: list[str], data: dict[str, str], out: Path, runner: Runner = run_in_process_of_its_own,
              say: Callable[[str], None] = print) -> dict[str, str]:
    """Run benchmarks `names` (SUITE keys, in that order) not yet in `out`, appending to it each
    JSON line a benchmark prints, with "suite" (its name), "command" and "commit" (the checkout's,
    conav_jax.provenance.git_state; "dirty" beside it), or one record with "error" where it
    exits non-zero or prints no JSON. Returns {name: "ran" | "failed" | "skipped"}. ValueError
    (before anything runs) for an unknown name or a missing dataset."""
    from conav_jax.provenance import git_state

    commands = {name: suite_command(name, data) for name in names}
    commit, dirty = git_state()
    done, outcome = finished(out), {}
    out.parent.mkdir(parents=True, exist_ok=True)
    for k, (name, argv) in enumerate(commands.items(), start=1):
        if name in done:
            outcome[name] = "skipped"
            say(f"[{k}/{len(commands)}] {name}: in {out} already")
            continue
        text = "conav " + shlex.join(argv)
        say(f"[{k}/{len(commands)}] {name}: {text}")
        t0 = time.perf_counter()
        rc, stdout, stderr = runner(argv)
        records = [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]
        base = {"suite": name, "command": text, "commit": commit, "dirty": dirty}
        if rc != 0 or not records:
            tail = "\n".join(stderr.strip().splitlines()[-5:])
            records = [{"error": f"exit status {rc}" if rc else "no JSON line printed", "stderr_tail": tail}]
        with open(out, "a") as f:
            for record in records:
                f.write(json.dumps({**base, **record}) + "\n")
        outcome[name] = "failed" if "error" in records[0] else "ran"
        say(f"    {outcome[name]} in {time.perf_counter() - t0:.0f} s" +
            (f": {records[0]['error']}\n{records[0]['stderr_tail']}" if outcome[name] == "failed" else ""))
    return outcome
