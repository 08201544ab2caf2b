"""Run-time switches and the record of where a run happened.

- `enable_compilation_cache(path)`: JAX's persistent compilation cache, so a second run of the same
  config skips XLA compilation (on a 2-core CPU that is most of a short fit's time). The CLI turns it
  on by default at `$DIFFCLOTH_CACHE` or `~/.cache/diffcloth/jax`; `--no-cache` or
  `DIFFCLOTH_CACHE=off` turns it off (the test suite does the latter).
- `environment()`: versions, backend, devices and float64 flag, written next to every fit result.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

__all__ = ["cache_disabled", "default_cache_dir", "enable_compilation_cache", "environment"]


def cache_disabled() -> bool:
    """True when `DIFFCLOTH_CACHE` is "off", "0" or "none"."""
    return os.environ.get("DIFFCLOTH_CACHE", "").strip().lower() in ("off", "0", "none")


def default_cache_dir() -> Path:
    """`$DIFFCLOTH_CACHE`, else `$XDG_CACHE_HOME/diffcloth/jax`, else `~/.cache/diffcloth/jax`."""
    if os.environ.get("DIFFCLOTH_CACHE") and not cache_disabled():
        return Path(os.environ["DIFFCLOTH_CACHE"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "diffcloth" / "jax"


def enable_compilation_cache(
    path: str | Path | None = None, min_compile_seconds: float = 0.0
) -> Path:
    """Cache compiled XLA programs on disk (programs that took >= min_compile_seconds to build).

    The default 0 also caches the ~116 small eager programs of a fit (one CPU compile of
    30-200 ms each): a warm `diffcloth fit configs/drape_fit.toml` spends 3.5 s instead of 7.8 s
    in backend compilation (loaded machine; 1.8 MB of cache).
    """
    import jax

    path = Path(path) if path is not None else default_cache_dir()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_seconds))
    return path


def environment() -> dict:
    """Where this run happened: Python, JAX, jaxlib, optax, numpy versions, backend, devices, x64."""
    import jax
    import jaxlib
    import numpy as np
    import optax

    from diffcloth import __version__

    devices = jax.devices()
    return {
        "diffcloth": __version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "optax": optax.__version__,
        "numpy": np.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in devices],
        "x64": bool(jax.config.jax_enable_x64),
        "compilation_cache": jax.config.jax_compilation_cache_dir,
    }
