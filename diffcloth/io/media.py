"""Images and videos (PNG, GIF, MP4) and result JSON.

Images are float (H, W, C) in [0, 1] (C = 1, 3 or 4; (H, W) is grey); a video is (T, H, W, C).
Writing clips to [0, 1] and rounds to 8 bits (or 16 bits: `save_png(..., bits=16)`); reading
returns float32 in [0, 1] (uint8 / 255, uint16 / 65535, exactly: 16-bit colour PNGs keep all bits).
MP4 needs the optional `imageio-ffmpeg` (`pip install "diffcloth[video]"`); without it
`save_video` writes a GIF next to the requested path and logs why.

Colour: diffcloth computes in linear RGB. Files can hold linear values or sRGB-encoded ones:
  - `colorspace="srgb"`: for people. Writing encodes the linear image with the sRGB transfer
    function (and marks the PNG with an sRGB chunk); reading decodes such a file back to linear.
    The CLI's render output, fit reports (compare.gif) and the gallery are written this way.
  - `colorspace="linear"`: data for programs. Values are written and read as they are (PNGs get
    a gAMA 1.0 chunk), so a linear image round-trips exactly up to quantisation.
  - reading with `colorspace="auto"` (the default of `load_image`): the file's own sRGB/gAMA
    chunk decides; without one, 8-bit files are taken as sRGB (what image libraries and cameras
    assume) and 16-bit files as linear.
Alpha is never colour-converted.

Example:
    >>> import numpy as np, tempfile, os
    >>> d = tempfile.mkdtemp()
    >>> p = save_png(os.path.join(d, "a.png"), np.full((4, 4, 3), 0.5))
    >>> load_image(p).shape
    (4, 4, 3)
"""

from __future__ import annotations

import json
import logging
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "linear_to_srgb",
    "load_image",
    "load_image_sequence",
    "check_numbered_sequence",
    "load_json",
    "load_video",
    "save_image_sequence",
    "save_json",
    "save_png",
    "save_video",
    "side_by_side",
    "srgb_to_linear",
    "to_jsonable",
    "read_image_raw",
    "to_uint16",
    "to_uint8",
]

log = logging.getLogger("diffcloth.io")

#: file colour encodings: "srgb" (for people) and "linear" (data); reading also takes "auto".
COLORSPACES = ("srgb", "linear")


