"""PNG / GIF / MP4 fallback / JSON / image folders."""

import json
import logging

import jax.numpy as jnp
import numpy as np
import pytest

import diffcloth.io as dio
from diffcloth.io import media
from diffcloth.io.media import (
    load_image,
    load_image_sequence,
    load_json,
    load_video,
    save_image_sequence,
    save_json,
    save_png,
    save_video,
    side_by_side,
    to_uint8,
)


def _video(t=4, h=12, w=10, c=3, seed=0):
    rng = np.random.default_rng(seed)
    # few distinct colours so the GIF palette is exact
    levels = np.array([0.0, 0.2, 0.6, 1.0])
    return levels[rng.integers(0, 4, size=(t, h, w, c))].astype(np.float32)


def test_all_is_accurate():
    for name in media.__all__:
        assert callable(getattr(media, name)), name
        assert getattr(dio, name) is getattr(media, name)


def test_png_round_trip(tmp_path):
    img = np.linspace(0, 1, 8 * 6 * 3).reshape(8, 6, 3)
    p = save_png(tmp_path / "sub" / "a.png", img)
    back = load_image(p)
    assert back.shape == (8, 6, 3) and back.dtype == np.float32
    np.testing.assert_allclose(back, img, atol=0.5 / 255 + 1e-6)
    grey = load_image(save_png(tmp_path / "g.png", jnp.full((5, 7), 0.2)))
    assert grey.shape == (5, 7, 1)
    np.testing.assert_allclose(grey, 51 / 255, atol=1e-6)
    rgba = load_image(save_png(tmp_path / "c.png", np.full((3, 3, 4), 1.0)))
    assert rgba.shape == (3, 3, 4)


def test_uint8_rule_and_bad_images(tmp_path):
    np.testing.assert_array_equal(
        to_uint8(np.array([-1.0, 0.0, 0.5, 1.0, 2.0])), [0, 0, 128, 255, 255]
    )
    with pytest.raises(ValueError, match="NaN"):
        to_uint8(np.array([0.0, np.nan]))
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        save_png(tmp_path / "x.png", np.zeros((4, 4, 2)))


def test_gif_round_trip(tmp_path):
    v = _video()
    p = save_video(tmp_path / "v.gif", v, fps=10)
    assert p.suffix == ".gif"
    back = load_video(p)
    assert back.shape == v.shape
    np.testing.assert_allclose(back, v, atol=2 / 255)
    # grey and RGBA videos are accepted
    assert load_video(save_video(tmp_path / "g.gif", v[..., 0])).shape == v.shape
    rgba = np.concatenate([v, np.ones_like(v[..., :1])], axis=-1)
    np.testing.assert_allclose(load_video(save_video(tmp_path / "a.gif", rgba)), v, atol=2 / 255)


def test_mp4_falls_back_to_gif_with_message(tmp_path, caplog, monkeypatch):
    monkeypatch.setattr(media, "_has_ffmpeg", lambda: False)
    with caplog.at_level(logging.WARNING, logger="diffcloth.io"):
        p = save_video(tmp_path / "v.mp4", _video())
    assert p == tmp_path / "v.gif" and p.exists() and not (tmp_path / "v.mp4").exists()
    assert "imageio-ffmpeg is not installed" in caplog.text and "v.gif" in caplog.text


def test_save_video_bad_args(tmp_path):
    with pytest.raises(ValueError, match="fps"):
        save_video(tmp_path / "v.gif", _video(), fps=0)
    with pytest.raises(ValueError, match=r"\.gif or \.mp4"):
        save_video(tmp_path / "v.avi", _video())
    with pytest.raises(ValueError, match="no frames"):
        save_video(tmp_path / "v.gif", np.zeros((0, 4, 4, 3)))


def test_side_by_side():
    t = np.zeros((2, 4, 5, 3), np.float32)
    f = np.full((2, 4, 5, 3), 0.25, np.float32)
    out = side_by_side(t, f, gain=2.0, separator=1)
    assert out.shape == (2, 4, 17, 3)
    np.testing.assert_allclose(out[..., :5, :], 0.0)
    np.testing.assert_allclose(out[..., 5, :], 1.0)
    np.testing.assert_allclose(out[..., 6:11, :], 0.25)
    np.testing.assert_allclose(out[..., 12:, :], 0.5)
    assert side_by_side(t[0], f[0], separator=0).shape == (4, 15, 3)
    with pytest.raises(ValueError, match="target shape"):
        side_by_side(t, f[:1])


def test_json_round_trip(tmp_path):
    obj = {
        "a": np.float32(1.5),
        "b": jnp.array([1.0, 2.0]),
        "c": float("nan"),
        "n": np.int64(3),
        "nested": [{"x": np.arange(2)}],
        "ok": True,
    }
    p = save_json(tmp_path / "r.json", obj)
    back = load_json(p)
    assert back == {
        "a": 1.5,
        "b": [1.0, 2.0],
        "c": None,
        "n": 3,
        "nested": [{"x": [0, 1]}],
        "ok": True,
    }
    json.loads(p.read_text())  # strict JSON (no NaN tokens)
    with pytest.raises(TypeError, match="object"):
        save_json(tmp_path / "bad.json", {"x": object()})


def test_image_sequence_round_trip_and_errors(tmp_path):
    v = _video(t=11)
    save_image_sequence(tmp_path / "frames", v)
    # natural order: rename to unpadded names so "frame_10" sorts after "frame_2"
    for p in sorted((tmp_path / "frames").glob("*.png")):
        p.rename(p.with_name(f"f_{int(p.stem.split('_')[1])}.png"))
    back = load_image_sequence(tmp_path / "frames")
    assert back.shape == v.shape
    np.testing.assert_allclose(back, v, atol=0.5 / 255 + 1e-6)
    with pytest.raises(ValueError, match="does not exist"):
        load_image_sequence(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no files"):
        load_image_sequence(tmp_path / "empty")
    save_png(tmp_path / "frames" / "f_11.png", np.zeros((3, 3, 3)))  # next number: no gap
    with pytest.raises(ValueError, match="differ in size"):
        load_image_sequence(tmp_path / "frames")
