"""Issue 35, class 5: targets are read as they are.

One reader (`diffcloth.io.png.read_png`, reached through `load_image` for every PNG) decodes every
standard PNG exactly, interlaced (Adam7) 16-bit files included (they were read through Pillow as
8-bit sRGB: six times too dark); a numbered sequence with a gap is refused naming the missing
frame (`io.media.check_numbered_sequence`, used by `load_targets` and `load_image_sequence`);
float targets outside [0, 1] and ragged lists are refused by `validate_targets`, naming
`targets`. The Adam7 files are written here by a small independent encoder, checked against
Pillow's decoder for 8 bits.
"""

import struct
import zlib

import numpy as np
import pytest
from test_hardening import FIT, TINY, assert_usage_error, run, write

from diffcloth.fit import validate_targets
from diffcloth.io import load_image, load_image_sequence, save_png
from diffcloth.io.media import check_numbered_sequence
from diffcloth.io.png import ADAM7, read_png

COLOR_TYPE = {1: 0, 2: 4, 3: 2, 4: 6}


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _rows(sub: np.ndarray, depth: int, filt: int) -> bytes:
    """Rows of one (sub-)image with filter `filt` (0 none, 1 sub, 2 up) applied per byte."""
    h = sub.shape[0]
    if depth == 16:
        data = sub.astype(">u2").reshape(h, -1).view(np.uint8)
    elif depth == 8:
        data = sub.astype(np.uint8).reshape(h, -1)
    else:  # pack sub-8-bit samples
        bits = ((sub.reshape(h, -1)[..., None] >> np.arange(depth - 1, -1, -1)) & 1).astype(
            np.uint8
        )
        data = np.packbits(bits.reshape(h, -1), axis=1)
    bpp = max(1, sub.shape[-1] * depth // 8)
    out = bytearray()
    prev = np.zeros(data.shape[1], np.int32)
    for r in range(h):
        row = data[r].astype(np.int32)
        if filt == 1:
            left = np.concatenate([np.zeros(bpp, np.int32), row[:-bpp]])
            enc = (row - left) & 0xFF
        elif filt == 2:
            enc = (row - prev) & 0xFF
        else:
            enc = row
        out += bytes([filt]) + enc.astype(np.uint8).tobytes()
        prev = row
    return bytes(out)


def write_png_raw(path, img, *, depth=8, interlace=False, ctype=None, palette=None, filt=1,
                  chunks=b""):  # fmt: skip
    """An independent PNG encoder: (H, W, C) samples, any depth, plain or Adam7."""
    img = np.asarray(img)
    h, w, c = img.shape
    ctype = COLOR_TYPE[c] if ctype is None else ctype
    head = struct.pack(">IIBBBBB", w, h, depth, ctype, 0, 0, int(interlace))
    if interlace:
        raw = b"".join(
            _rows(img[r0::dr, c0::dc], depth, filt)
            for r0, c0, dr, dc in ADAM7
            if img[r0::dr, c0::dc].size
        )
    else:
        raw = _rows(img, depth, filt)
    extra = chunks + (_chunk(b"PLTE", palette.astype(np.uint8).tobytes()) if palette is not None
                      else b"")  # fmt: skip
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", head) + extra
                     + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b""))  # fmt: skip
    return path


RNG = np.random.default_rng(35)


@pytest.mark.parametrize("size", [(1, 1), (3, 5), (9, 7), (16, 16), (17, 10)])
@pytest.mark.parametrize("channels", [1, 2, 3, 4])
@pytest.mark.parametrize("depth", [8, 16])
def test_adam7_round_trips_every_layout_exactly(tmp_path, size, channels, depth):
    top = 65535 if depth == 16 else 255
    img = RNG.integers(0, top + 1, size=(*size, channels)).astype(np.uint16 if depth == 16 else
                                                                    np.uint8)  # fmt: skip
    for filt in (0, 1, 2):
        p = write_png_raw(tmp_path / f"a{filt}.png", img, depth=depth, interlace=True, filt=filt)
        got, info = read_png(p)
        assert got.dtype == img.dtype and info["interlaced"] and info["bit_depth"] == depth
        np.testing.assert_array_equal(got, img)


def test_adam7_8_bit_agrees_with_pillow(tmp_path):
    from PIL import Image

    img = RNG.integers(0, 256, size=(13, 11, 3)).astype(np.uint8)
    p = write_png_raw(tmp_path / "a.png", img, interlace=True)
    with Image.open(p) as im:
        assert im.info.get("interlace") == 1
        np.testing.assert_array_equal(np.asarray(im), img)  # the encoder is right
    np.testing.assert_array_equal(read_png(p)[0], img)


