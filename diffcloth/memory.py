"""Memory estimates made before compiling, so an impossible job is refused in a second, not after
minutes of compilation or an out-of-memory abort.

    est = estimate_memory(scene, "fit", multistart=4)   # bytes, from the sizes alone
    check_memory(est, "fit")                           # MemoryLimitError if over the limit

The limit is `$DIFFCLOTH_MEMORY_LIMIT` (bytes, or with a suffix: "8G", "512M"), else 90 % of the
memory available now (the accelerator's memory when JAX runs on a GPU/TPU and reports it). The
model counts the arrays a job keeps (trajectory, tessellated frames, video, gradients) and the
renderer's per-pixel working buffers; its per-pixel and per-vertex constants come from XLA's
memory analysis of the compiled render of configs/drape.toml (`benchmarks/memory.py` style), and
it errs on the high side.
"""

from __future__ import annotations

import math
import os

__all__ = ["MemoryLimitError", "check_memory", "estimate_memory", "format_bytes", "memory_limit"]

#: bytes per pixel per camera of one rendered frame's working set, in units of the float size
#: (G-buffer, 2x2-window candidates, shading temporaries); measured, rounded up.
FLOATS_PER_PIXEL = 160
#: floats per tessellated vertex of one frame (positions, frames, texture coordinates, setup).
FLOATS_PER_VERTEX = 120
#: floats per control-net node per substep kept by a step (forces, springs, solver vectors).
FLOATS_PER_NODE = 60


class MemoryLimitError(ValueError):
    """A job would need more memory than allowed; the message holds the estimate and the limit."""


def format_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024.0
    return f"{n:.3g} EiB"


def _parse_size(text: str) -> int:
    t = text.strip().upper().removesuffix("B").removesuffix("I")
    scale = {"K": 1024, "M": 1024**2, "G": 1024**3, "T": 1024**4}.get(t[-1:], 1)
    value = float(t[:-1] if t[-1:] in "KMGT" else t)
    if not math.isfinite(value) or value <= 0:
        raise ValueError
    return int(value * scale)


def _available_host() -> int | None:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _available_device() -> int | None:
    try:
        import jax

        dev = jax.devices()[0]
        if dev.platform == "cpu":
            return None
        stats = dev.memory_stats() or {}
        limit = stats.get("bytes_limit")
        return None if limit is None else int(limit) - int(stats.get("bytes_in_use", 0))
    except Exception:  # noqa: BLE001  (no stats on this backend)
        return None


def memory_limit() -> tuple[int | None, str]:
    """(bytes allowed or None when unknown, where the figure comes from)."""
    env = os.environ.get("DIFFCLOTH_MEMORY_LIMIT", "").strip()
    if env:
        try:
            return _parse_size(env), f"DIFFCLOTH_MEMORY_LIMIT={env}"
        except (ValueError, IndexError):
            raise MemoryLimitError(
                f"DIFFCLOTH_MEMORY_LIMIT={env!r} is not a size; give bytes or e.g. 8G, 512M"
            ) from None
    dev = _available_device()
    if dev is not None:
        return int(0.9 * dev), "90 % of the accelerator memory available"
    host = _available_host()
    if host is None:
        return None, "unknown"
    return int(0.9 * host), "90 % of the memory available now"


def estimate_memory(
    scene, job: str = "render", *, multistart: int = 1, chunk: int | None = None, num_frames=None
) -> int:
    """Bytes a job on `scene` needs at its peak (an upper estimate, computed from sizes only).

    job: "simulate" (trajectory on the host, `chunk` frames at a time on the device), "render"
    (trajectory + video + `chunk` frames rendered at once), "fit" (forward and backward pass of
    the video loss, times `multistart`). num_frames overrides the scene's.
    """
    if job not in ("simulate", "render", "fit"):
        raise ValueError(f"job={job!r}; allowed: 'simulate', 'render', 'fit'")
    b = 8 if str(scene.material.stretch.dtype) == "float64" else 4
    T = int(scene.num_frames if num_frames is None else num_frames)
    nodes = int(scene.net.rows) * int(scene.net.cols)
    traj = T * nodes * 6 * b  # x and v per frame
    step = nodes * FLOATS_PER_NODE * b
    if job == "simulate":
        return int(traj + min(T, chunk or T) * nodes * 6 * b + step)
    h, w = scene.image_shape
    cams = len(scene.cameras)
    frames = T // max(1, int(scene.frame_stride))
    level = int(scene.level)
    verts = (int(scene.net.rows) * level + 1) * (int(scene.net.cols) * level + 1)
    per_frame = cams * h * w * FLOATS_PER_PIXEL * b + verts * FLOATS_PER_VERTEX * b
    video = cams * frames * h * w * 3 * b
    if job == "render":
        return int(traj + 2 * video + min(frames, chunk or 1) * per_frame + step)
    # fit: trajectory and its cotangent, video, target and cotangent, one frame's forward and
    # backward working set, sqrt-checkpointed physics states
    blocks = math.isqrt(max(T, 1)) + 1
    per_start = 2 * traj + 3 * video + 3 * per_frame + blocks * step
    return int(multistart * per_start + video)


def check_memory(estimate: int, what: str, *, hint: str = "") -> None:
    """MemoryLimitError when `estimate` exceeds `memory_limit()`; the message gives both."""
    limit, source = memory_limit()
    if limit is not None and estimate > limit:
        raise MemoryLimitError(
            f"{what} needs about {format_bytes(estimate)}, more than the limit "
            f"{format_bytes(limit)} ({source}); {hint or 'make the job smaller'} "
            "(or set DIFFCLOTH_MEMORY_LIMIT to allow more)"
        )
