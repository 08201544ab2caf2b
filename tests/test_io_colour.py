"""Colour encodings and exact PNG bits (issues 14 item 5 and 15 item 7): 8- and 16-bit sRGB and
linear round trips, the "auto" rule, PNG filters decoded exactly, and sRGB files for people."""

import struct
import zlib

import numpy as np
import pytest

from diffcloth.io import linear_to_srgb, load_image, save_png, save_video, srgb_to_linear
from diffcloth.io.png import read_png, write_png

RNG = np.random.default_rng(7)


def test_transfer_functions_are_inverse_and_standard():
    x = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    # IEC 61966-2-1 reference points: linear 0.5 -> 0.7354, 0.0031308 -> 0.04045 (the knee)
    np.testing.assert_allclose(linear_to_srgb([0.5, 0.0031308, 1.0]), [0.735357, 0.04045, 1.0],
                               atol=1e-5)  # fmt: skip


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("colorspace", ["srgb", "linear"])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_png_round_trips(tmp_path, bits, colorspace, channels):
    img = RNG.random((7, 9, channels))
    p = save_png(tmp_path / "a.png", img, colorspace=colorspace, bits=bits)
    q = 2**bits - 1
    back = load_image(p)  # "auto" reads the chunk written by save_png
    assert back.shape == (7, 9, channels) and back.dtype == np.float32
    same = load_image(p, colorspace=colorspace)
    np.testing.assert_array_equal(back, same)
    if colorspace == "linear":
        np.testing.assert_allclose(back, img, atol=0.5 / q + 1e-6)
    else:  # quantised in sRGB, so compare in sRGB: within half a quantisation step
        c = min(channels, 3)
        enc = linear_to_srgb(img[..., :c])
        np.testing.assert_allclose(linear_to_srgb(back[..., :c]), enc, atol=0.5 / q + 1e-6)
        if channels == 4:  # alpha is never converted
            np.testing.assert_allclose(back[..., 3], img[..., 3], atol=0.5 / q + 1e-6)
    raw = read_png(p)[0]
    assert raw.dtype == (np.uint16 if bits == 16 else np.uint8)
    np.testing.assert_allclose(load_image(p, colorspace="linear"), raw / q, rtol=1e-7)  # float32


def _filtered_png(path, a: np.ndarray, filters):
    """Encode with the given per-row PNG filters (the reference definitions, pixel by pixel)."""
    h, w, c = a.shape
    depth = 16 if a.dtype == np.uint16 else 8
    rows = a.astype(">u2" if depth == 16 else np.uint8).reshape(h, -1).view(np.uint8).astype(int)
    bpp = c * depth // 8
    out = []
    for r in range(h):
        f = filters[r % len(filters)]
        line = [f]
        for i in range(rows.shape[1]):
            x = rows[r, i]
            a_ = rows[r, i - bpp] if i >= bpp else 0
            b_ = rows[r - 1, i] if r else 0
            c_ = rows[r - 1, i - bpp] if r and i >= bpp else 0
            p = a_ + b_ - c_
            pa, pb, pc = abs(p - a_), abs(p - b_), abs(p - c_)
            paeth = a_ if pa <= pb and pa <= pc else (b_ if pb <= pc else c_)
            pred = [0, a_, b_, (a_ + b_) // 2, paeth][f]
            line.append((x - pred) % 256)
        out.append(bytes(line))

    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))

    ctype = {1: 0, 2: 4, 3: 2, 4: 6}[c]
    head = struct.pack(">IIBBBBB", w, h, depth, ctype, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", head)
        + chunk(b"IDAT", zlib.compress(b"".join(out)))
        + chunk(b"IEND", b"")
    )


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_every_png_filter_decodes_exactly(tmp_path, dtype):
    top = np.iinfo(dtype).max
    a = RNG.integers(0, top + 1, size=(6, 5, 3)).astype(dtype)
    a[2:4] = top // 3  # flat rows, where Up/Paeth matter
    _filtered_png(tmp_path / "f.png", a, filters=[0, 1, 2, 3, 4, 4, 3])
    got, info = read_png(tmp_path / "f.png")
    np.testing.assert_array_equal(got, a)
    assert info["bit_depth"] == (16 if dtype == np.uint16 else 8) and not info["srgb"]


def test_auto_rule_without_chunks_and_bad_arguments(tmp_path):
    write_png(tmp_path / "8.png", np.full((2, 2, 3), 188, np.uint8))
    write_png(tmp_path / "16.png", np.full((2, 2, 3), 40000, np.uint16))
    np.testing.assert_allclose(load_image(tmp_path / "8.png")[0, 0, 0],
                               srgb_to_linear(188 / 255), rtol=1e-6)  # fmt: skip
    np.testing.assert_allclose(load_image(tmp_path / "16.png")[0, 0, 0], 40000 / 65535, rtol=1e-6)
    with pytest.raises(ValueError, match="colorspace='rgb'; allowed: 'srgb', 'linear'"):
        save_png(tmp_path / "x.png", np.zeros((2, 2, 3)), colorspace="rgb")
    with pytest.raises(ValueError, match="bits=12"):
        save_png(tmp_path / "x.png", np.zeros((2, 2, 3)), bits=12)
    with pytest.raises(ValueError, match="colorspace="):
        load_image(tmp_path / "8.png", colorspace="gamma")
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="not a PNG"):
        load_image(tmp_path / "bad.png")


def test_images_for_people_are_srgb_encoded(tmp_path):
    import imageio.v3 as iio

    lin = np.full((1, 4, 4, 3), 0.2)
    save_video(tmp_path / "v.gif", lin, colorspace="srgb")
    got = iio.imread(tmp_path / "v.gif", index=None, mode="RGB")
    assert abs(int(got[0, 0, 0, 0]) - round(255 * float(linear_to_srgb(0.2)))) <= 1  # 124, not 51
    p = save_png(tmp_path / "p.png", lin[0], colorspace="srgb")
    assert read_png(p)[1]["srgb"]  # marked, so viewers and load_image know
    np.testing.assert_allclose(load_image(p), 0.2, atol=0.003)


def test_fit_report_compare_gif_is_srgb_and_says_so(tmp_path):
    import imageio.v3 as iio

    from diffcloth.fit.loop import FitResult, History
    from diffcloth.report import write_fit_report

    h = History(loss=np.array([1.0, 0.5]), params={"bend": np.array([1.0, 2.0])},
                grad_norm={"bend": np.array([1.0, 0.1])}, wall_s=np.array([0.0, 1.0]))  # fmt: skip
    r = FitResult(params={"bend": np.array(2.0)}, raw={"bend": np.array(0.7)}, loss=0.5,
                  initial={"bend": np.array(1.0)}, history=h, iterations=1, wall_s=1.0,
                  status="max_steps", message="", best_step=1,
                  last_finite={"bend": np.array(2.0)})  # fmt: skip
    target = np.full((2, 4, 4, 3), 0.2)
    write_fit_report(tmp_path, r, target=target, fitted=target, plots=False)
    gif = iio.imread(tmp_path / "compare.gif", index=None, mode="RGB")
    assert abs(int(gif[0, 0, 0, 0]) - round(255 * float(linear_to_srgb(0.2)))) <= 1
    md = (tmp_path / "report.md").read_text()
    assert "sRGB-encoded" in md
    res = (tmp_path / "result.json").read_text()
    assert '"status": "max_steps"' in res
