"""Provenance: what a number was made with, recorded beside it.

Every run's config and every evaluation's metrics.json carry `provenance(...)`: the code's
commit, whether the tree held uncommitted changes and a hash of the source itself (`code_hash`),
the JAX version and the device, and the settings that change what a figure means (physics
implementation, caster, materials, encoder, resolution). A resumed run may be continued by other code (the commit changes), so the run
format compares configs without this block (`PROVENANCE_KEY`).
"""

from __future__ import annotations

import functools
import os
import subprocess
from pathlib import Path

PROVENANCE_KEY = "provenance"
# Names the commit of a copy of the tree whose git state is not its own (a copy made on another
# machine): provenance records it, and "dirty" as unknown.
COMMIT_ENV = "CONAV_COMMIT"
UNKNOWN = "unknown"
_REPO = Path(__file__).resolve().parents[1]


@functools.lru_cache(maxsize=1)
def git_state(repo: str | Path = _REPO) -> tuple[str, bool | None]:
    """(commit hash, dirty) of the checkout holding this package; (UNKNOWN, None) outside one
    (an installed wheel) or where git is missing. Dirty: tracked files differ from the commit."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, check=True,
                              timeout=30).stdout.strip()

    if os.environ.get(COMMIT_ENV):  # a copy of the tree that is not its git checkout
        return os.environ[COMMIT_ENV], None
    try:
        commit = git("rev-parse", "HEAD")
        dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError):
        return UNKNOWN, None
    return commit or UNKNOWN, dirty


# The packages whose source is the code: the stage folders install under `conav_jax` from folders
# of their own (pyproject.toml's package-dir), which an editable install does not nest in it.
SOURCE_PACKAGES = ("conav_jax", "conav_jax.envs", "conav_jax.train", "conav_jax.eval")


@functools.lru_cache(maxsize=1)
def code_hash() -> str:
    """`source_hash` of this package: the same for the same code however it is installed (a
    checkout, an editable install, a copy on another machine), so a record whose git state is
    unknown (COMMIT_ENV) can still be matched to a commit's code."""
    return source_hash(SOURCE_PACKAGES)


def source_hash(packages: tuple[str, ...]) -> str:
    """The first 16 hex digits of a sha256 over the Python source of `packages` and their
    subpackages, module by module in dotted-name order (name, then bytes)."""
    import hashlib
    import importlib.util
    import pkgutil

    sources, todo, seen = {}, list(packages), set()
    while todo:
        package = todo.pop()
        if package in seen:
            continue
        seen.add(package)
        spec = importlib.util.find_spec(package)
        for location in spec.submodule_search_locations or ():
            for path in Path(location).glob("*.py"):
                sources[f"{package}.{path.stem}"] = path
            todo += [f"{package}.{m.name}" for m in pkgutil.iter_modules([location]) if m.ispkg]
    digest = hashlib.sha256()
    for name in sorted(sources):
        digest.update(name.encode() + b"\0" + sources[name].read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def device_description() -> dict:
    """The default JAX backend's platform, device kind and device count, and the JAX version."""
    import jax

    devices = jax.devices()
    return {"jax": jax.__version__, "platform": devices[0].platform, "device": devices[0].device_kind,
            "device_count": len(devices)}


def provenance(**settings) -> dict:
    """The provenance block of a run or an evaluation: commit, dirty, JAX version and device,
    plus `settings` (the env's resolved physics, caster, materials and resolution, from
    `conav_jax.envs.config.env_settings`; a policy's encoder; ...), which override nothing above."""
    commit, dirty = git_state()
    clash = sorted(set(settings) & {"commit", "dirty", "code", "jax", "platform", "device", "device_count"})
    if clash:
        raise ValueError(f"provenance settings may not replace {clash}")
    return {"commit": commit, "dirty": dirty, "code": code_hash(), **device_description(), **settings}
