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

import dataclasses
import math
import os

__all__ = [
    "JobSizes",
    "MemoryLimitError",
    "check_memory",
    "estimate_memory",
    "format_bytes",
    "memory_limit",
]

#: floats per pixel per camera of one rendered frame's working set (G-buffer, 2x2-window
#: candidates, shading temporaries). XLA's memory analysis of the compiled render of
#: configs/drape.toml (float32, level 4) gave 1.49 MB at 32x32 and 3.27 MB at 96x96, i.e.
#: ~54 floats per pixel; 160 leaves room for other shading modes and textures.
FLOATS_PER_PIXEL = 160
#: floats per tessellated vertex of one frame (the same measurement gave ~146).
FLOATS_PER_VERTEX = 200
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


@dataclasses.dataclass(frozen=True)
class JobSizes:
    """The sizes a memory estimate needs (from a Scene or straight from a Config, so a huge net
    is refused before it is built)."""

    num_frames: int
    rows: int
    cols: int
    height: int = 1
    width: int = 1
    cameras: int = 1
    frame_stride: int = 1
    level: int = 4
    float_bytes: int = 4

    @classmethod
    def from_scene(cls, scene, num_frames: int | None = None) -> JobSizes:
        h, w = scene.image_shape
        return cls(
            num_frames=int(scene.num_frames if num_frames is None else num_frames),
            rows=int(scene.net.rows), cols=int(scene.net.cols), height=int(h), width=int(w),
            cameras=len(scene.cameras), frame_stride=int(scene.frame_stride),
            level=int(scene.level),
            float_bytes=8 if str(scene.material.density.dtype) == "float64" else 4,
        )  # fmt: skip

    @classmethod
    def from_config(cls, config, *, num_frames=None, size=None, x64=None) -> JobSizes:
        """From a validated `diffcloth.config.Config`; `size` overrides width and height."""
        if x64 is None:
            import jax

            x64 = bool(jax.config.jax_enable_x64)
        rc = config.render
        return cls(
            num_frames=int(config.sim.num_frames if num_frames is None else num_frames),
            rows=int(config.net.rows), cols=int(config.net.cols),
            height=int(rc.height if size is None else size),
            width=int(rc.width if size is None else size),
            cameras=len(config.cameras), frame_stride=int(rc.frame_stride), level=int(rc.level),
            float_bytes=8 if x64 else 4,
        )  # fmt: skip


def estimate_memory(sizes, job: str = "render", *, multistart: int = 1, chunk=None) -> int:
    """Bytes a job needs at its peak (an upper estimate, computed from sizes only).

    sizes: a JobSizes, or a Scene. job: "simulate" (trajectory on the host, `chunk` frames at a
    time on the device), "render" (trajectory + video + `chunk` frames rendered at once), "fit"
    (forward and backward pass of the video loss, times `multistart`).
    """
    if job not in ("simulate", "render", "fit"):
        raise ValueError(f"job={job!r}; allowed: 'simulate', 'render', 'fit'")
    s = sizes if isinstance(sizes, JobSizes) else JobSizes.from_scene(sizes)
    b, T = s.float_bytes, s.num_frames
    nodes = s.rows * s.cols
    traj = T * nodes * 6 * b  # x and v per frame
    step = nodes * FLOATS_PER_NODE * b
    if job == "simulate":
        return int(traj + min(T, chunk or T) * nodes * 6 * b + step)
    frames = T // max(1, s.frame_stride)
    verts = (s.rows * s.level + 1) * (s.cols * s.level + 1)
    pixels = s.cameras * s.height * s.width
    per_frame = pixels * FLOATS_PER_PIXEL * b + verts * FLOATS_PER_VERTEX * b
    video = s.cameras * frames * s.height * s.width * 3 * b
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
