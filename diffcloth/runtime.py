"""Run-time switches and the record of where a run happened.

- `enable_compilation_cache(path)`: JAX's persistent compilation cache, so a second run of the same
  config skips XLA compilation (on a 2-core CPU that is most of a short fit's time). The CLI turns it
  on by default at `$DIFFCLOTH_CACHE` or `~/.cache/diffcloth/jax`; `--no-cache` or
  `DIFFCLOTH_CACHE=off` turns it off (the test suite does the latter).
- `tune_xla_cpu()`: runs once at `import diffcloth`: lets XLA's CPU compiler build each small
  while loop (a small net's substep scan, its transpose, the frame loop around them) as one
  compiled function instead of one runtime call per fused op per iteration, and keeps
  reductions in XLA's own loops rather than YNNPACK fusions. `DIFFCLOTH_XLA_TUNING=off` leaves
  XLA_FLAGS alone.
- `tune_malloc()`: runs once at `import diffcloth` on Linux with glibc: keeps freed memory in the
  process heap instead of returning it to the system, so the buffers of each call of a compiled
  program reuse pages already mapped (256^2 render gradient 38.2 -> 32.9 ms on the 2-core CPU,
  `benchmarks/render_profile.py` with `DIFFCLOTH_MALLOC_TUNING=off` and without).
  `DIFFCLOTH_MALLOC_TUNING=off` leaves the allocator alone.
- `environment()`: versions, backend, devices and float64 flag, written next to every fit result.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

__all__ = [
    "SMALL_LOOP_BYTES",
    "YNN_NO_REDUCE",
    "cache_disabled",
    "check_cache_dir",
    "default_cache_dir",
    "enable_compilation_cache",
    "environment",
    "malloc_tuned",
    "tune_malloc",
    "tune_xla_cpu",
    "unwritable_folder",
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

YNN_FUSION_FLAG = "--xla_cpu_experimental_ynn_fusion_type"
# jaxlib 0.10's XLA hands reductions (e.g. a sum over a pixel's 3 or 4 colour channels, common in
# the rasterizer's backward) to YNNPACK fusions; on the 2-core CPU these ran slower than XLA's
# own loops (`benchmarks/render_profile.py`: 256^2 render forward 15.3 -> 10.3 ms). "-reduce"
# takes reductions out of the default list. Added only for the jaxlib releases where the flag
# was checked to exist: XLA aborts on flags it does not know.
YNN_NO_REDUCE = f"{YNN_FUSION_FLAG}=-reduce"
YNN_JAXLIB = ((0, 10, 2), (0, 11, 0))  # [first checked, first not checked)


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


def unwritable_folder(folder: str | Path) -> str | None:
    """Why files cannot be written into `folder` (an existing folder), or None. Marked read-only
    (no write permission bit at all: refused even for root, who could write anyway), or a real
    write of a probe file fails (permissions, a read-only file system)."""
    import stat
    import tempfile

    folder = Path(folder)
    try:
        if not stat.S_IMODE(folder.stat().st_mode) & 0o222:
            return "it is read-only (no write permission)"
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".diffcloth-write-test-"):
            pass
    except OSError as err:
        return f"cannot write there ({err.strerror or err})"
    return None


def check_cache_dir(path: str | Path | None = None) -> Path:
    """The compilation cache folder (default `default_cache_dir()`), made if missing, or OSError
    saying why it cannot hold the cache: a file in the way, no permission to write, a read-only
    file system. JAX itself only logs a warning when it cannot write a cache entry, so a warm-up
    into an unusable folder would otherwise compile everything and keep nothing."""
    path = Path(path).expanduser() if path is not None else default_cache_dir()
    if path.exists() and not path.is_dir():
        raise OSError(
            f"compilation cache {str(path)!r} is not a folder; name another with --cache DIR"
        )
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        why = f"cannot be made ({err.strerror or err})"
    else:
        why = unwritable_folder(path)
    if why:
        raise OSError(
            f"compilation cache folder {str(path)!r}: {why}; name another with --cache DIR"
        )
    return path


def tune_xla_cpu(small_loop_bytes: int = SMALL_LOOP_BYTES) -> bool:
    """Add XLA's small-while-loop threshold and, on the jaxlib releases checked, `YNN_NO_REDUCE`
    to XLA_FLAGS; True if XLA_FLAGS was changed.

    Each is left out when XLA_FLAGS already names it (the user's value wins). No change at all
    when `DIFFCLOTH_XLA_TUNING` is "off"/"0"/"none" or when a JAX backend has already started
    (XLA read its flags then; the change would not take effect). Only XLA's CPU compiler reads
    the options (not yet checked on a GPU run).
    """
    if os.environ.get("DIFFCLOTH_XLA_TUNING", "").strip().lower() in ("off", "0", "none"):
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    if _backend_started():
        return False
    tokens = flags.split()
    if SMALL_LOOP_KEY not in flags:
        option = f"{SMALL_LOOP_KEY}={int(small_loop_bytes)}"
        for i, tok in enumerate(tokens):
            if tok.startswith("--xla_backend_extra_options="):
                tokens[i] = f"{tok},{option}"  # the flag is one comma-separated map: extend it
                break
        else:
            tokens.append(f"--xla_backend_extra_options={option}")
    if YNN_FUSION_FLAG not in flags and _jaxlib_has_ynn_flag():
        tokens.append(YNN_NO_REDUCE)
    if tokens == flags.split():
        return False
    os.environ["XLA_FLAGS"] = " ".join(tokens)
    return True


def _jaxlib_has_ynn_flag() -> bool:
    """jaxlib's version (read without starting a backend) is one where the YNN flag was checked."""
    try:
        from jaxlib.version import __version__ as version
    except ImportError:  # pragma: no cover
        return False
    try:
        release = tuple(int(p) for p in version.split(".")[:3])
    except ValueError:  # a development build: leave XLA's defaults
        return False
    low, high = YNN_JAXLIB
    return low <= release < high


_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4  # glibc's mallopt parameters (malloc.h)
_TRIM_THRESHOLD = 2**31 - 1  # bytes free at the heap's top before glibc gives them back: never
_malloc_tuned = False


def tune_malloc() -> bool:
    """Make glibc's malloc keep freed memory for reuse; True if it did (now or before).

    XLA's CPU runtime allocates each call's temporary buffers afresh. glibc serves large requests
    with new mappings (mmap) and returns them on free, and shrinks the heap when its top is
    free, so every call of a compiled program page-faults on all the memory it touches: at
    256^2 a third of the render gradient's time. With mmap off (`M_MMAP_MAX` 0) and the heap
    never trimmed, the next call reuses the same, already mapped pages. The process keeps its
    peak memory until it exits. Only with glibc (Linux); elsewhere nothing happens.
    `DIFFCLOTH_MALLOC_TUNING` "off"/"0"/"none" leaves the allocator alone.
    """
    global _malloc_tuned
    if _malloc_tuned:
        return True
    if os.environ.get("DIFFCLOTH_MALLOC_TUNING", "").strip().lower() in ("off", "0", "none"):
        return False
    if not _glibc():
        return False
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # pragma: no cover - a libc without mallopt
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # mallopt returns 1 on success
    _malloc_tuned = bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD)) and bool(
        mallopt(_M_MMAP_MAX, 0)
    )
    return _malloc_tuned


def _glibc() -> bool:
    """The C library is glibc (asked of the C library itself: no file is read)."""
    try:
        return (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc")
    except (AttributeError, ValueError, OSError):  # not a POSIX system, or not glibc
        return False


def malloc_tuned() -> bool:
    """Whether `tune_malloc` changed glibc's malloc in this process."""
    return _malloc_tuned


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
        "malloc_tuned": _malloc_tuned,
        "compilation_cache": jax.config.jax_compilation_cache_dir,
    }