def test_interlaced_16_bit_target_is_read_at_full_depth_not_as_dark_srgb(tmp_path):
    """The issue's case: linear 16-bit values, interlaced. Read through Pillow they were reduced
    to 8 bits and decoded as sRGB: about 6x too dark at 0.25."""
    value = np.full((8, 8, 3), round(0.25 * 65535), np.uint16)
    p = write_png_raw(tmp_path / "frame_0.png", value, depth=16, interlace=True)
    img = load_image(p)  # auto: 16-bit files are linear
    np.testing.assert_allclose(img, 0.25, atol=1e-5)
    srgb = load_image(p, colorspace="srgb")
    assert srgb.max() < 0.06  # what the old path produced by default: ~0.05, 5x darker
    # grey + alpha, the alpha untouched
    ga = np.stack([np.full((5, 6), 1000), np.full((5, 6), 65535)], -1).astype(np.uint16)
    got = load_image(write_png_raw(tmp_path / "ga.png", ga, depth=16, interlace=True))
    np.testing.assert_allclose(got[..., 0], 1000 / 65535, rtol=1e-6)
    assert np.all(got[..., 1] == 1.0)


def test_palette_and_sub_8_bit_pngs_are_read_by_the_same_reader(tmp_path):
    from PIL import Image

    # palette, written by Pillow (8-bit indices), plain and with a tRNS chunk
    rgb = RNG.integers(0, 256, size=(6, 7, 3)).astype(np.uint8)
    im = Image.fromarray(rgb).quantize(colors=16)
    im.save(tmp_path / "p.png")
    got, info = read_png(tmp_path / "p.png")
    np.testing.assert_array_equal(got, np.asarray(im.convert("RGB")))
    # 2-bit palette, interlaced, with transparency for entry 1
    pal = np.array([[0, 0, 0], [255, 0, 0], [0, 255, 0], [0, 0, 255]])
    idx = RNG.integers(0, 4, size=(5, 9, 1)).astype(np.uint8)
    p = write_png_raw(tmp_path / "p2.png", idx, depth=2, ctype=3, palette=pal, interlace=True,
                      chunks=_chunk(b"tRNS", bytes([255, 0])))  # fmt: skip
    got, _ = read_png(p)
    np.testing.assert_array_equal(got[..., :3], pal[idx[..., 0]])
    np.testing.assert_array_equal(got[..., 3], np.where(idx[..., 0] == 1, 0, 255))
    # 1-, 2- and 4-bit grey are scaled to 0..255
    for depth in (1, 2, 4):
        g = RNG.integers(0, 2**depth, size=(4, 11, 1)).astype(np.uint8)
        got, info = read_png(write_png_raw(tmp_path / f"g{depth}.png", g, depth=depth))
        np.testing.assert_array_equal(got, g.astype(np.uint16) * 255 // (2**depth - 1))
        assert info["bit_depth"] == 8 and info["file_bit_depth"] == depth


@pytest.mark.parametrize(
    "depth, ctype, needle",
    [(4, 2, "colour type 2 with bit depth 4"), (16, 3, "colour type 3 with bit depth 16"),
     (8, 5, "colour type 5")],
)  # fmt: skip
def test_invalid_png_headers_are_refused_naming_the_file(tmp_path, depth, ctype, needle):
    p = tmp_path / "bad.png"
    head = struct.pack(">IIBBBBB", 2, 2, depth, ctype, 0, 0, 0)
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", head) + _chunk(b"IDAT", zlib.compress(
        b"\0" * 40)) + _chunk(b"IEND", b""))  # fmt: skip
    with pytest.raises(ValueError, match=needle) as info:
        load_image(p)
    assert "bad.png" in str(info.value)


def test_a_png_is_recognised_by_its_content_and_a_fake_png_is_refused(tmp_path):
    img = np.full((4, 4, 3), 0.5)
    p = save_png(tmp_path / "x.png", img, colorspace="linear", bits=16)
    q = tmp_path / "x.img"
    q.write_bytes(p.read_bytes())
    np.testing.assert_allclose(load_image(q), 0.5, atol=1e-4)
    (tmp_path / "fake.png").write_text("not an image")
    with pytest.raises(ValueError, match="fake.png: not a PNG"):
        load_image(tmp_path / "fake.png")


# ----------------------------------------------------------------------------- numbered sequences


def _frames(folder, names, value=0.3):
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        save_png(folder / n, np.full((16, 16, 3), value), colorspace="srgb")
    return folder


@pytest.mark.parametrize(
    "names, needles",
    [
        (["frame_0.png", "frame_1.png", "frame_3.png"], ["lack 1 frame", "frame_2.png"]),
        (["f_0001.png", "f_0002.png", "f_0004.png"], ["f_0003.png"]),
        (["img7.png", "img8.png", "img10.png"], ["img9.png"]),
        (["frame_0.png", "frame_2.png", "frame_3.png"], ["frame_1.png"]),
        (["frame_0.png", "frame_1.png", "mask_0.png"], ["2 naming patterns", "target_glob"]),
        (["frame_1.png", "frame_01.png", "frame_2.png"], ["frame number 1 appears twice"]),
    ],
    ids=["issue", "padded", "no_separator", "gap_first", "two_patterns", "duplicate"],
)
def test_fit_refuses_a_numbered_sequence_with_a_gap(tmp_path, capsys, names, needles):
    _frames(tmp_path / "targets", names)
    cfg = write(tmp_path, TINY + FIT + 'targets = "targets"\n')
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert_usage_error(code, err, "[fit] targets", *needles)
    assert not (tmp_path / "o").exists()


