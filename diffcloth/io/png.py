"""A small exact PNG codec in numpy + zlib: 8- and 16-bit grey, grey+alpha, RGB and RGBA.

Pillow (and so imageio) reduces 16-bit colour PNGs to 8 bits; this reader keeps every bit.
Decoding undoes the five PNG row filters with a wavefront over anti-diagonals (pixel (r, c)
depends on (r, c-1), (r-1, c) and (r-1, c-1)), so the Python loop runs H + W times, not H * W.
Interlaced (Adam7) and palette files are left to Pillow (`read_png` returns None for them).
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

__all__ = ["read_png", "write_png"]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}  # colour type -> channels
_COLOR_TYPE = {1: 0, 2: 4, 3: 2, 4: 6}  # channels -> colour type


def _chunk(kind: bytes, data: bytes) -> bytes:
    crc = zlib.crc32(kind + data) & 0xFFFFFFFF
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)


def write_png(path, array: np.ndarray, *, srgb_chunk: bool | None = None) -> Path:
    """Write a uint8 or uint16 array (H, W) or (H, W, C), C in 1..4, as PNG (filter 0, zlib 6).

    srgb_chunk: True adds an sRGB chunk (the values are sRGB-encoded), False a gAMA chunk of 1.0
    (the values are linear), None neither.
    """
    a = np.asarray(array)
    if a.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"write_png: array must be uint8 or uint16, got {a.dtype}")
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[-1] not in _COLOR_TYPE or 0 in a.shape[:2]:
        raise ValueError(f"write_png: expected (H, W) or (H, W, 1-4), got {np.shape(array)}")
    h, w, c = a.shape
    depth = 16 if a.dtype == np.uint16 else 8
    rows = a.astype(">u2" if depth == 16 else np.uint8).reshape(h, -1).view(np.uint8)
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], axis=1).tobytes()
    head = struct.pack(">IIBBBBB", w, h, depth, _COLOR_TYPE[c], 0, 0, 0)
    extra = b""
    if srgb_chunk is True:
        extra = _chunk(b"sRGB", b"\x00")
    elif srgb_chunk is False:
        extra = _chunk(b"gAMA", struct.pack(">I", 100000))
    path = Path(path)
    path.write_bytes(
        _SIGNATURE
        + _chunk(b"IHDR", head)
        + extra
        + _chunk(b"IDAT", zlib.compress(raw, 6))
        + _chunk(b"IEND", b"")
    )
    return path


def _unfilter(data: np.ndarray, h: int, stride: int, bpp: int) -> np.ndarray:
    """Undo the PNG filters: data (h, 1 + stride) uint8 -> (h, stride) uint8."""
    ftype = data[:, 0]
    if np.any(ftype > 4):
        raise ValueError(f"corrupt PNG: unknown row filter {int(ftype.max())}")
    raw = data[:, 1:].astype(np.int32)
    if np.all(ftype == 0):
        return raw.astype(np.uint8)
    w = stride // bpp
    px = raw.reshape(h, w, bpp)
    out = np.zeros((h + 1, w + 1, bpp), np.int32)  # padded: row 0 and column 0 are zeros
    for d in range(h + w - 1):
        r = np.arange(max(0, d - w + 1), min(h - 1, d) + 1)
        c = d - r
        a = out[r + 1, c]  # left
        b = out[r, c + 1]  # up
        ul = out[r, c]  # upper left
        f = ftype[r][:, None]
        p = a + b - ul
        pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - ul)
        paeth = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, ul))
        pred = np.select([f == 1, f == 2, f == 3, f == 4], [a, b, (a + b) // 2, paeth], 0)
        out[r + 1, c + 1] = (px[r, c] + pred) & 0xFF
    return out[1:, 1:].reshape(h, stride).astype(np.uint8)


def read_png(path) -> tuple[np.ndarray, dict] | None:
    """Read a PNG exactly: (uint8 or uint16 array (H, W, C), info) or None if this reader does not
    handle the file (palette, interlaced or sub-8-bit PNGs; read those with Pillow).

    info: {"bit_depth", "srgb" (an sRGB chunk is present), "gamma" (gAMA value or None)}.
    Raises ValueError for a file that is not a valid PNG.
    """
    blob = Path(path).read_bytes()
    if not blob.startswith(_SIGNATURE):
        raise ValueError(f"{path}: not a PNG file")
    pos, idat, head = 8, [], None
    info = {"srgb": False, "gamma": None}
    while pos + 8 <= len(blob):
        (length,) = struct.unpack(">I", blob[pos : pos + 4])
        kind = blob[pos + 4 : pos + 8]
        data = blob[pos + 8 : pos + 8 + length]
        if len(data) != length:
            raise ValueError(f"{path}: truncated PNG chunk {kind!r}")
        pos += 12 + length
        if kind == b"IHDR":
            head = struct.unpack(">IIBBBBB", data)
        elif kind == b"IDAT":
            idat.append(data)
        elif kind == b"sRGB":
            info["srgb"] = True
        elif kind == b"gAMA" and length == 4:
            info["gamma"] = struct.unpack(">I", data)[0] / 100000.0
        elif kind == b"IEND":
            break
    if head is None or not idat:
        raise ValueError(f"{path}: PNG without IHDR or image data")
    w, h, depth, ctype, _, _, interlace = head
    if ctype not in _CHANNELS or depth not in (8, 16) or interlace:
        return None
    info["bit_depth"] = depth
    c = _CHANNELS[ctype]
    bpp = c * depth // 8
    stride = w * bpp
    try:
        raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8)
    except zlib.error as err:
        raise ValueError(f"{path}: corrupt PNG data ({err})") from None
    if raw.size < h * (stride + 1):
        raise ValueError(f"{path}: PNG data too short for {w}x{h}")
    rows = _unfilter(raw[: h * (stride + 1)].reshape(h, stride + 1), h, stride, bpp)
    if depth == 16:
        img = rows.reshape(h, w * c * 2).view(">u2").astype(np.uint16)
    else:
        img = rows
    return img.reshape(h, w, c), info
