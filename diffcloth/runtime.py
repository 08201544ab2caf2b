"""Run-time switches and the record of where a run happened.

- `enable_compilation_cache(path)`: JAX's persistent compilation cache, so a second run of the same
  config skips XLA compilation (on a 2-core CPU that is most of a short fit's time). The CLI turns it
  on by default at `$DIFFCLOTH_CACHE` or `~/.cache/diffcloth/jax`; `--no-cache` or
  `DIFFCLOTH_CACHE=off` turns it off (the test suite does the latter).
- `tune_xla_cpu()`: runs once at `import diffcloth`: lets XLA's CPU compiler build each small
  while loop (a small net's substep scan, its transpose, the frame loop around them) as one
  compiled function instead of one runtime call per fused op per iteration. `DIFFCLOTH_XLA_TUNING=off`
  leaves XLA_FLAGS alone.
- `environment()`: versions, backend, devices and float64 flag, written next to every fit result.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

__all__ = [
    "SMALL_LOOP_BYTES",
    "cache_disabled",
    "default_cache_dir",
    "enable_compilation_cache",
    "environment",
    "tune_xla_cpu",
]

SMALL_LOOP_KEY = "xla_cpu_small_while_loop_byte_threshold"
# XLA's CPU backend runs a while loop as one runtime call per fused op per iteration (its "thunk"
# runtime) unless the loop's one-iteration memory traffic (HloCostAnalysis bytes accessed) is below
# this threshold (XLA default: 1,024 B); then the whole loop is compiled into one function. On
# the 2-core CPU, 2 MB takes in the substep scans of the fit configs' 13 x 10 nets and their
# transposes (13 x 10 gradient 0.5x; fit steps of the main job and drape_material 0.39x / 0.48x
# of d26acf4's, against 0.49x / 0.54x without) and leaves 64 x 64 and larger on the thunk
# runtime (their gradient ran 1.1x slower as one function). Larger thresholds also hoisted the
# backward's outer frame loop: longer compiles, no faster steps (docs/performance.md).
SMALL_LOOP_BYTES = 2_000_000


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


def tune_xla_cpu(small_loop_bytes: int = SMALL_LOOP_BYTES) -> bool:
    """Add XLA's small-while-loop threshold to XLA_FLAGS; True if XLA_FLAGS was changed.

    No change when `DIFFCLOTH_XLA_TUNING` is "off"/"0"/"none", when XLA_FLAGS already names the
    threshold (the user's value wins), or when a JAX backend has already started (XLA read its
    flags then; the change would not take effect). Only XLA's CPU compiler reads the option (not
    yet checked on a GPU run).
    """
    if os.environ.get("DIFFCLOTH_XLA_TUNING", "").strip().lower() in ("off", "0", "none"):
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    if SMALL_LOOP_KEY in flags or _backend_started():
        return False
    option = f"{SMALL_LOOP_KEY}={int(small_loop_bytes)}"
    tokens = flags.split()
    for i, tok in enumerate(tokens):
        if tok.startswith("--xla_backend_extra_options="):
            tokens[i] = f"{tok},{option}"  # the flag is one comma-separated map: extend it
            break
    else:
        tokens.append(f"--xla_backend_extra_options={option}")
    os.environ["XLA_FLAGS"] = " ".join(tokens)
    return True


def _backend_started() -> bool:
    try:
        from jax._src import xla_bridge
    except ImportError:  # pragma: no cover - a JAX without the module: assume started, do nothing
        return True
    started = getattr(xla_bridge, "backends_are_initialized", None)
    return True if started is None else bool(started())


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
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "compilation_cache": jax.config.jax_compilation_cache_dir,
    }
