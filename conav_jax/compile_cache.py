"""JAX's persistent compilation cache, kept between runs: switched on before a `conav` command
or a `conav reproduce` step's own process runs, so a second run recompiles nothing."""

from __future__ import annotations

import os
from pathlib import Path

COMPILE_CACHE_ENV = "CONAV_COMPILE_CACHE"  # a directory, or "off"


def default_compile_cache_dir() -> Path:
    """Where compiled XLA programs are kept between runs: $XDG_CACHE_HOME/conav_jax/xla (or ~/.cache/...)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "conav_jax" / "xla"


def enable_compile_cache(setting: str | None) -> Path | None:
    """Turn on JAX's persistent compilation cache: `setting` a directory, "off", or None for
    $CONAV_COMPILE_CACHE, else the default directory. Returns the directory (None when off).
    Every program is kept, whatever its compile time: a CPU run compiles many small ones."""
    setting = setting or os.environ.get(COMPILE_CACHE_ENV) or str(default_compile_cache_dir())
    if setting.lower() in ("off", "none", "0", ""):
        return None
    import jax

    path = Path(setting).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