def test_a_gap_outside_the_chosen_frames_is_still_a_misalignment(tmp_path, capsys):
    """target_frames picks images by index after sorting, so a gap before them shifts them too."""
    _frames(tmp_path / "targets", ["frame_0.png", "frame_2.png", "frame_3.png", "frame_4.png"])
    cfg = write(tmp_path, TINY + FIT + 'targets = "targets"\ntarget_frames = [1, 4]\n')
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert_usage_error(code, err, "frame_1.png")


def test_even_sequences_pass(tmp_path):
    check_numbered_sequence(["a_5.png", "a_6.png", "a_7.png"])  # any start
    check_numbered_sequence(["a_0.png", "a_2.png", "a_4.png"])  # a constant step
    check_numbered_sequence(["left.png", "right.png"])  # no numbers: nothing to check
    check_numbered_sequence(["cam2_f9.png", "cam2_f10.png"])  # the last number counts
    folder = _frames(tmp_path / "s", ["frame_0.png", "frame_2.png", "frame_4.png"])
    assert load_image_sequence(folder).shape == (3, 16, 16, 3)
    _frames(folder, ["frame_8.png"])
    with pytest.raises(ValueError, match="frame_6.png"):
        load_image_sequence(folder)


# ----------------------------------------------------------------------------- validate_targets

SHAPE = (2, 4, 4, 3)


@pytest.mark.parametrize(
    "value, needles",
    [
        (1.5, ["[0.5, 1.5]", "outside the allowed [0, 1]"]),
        (-0.25, ["[-0.25, 0.5]", "outside the allowed [0, 1]"]),
        (1.0 + 1e-3, ["outside the allowed [0, 1]"]),
        (200.0, ["up to 200", "0..255"]),
    ],
    ids=["bright", "negative", "just_above", "looks_8_bit"],
)
def test_float_targets_outside_0_1_are_refused(value, needles):
    targets = np.full(SHAPE, 0.5, np.float32)
    targets[1, 2, 3, 0] = value
    with pytest.raises(ValueError) as info:
        validate_targets(targets, SHAPE)
    msg = str(info.value)
    assert msg.startswith("targets ")
    for n in needles:
        assert n in msg, (n, msg)
    if value in (1.5, -0.25):
        assert "(1, 2, 3, 0)" in msg  # the first bad index


def test_in_range_and_integer_targets_pass_and_opt_outs():
    validate_targets(np.zeros(SHAPE), SHAPE)
    validate_targets(np.ones(SHAPE, np.float64), SHAPE)
    validate_targets(np.full(SHAPE, 255, np.uint8), SHAPE)
    validate_targets(np.full(SHAPE, 65535, np.uint16), SHAPE)
    bright = np.full(SHAPE, 1.2)
    validate_targets(bright, SHAPE, value_range=(0.0, None))  # a rendered (linear HDR) video
    validate_targets(bright, SHAPE, check_range=False)
    with pytest.raises(ValueError, match=r"allowed \[0, inf\]"):
        validate_targets(-bright, SHAPE, value_range=(0.0, None))


@pytest.mark.parametrize(
    "targets, needles",
    [
        ([np.zeros((4, 4, 3)), np.zeros((5, 4, 3))], ["targets is a ragged list", "(5, 4, 3)"]),
        ([np.zeros((4, 4, 3))] * 2 + [np.zeros((4, 4, 4))], ["targets[2] has shape (4, 4, 4)"]),
        ([[np.zeros((4, 4, 3))] * 2, [np.zeros((4, 4, 3))] * 3], ["ragged", "(3,)"]),
        ([[[0.0] * 3] * 4] * 3 + [[[0.0] * 3] * 5], ["ragged", "targets"]),
    ],
    ids=["frame_size", "channels", "cameras", "nested_lists"],
)
def test_ragged_target_lists_name_targets(targets, needles):
    with pytest.raises(ValueError) as info:
        validate_targets(targets, (None, None, None, None))
    msg = str(info.value)
    assert "setting an array element" not in msg and "inhomogeneous" not in msg
    for n in needles:
        assert n in msg, (n, msg)


def test_fit_refuses_ragged_and_0_255_targets_before_compiling(tiny):
    import diffcloth as dc

    ragged = [np.zeros((16, 16, 3))] * 2 + [np.zeros((8, 16, 3))]
    with pytest.raises(ValueError, match="targets is a ragged list"):
        dc.fit.fit(tiny, ragged, ["bend"], steps=1)
    with pytest.raises(ValueError, match="0..255"):
        dc.fit.fit(tiny, np.full(tiny.video_shape, 200.0), ["bend"], steps=1)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    import diffcloth as dc

    return dc.load_scene(write(tmp_path_factory.mktemp("t"), TINY))
