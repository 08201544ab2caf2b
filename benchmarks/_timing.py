"""The one timing helper and JSON line schema of every `benchmarks/*.py` script.

Timing: `timed(fn, *args, repeats=7)` calls `fn(*args)` once untimed (compile + warm-up), then
`repeats` times, blocking on the result each time (`jax.block_until_ready`), and returns a
`Timing` (median and minimum, seconds). The median is the figure to quote; the minimum helps on
a shared machine. `compile_and_run(fn, *args)` times the first call separately (compile share).

JSON lines (one object per line on stdout, and in `benchmarks/results/<script>.jsonl`):
  bench     str    what the line measures (the case family, e.g. "physics", "render", "meta")
  ...       case keys (net, size, mode, ...) identifying the case
  *_ms / *_us / *_s   timings with their unit in the key name, medians unless the key says
                      otherwise (*_min_ms: minimum)
  ratio keys (*_ratio) are always new / reference or diffcloth / peer (below 1: faster)
The first line of each script has bench "meta": `meta(script)` (machine, Python, JAX, backend,
default float dtype, CPU count, load average at start, UTC time).
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import platform
import sys
import time

import numpy as np


@dataclasses.dataclass(frozen=True)
class Timing:
    """Median and minimum wall time of the timed calls, s; `runs` timed calls."""

    median: float
    min: float
    runs: int

    @property
    def median_ms(self) -> float:
        return round(self.median * 1e3, 3)

    @property
    def min_ms(self) -> float:
        return round(self.min * 1e3, 3)


def _block(out):
    import jax

    return jax.block_until_ready(out)


def timed(fn, *args, repeats: int = 7, warmup: int = 1) -> Timing:
    """Median and minimum of `repeats` calls of fn(*args) after `warmup` untimed calls."""
    for _ in range(warmup):
        _block(fn(*args))
    times = []
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        _block(fn(*args))
        times.append(time.perf_counter() - t)
    return Timing(float(np.median(times)), float(np.min(times)), len(times))


def timed_alternating(calls: dict, repeats: int = 7, warmup: int = 1) -> dict:
    """`timed` for several calls {name: (fn, args)} in one loop: each round calls every one once,
    the order reversed every other round, so a change in the machine's load during the run
    reaches all of them alike (the figure to take ratios of on a shared machine).
    Returns {name: Timing}."""
    for fn, args in calls.values():
        for _ in range(warmup):
            _block(fn(*args))
    names = list(calls)
    times = {n: [] for n in names}
    for r in range(max(1, repeats)):
        for n in names if r % 2 == 0 else names[::-1]:
            fn, args = calls[n]
            t = time.perf_counter()
            _block(fn(*args))
            times[n].append(time.perf_counter() - t)
    return {n: Timing(float(np.median(v)), float(np.min(v)), len(v)) for n, v in times.items()}


def compile_and_run(fn, *args) -> float:
    """Wall time of the first call (trace + compile + one run), s."""
    t = time.perf_counter()
    _block(fn(*args))
    return time.perf_counter() - t


def meta(script: str, **extra) -> dict:
    """The "meta" line every script prints first."""
    import jax
    import jax.numpy as jnp

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    return dict(
        bench="meta",
        script=script,
        machine=platform.processor() or platform.machine(),
        python=sys.version.split()[0],
        jax=jax.__version__,
        backend=jax.default_backend(),
        dtype=str(jnp.zeros(()).dtype),
        cpus=os.cpu_count(),
        load_1min=None if load is None else round(load, 2),
        utc=datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        xla_flags=os.environ.get("XLA_FLAGS", ""),  # `import diffcloth` adds its CPU loop option
        malloc_tuned=_malloc_tuned(),  # `import diffcloth` keeps freed memory mapped (glibc)
        **extra,
    )


def _malloc_tuned():
    try:
        from diffcloth.runtime import malloc_tuned
    except ImportError:  # a baseline checkout from before the allocator setting
        return False
    return malloc_tuned()


def emit(row: dict, out=None) -> dict:
    """Print one JSON line (and append it to the open file `out`, if given)."""
    line = json.dumps(row)
    print(line, flush=True)
    if out is not None:
        out.write(line + "\n")
        out.flush()
    return row