def linear_to_srgb(x) -> np.ndarray:
    """Linear RGB in [0, 1] -> sRGB-encoded values (IEC 61966-2-1 transfer function); clips."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1.0 / 2.4) - 0.055)


def srgb_to_linear(x) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear RGB (the inverse of `linear_to_srgb`)."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _check_colorspace(colorspace, allowed=COLORSPACES) -> str:
    if colorspace not in allowed:
        raise ValueError(f"colorspace={colorspace!r}; allowed: {', '.join(map(repr, allowed))}")
    return colorspace


def _encode(image: np.ndarray, colorspace: str) -> np.ndarray:
    """Linear float image -> values to store; alpha (4th channel) untouched."""
    if colorspace == "linear" or image.dtype in (np.uint8, np.uint16, np.bool_):
        return image
    a = _finite(image)
    if a.ndim >= 3 and a.shape[-1] == 4:
        return np.concatenate([linear_to_srgb(a[..., :3]), np.clip(a[..., 3:], 0, 1)], -1)
    return linear_to_srgb(a)


def _finite(image) -> np.ndarray:
    """The image as float64; raises naming the shape and count when it holds NaN/inf."""
    a = np.asarray(image, np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(
            f"image of shape {a.shape} contains {int((~np.isfinite(a)).sum())} NaN/inf"
        )
    return a


def _quantize(image, top: int, dtype) -> np.ndarray:
    """Float [0, 1] -> integers 0..top (clip, scale, round) of `dtype`; NaN/inf raise."""
    return np.round(np.clip(_finite(image), 0.0, 1.0) * float(top)).astype(dtype)


def to_uint8(image) -> np.ndarray:
    """Float [0, 1] -> uint8 (clip, * 255, round); uint8 passes through; NaN/inf raise."""
    a = np.asarray(image)
    if a.dtype == np.uint8:
        return a
    if a.dtype == np.bool_:
        return a.astype(np.uint8) * 255
    return _quantize(a, 255, np.uint8)


def _check_image(image, name: str = "image") -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[-1] == 1:
        a = a[..., 0]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[-1] in (3, 4))):
        raise ValueError(f"{name} must be (H, W), (H, W, 1), (H, W, 3) or (H, W, 4); got {a.shape}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{name} has an empty size {a.shape}")
    return a


def _check_video(video, name: str = "video") -> np.ndarray:
    a = np.asarray(video)
    if a.ndim == 4 and a.shape[-1] == 1:
        a = a[..., 0]
    if not (a.ndim == 3 or (a.ndim == 4 and a.shape[-1] in (3, 4))):
        raise ValueError(
            f"{name} must be (T, H, W), (T, H, W, 1), (T, H, W, 3) or (T, H, W, 4); got {a.shape}"
        )
    if a.shape[0] == 0:
        raise ValueError(f"{name} has no frames (shape {a.shape})")
    return a


def to_uint16(image) -> np.ndarray:
    """Float [0, 1] -> uint16 (clip, * 65535, round); uint16 passes through; NaN/inf raise."""
    a = np.asarray(image)
    if a.dtype == np.uint16:
        return a
    if a.dtype == np.uint8:
        return a.astype(np.uint16) * 257
    return _quantize(a, 65535, np.uint16)


def save_png(path, image, *, colorspace: str = "linear", bits: int = 8) -> Path:
    """Write one image as PNG. Creates parent folders. Returns the path.

    Args:
      image: (H, W), (H, W, 1|3|4) float in [0, 1] (clipped), or uint8/uint16 (taken as already
        encoded in `colorspace` and written as they are).
      colorspace: "linear" (default): values are stored as they are, for programs (gAMA 1.0
        chunk). "srgb": `image` is linear RGB and is sRGB-encoded, for people (sRGB chunk).
      bits: 8 or 16 bits per channel.
    """
    from diffcloth.io.png import write_png

    _check_colorspace(colorspace)
    if bits not in (8, 16):
        raise ValueError(f"bits={bits!r}; allowed: 8, 16")
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"save_png: path {str(path)!r} must end in .png")
    img = _encode(_check_image(image), colorspace)
    data = to_uint16(img) if bits == 16 else to_uint8(img)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_png(path, data, srgb_chunk=colorspace == "srgb")


def read_image_raw(path) -> tuple[np.ndarray, str | None]:
    """(stored values as uint8/uint16/float array (H, W, C), the file's own colour encoding:
    "srgb", "linear" or None when the file does not say). Every PNG (recognised by its signature,
    whatever the suffix; interlaced, palette and 16-bit files included) is read exactly by
    `diffcloth.io.png`, never through Pillow's 8-bit reduction; other formats with imageio."""
    from diffcloth.io.png import _SIGNATURE, read_png

    path = Path(path)
    with path.open("rb") as fh:
        is_png = fh.read(len(_SIGNATURE)) == _SIGNATURE
    if is_png or path.suffix.lower() == ".png":  # a .png that is not one: read_png says so
        img, info = read_png(path)
        tag = None
        if info["srgb"]:
            tag = "srgb"
        elif info["gamma"] is not None:
            tag = "linear" if abs(info["gamma"] - 1.0) < 0.01 else "srgb"
        return img, tag
    import imageio.v3 as iio

    a = np.asarray(iio.imread(path))
    if a.ndim == 2:
        a = a[..., None]
    return a, None


def load_image(path, *, colorspace: str = "auto") -> np.ndarray:
    """Read an image file as float32 (H, W, C) in [0, 1], linear unless colorspace says otherwise.

    uint8 / 255 and uint16 / 65535 exactly (16-bit colour PNGs keep all 16 bits); grey -> C = 1.
    colorspace: how the file's values are encoded: "srgb" (decoded to linear), "linear" (kept as
    they are), or "auto": the file's sRGB/gAMA chunk, else sRGB for 8-bit files and linear for
    16-bit and float files. Alpha is never converted.
    """
    _check_colorspace(colorspace, COLORSPACES + ("auto",))
    a, tag = read_image_raw(path)
    bits = {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16}.get(a.dtype)
    if a.dtype == np.uint16:
        img = a.astype(np.float64) / 65535.0
    elif a.dtype == np.uint8:
        img = a.astype(np.float64) / 255.0
    else:
        img = a.astype(np.float64)
    if colorspace == "auto":
        colorspace = tag or ("srgb" if bits == 8 else "linear")
    if colorspace == "srgb":
        c = min(img.shape[-1], 3) if img.shape[-1] != 2 else 1  # grey+alpha: convert grey only
        img[..., :c] = srgb_to_linear(img[..., :c])
    return img.astype(np.float32)


def _rgb_frames(video, colorspace: str = "linear") -> np.ndarray:
    """(T, H, W[, C]) -> uint8 (T, H, W, 3): grey repeated, alpha composited over black."""
    a = _encode(_check_video(video), colorspace)
    if a.ndim == 3:
        a = np.repeat(np.asarray(a)[..., None], 3, axis=-1)
    a = to_uint8(a)
    if a.shape[-1] == 4:
        rgb = a[..., :3].astype(np.float64) * (a[..., 3:].astype(np.float64) / 255.0)
        a = np.round(rgb).astype(np.uint8)
    return a


def _has_ffmpeg() -> bool:
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return False
    return True


def save_video(
    path, video, fps: float = 20.0, *, loop: int = 0, colorspace: str = "linear"
) -> Path:
    """Write a video (T, H, W, C) as GIF (.gif) or MP4 (.mp4, needs imageio-ffmpeg).

    Args:
      path: output file; the suffix picks the format (.gif or .mp4).
      video: (T, H, W), (T, H, W, 1|3|4) float in [0, 1] or uint8; alpha is composited over black.
      fps: frames per second (> 0).
      loop: GIF repeat count (0 = forever).
      colorspace: "linear" (default): values stored as they are; "srgb": `video` is linear RGB
        and is sRGB-encoded (for people: GIF and MP4 players assume sRGB).
    Returns:
      The path written: for .mp4 without imageio-ffmpeg, the same path with suffix .gif (and a
      logged warning saying so).
    """
    import imageio.v3 as iio

    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps={fps!r} must be a finite number > 0")
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise ValueError(f"save_video: path {str(path)!r} must end in .gif or .mp4")
    _check_colorspace(colorspace)
    frames = _rgb_frames(video, colorspace)
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".mp4":
        if _has_ffmpeg():
            h, w = frames.shape[1:3]
            if h % 2 or w % 2:  # yuv420p needs even sizes
                frames = np.pad(frames, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)), mode="edge")
            iio.imwrite(path, frames, plugin="FFMPEG", fps=fps, codec="libx264", macro_block_size=1)
            return path
        gif = path.with_suffix(".gif")
        log.warning(
            "imageio-ffmpeg is not installed, so MP4 cannot be written; wrote GIF %s instead "
            "(pip install 'diffcloth[video]' for MP4)",
            gif,
        )
        path = gif
    iio.imwrite(path, frames, extension=".gif", duration=1000.0 / fps, loop=loop)
    return path


def load_video(path) -> np.ndarray:
    """Read a GIF or MP4 as float32 (T, H, W, 3) in [0, 1]."""
    import imageio.v3 as iio

    path = Path(path)
    if path.suffix.lower() == ".gif":
        a = np.asarray(iio.imread(path, index=None, mode="RGB"))
    else:
        a = np.asarray(iio.imread(path, index=None))
    if a.ndim == 3:  # a single frame
        a = a[None]
    return a[..., :3].astype(np.float32) / 255.0


def side_by_side(target, fit, *, gain: float = 1.0, separator: int = 2) -> np.ndarray:
    """Frames showing target | fit | |target - fit| * gain side by side.

    Args:
      target, fit: images (H, W, C) or videos (T, H, W, C) of the same shape, float in [0, 1].
      gain: brightens the difference panel (clipped to [0, 1]).
      separator: width in pixels of the white lines between panels (>= 0).
    Returns:
      float32 (..., H, 3 W + 2 separator, C).
    """
    t = np.asarray(target, dtype=np.float32)
    f = np.asarray(fit, dtype=np.float32)
    if t.shape != f.shape:
        raise ValueError(f"side_by_side: target shape {t.shape} != fit shape {f.shape}")
    if t.ndim not in (3, 4):
        raise ValueError(f"side_by_side: expected (H, W, C) or (T, H, W, C), got {t.shape}")
    if separator < 0:
        raise ValueError(f"separator={separator} must be >= 0")
    diff = np.clip(np.abs(t - f) * gain, 0.0, 1.0)
    if t.shape[-1] == 4:  # keep the difference panel opaque
        diff[..., 3] = 1.0
    sep = np.ones(t.shape[:-2] + (separator, t.shape[-1]), np.float32)
    return np.concatenate([t, sep, f, sep, diff], axis=-2)


def to_jsonable(obj: Any) -> Any:
    """numpy/JAX arrays and scalars, Paths, dataclass-free containers -> plain JSON values.

    Non-finite floats become None (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (str, bool)) or obj is None:
        return obj
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if hasattr(obj, "shape") and hasattr(obj, "dtype"):  # numpy or jax array / numpy scalar
        a = np.asarray(obj)
        if a.dtype == np.bool_:
            return a.tolist()
        if np.issubdtype(a.dtype, np.integer):
            return a.tolist()
        if a.ndim == 0:
            return to_jsonable(float(a))
        return [to_jsonable(v) for v in a]
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    raise TypeError(f"cannot convert {type(obj).__name__} to JSON")


def save_json(path, obj) -> Path:
    """Write `obj` (dicts/lists of numbers, strings, arrays) as indented JSON. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(to_jsonable(obj), indent=2, allow_nan=False) + "\n")
    return path


def load_json(path) -> Any:
    """Read a JSON file."""
    return json.loads(Path(path).read_text())


def natural_key(p: Path):
    """Sort key for file names with numbers in natural order (frame2 before frame10)."""
    return [int(s) if s.isdigit() else s.lower() for s in re.split(r"(\d+)", p.name)]


_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def check_numbered_sequence(files, where: str = "") -> None:
    """Refuse a frame sequence whose numbering does not run evenly (ValueError naming the missing
    frames): frame_0, frame_1, frame_3 lacks frame_2, and every later image would be matched with
    the wrong rendered frame. The number is the last digit run of each file name; numbering may
    start anywhere and step by any constant (frame_0, frame_2, frame_4 is a sequence). Files of
    two different numbered patterns (frame_#.png next to mask_#.png), or two files with the same
    number (frame_1.png, frame_01.png), are refused too. Names without digits are not checked.

    Args:
      files: paths, in the order they will be used (natural order).
      where: text naming the folder (and pattern) in messages.
    """
    files = [Path(f) for f in files]
    numbered = [(f, _LAST_NUMBER.search(f.name)) for f in files]
    if not any(m for _, m in numbered):
        return
    patterns: dict[str, list] = {}
    for f, m in numbered:
        key = f.name if m is None else f.name[: m.start()] + "#" + f.name[m.end() :]
        patterns.setdefault(key, []).append((f, int(m.group(1)) if m else None))
    if len(patterns) > 1:
        shown = ", ".join(f"{k!r} ({len(v)})" for k, v in list(patterns.items())[:6])
        raise ValueError(
            f"{where}: the matching files follow {len(patterns)} naming patterns ({shown}); "
            "a frame sequence has one (narrow the file pattern, e.g. [fit] target_glob)"
        )
    ((key, entries),) = patterns.items()
    nums = sorted(n for _, n in entries)
    dupes = sorted({n for n in nums if nums.count(n) > 1})
    if dupes:
        names = [f.name for f, n in entries if n == dupes[0]]
        raise ValueError(f"{where}: frame number {dupes[0]} appears twice ({', '.join(names)})")
    if len(nums) < 3:
        step = nums[-1] - nums[0] if len(nums) == 2 else 1
    else:
        step = math.gcd(*(b - a for a, b in zip(nums[:-1], nums[1:], strict=True)))
    expected = range(nums[0], nums[-1] + 1, max(step, 1))
    missing = sorted(set(expected) - set(nums))
    if missing:
        width = len(_LAST_NUMBER.search(entries[0][0].name).group(1))
        example = [key.replace("#", str(n).zfill(width)) for n in missing[:6]]
        raise ValueError(
            f"{where}: the numbered frames {nums[0]} .. {nums[-1]} (step {step}) lack "
            f"{len(missing)} frame(s): {', '.join(example)}{' ...' if len(missing) > 6 else ''}; "
            "image i must show rendered frame i, so a gap would misalign every later frame "
            "(export the missing frames, or renumber the sequence)"
        )


def load_image_sequence(folder, pattern: str = "*.png", *, colorspace: str = "auto") -> np.ndarray:
    """Read a folder of frames (natural order: frame_2 before frame_10) into float32 (T, H, W, C).

    colorspace: as for `load_image`. Raises ValueError when the folder is missing or empty, the
    numbering has a gap (`check_numbered_sequence`), or the frames differ in size or channels
    (naming the odd files).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"target image folder {str(folder)!r} does not exist")
    files = sorted((p for p in folder.glob(pattern) if p.is_file()), key=natural_key)
    if not files:
        raise ValueError(f"no files matching {pattern!r} in {str(folder)!r}")
    check_numbered_sequence(files, f"{str(folder)!r} ({pattern!r})")
    frames = [load_image(p, colorspace=colorspace) for p in files]
    shapes = [f.shape for f in frames]
    common = max(set(shapes), key=shapes.count)
    odd = [f"{p.name}: {s}" for p, s in zip(files, shapes, strict=True) if s != common]
    if odd:
        raise ValueError(
            f"frames in {str(folder)!r} differ in size: most are {common}, but "
            + ", ".join(odd[:6])
            + (" ..." if len(odd) > 6 else "")
        )
    return np.stack(frames)


def save_image_sequence(
    folder, video, prefix: str = "frame_", *, colorspace: str = "linear", bits: int = 8
) -> list[Path]:
    """Write a video (T, H, W, C) as PNGs folder/prefix0000.png, ...; returns the paths.
    colorspace, bits: as for `save_png`."""
    v = _check_video(video)
    folder = Path(folder)
    return [
        save_png(folder / f"{prefix}{i:04d}.png", frame, colorspace=colorspace, bits=bits)
        for i, frame in enumerate(v)
    ]
