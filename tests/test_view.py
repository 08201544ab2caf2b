"""The browser viewer (`diffcloth view`, diffcloth/view/).

Model tests (re-simulation, forces, cameras, fit folders) need only the core. Tests marked
`browser` drive the real viewer in headless Chromium through playwright, on 127.0.0.1 only; they
skip, naming what is missing, without viser, playwright or a Chromium binary. Install all three:

    apt-get install -y chromium && pip install -e ".[view-test]"

(or `python -m playwright install chromium` where playwright may download its own browser; set
DIFFCLOTH_CHROMIUM=/path/to/chrome to pick a binary). With DIFFCLOTH_REQUIRE_BROWSER=1, as in
.ci/run, each of these skips fails instead.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from viewer_deps import need as _need
from viewer_deps import skip_or_fail as _skip

# A small drape with a strongly red cloth (so cloth pixels are easy to find in screenshots), one
# sphere and a floor; 12 frames keep the compile short.
SCENE = """
[net]
rows = 10
cols = 13
width = 1.2
height = 0.9
center = [0.0, 1.0, 0.0]
plane = "xz"

[material]
stretch = 200.0
shear = 50.0
bend = 1e-4
damping = 1e-4
density = 0.2
drag_normal = 0.5

[sim]
dt = 0.0333333333333
num_frames = 12
num_substeps = 40

[[spheres]]
center = [0.0, 0.5, 0.0]
radius = 0.3

[[planes]]
normal = [0.0, 1.0, 0.0]
offset = 0.0

[render]
width = 32
height = 32
level = 3

[[cameras]]
eye = [0.0, 1.6, 2.2]
target = [0.0, 0.6, 0.0]

[[cameras]]
eye = [2.0, 1.0, 0.3]
target = [0.0, 0.5, 0.0]

[appearance]
diffuse = [0.8, 0.03, 0.03]
"""

BALL = """
[net]
rows = 6
cols = 6
width = 0.8
height = 0.8
center = [0.0, 0.0, 0.0]
plane = "xy"
pinned = "top_row"

[sim]
dt = 0.0166666666667
num_frames = 8
num_substeps = 16

[[planes]]
normal = [0.0, 1.0, 0.0]
offset = -0.8

[[bodies]]
shape = "sphere"
radius = 0.15
mass = 0.2
position = [0.0, -0.2, 0.5]
velocity = [0.0, 0.0, -3.0]

[render]
width = 16
height = 16
flip = false
"""


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("view") / "drape.toml"
    path.write_text(SCENE)
    return path


@pytest.fixture(scope="module")
def model(scene_path):
    from diffcloth.view.model import load_view

    return load_view(scene_path, level=6)


# ---- core: the viewer stays out of `import diffcloth`; the CLI explains a missing extra -----
def test_import_diffcloth_does_not_import_the_viewer():
    code = (
        "import sys, diffcloth, diffcloth.cli; "
        "bad = [m for m in sys.modules if m.split('.')[0] in ('viser', 'playwright') "
        "or m.startswith('diffcloth.view')]; "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True, env={**os.environ})


def test_cli_view_without_the_extra_says_how_to_install(monkeypatch, capsys, scene_path):
    from diffcloth import cli

    monkeypatch.setitem(sys.modules, "viser", None)  # `import viser` now raises ImportError
    monkeypatch.delitem(sys.modules, "diffcloth.view.cli", raising=False)
    assert cli.main(["view", str(scene_path), "--no-cache"]) == 2
    err = capsys.readouterr().err
    assert "pip install 'diffcloth[view]'" in err and "viser" in err


def test_cli_view_export_and_bad_path(tmp_path, capsys, scene_path, model):
    _need("viser", "the viewer needs the `view` extra: pip install viser")
    from diffcloth import cli

    out = tmp_path / "rec.html"
    # same level and image size as the `model` fixture: the compiled function is reused
    argv = ["view", str(scene_path), "--export", str(out), "--level", "6", "--size", "32"]
    assert cli.main(argv + ["--no-cache"]) == 0
    html = out.read_text()
    assert "__VISER_EMBED_DATA__" in html and html.rstrip().endswith("</html>")
    assert f"wrote {out}" in capsys.readouterr().out
    assert cli.main(["view", str(tmp_path / "missing.toml"), "--no-cache"]) == 2
    assert "no such config file or result folder" in capsys.readouterr().err


# ---- the model: frames, re-simulation, forces, cameras, fit folders ------------------------------
def test_frames_are_the_tessellated_collided_cloth(model):
    from diffcloth import surface

    f = model.frames
    T = model.num_frames
    grid = surface.vertex_grid_shape((10, 13), 6, "bspline")
    assert f.cloth.shape == (T, grid[0] * grid[1], 3) and bool(f.ok)
    assert model.faces.shape == (2 * (grid[0] - 1) * (grid[1] - 1), 3)
    assert model.faces.max() == f.cloth.shape[1] - 1
    # the last frame rests on the sphere: no vertex inside it
    d = np.linalg.norm(f.cloth[-1] - np.array([0.0, 0.5, 0.0]), axis=-1)
    assert d.min() >= 0.3 - 1e-5
    assert model.cloth_color[0] > 200 and model.cloth_color[1] < 60  # sRGB of the red diffuse


def test_slider_resimulation_changes_the_cloth_without_recompiling(model):
    from diffcloth.view.model import _SIMULATE

    before = model.frames.cloth.copy()
    cache = _SIMULATE._cache_size()
    wall = model.resimulate({"stretch": 2.0, "wind": [3.0, 0.0, 0.0]})
    assert _SIMULATE._cache_size() == cache  # new values, same compiled program
    assert wall > 0 and model.log[-1].startswith("re-simulation")
    after = model.frames.cloth
    assert np.abs(after[-1] - before[-1]).max() > 0.01  # a much softer cloth in a side wind
    np.testing.assert_allclose(after[0][:, 1], before[0][:, 1], atol=0.01)  # frame 0 still flat
    model.resimulate({"stretch": 200.0, "wind": [0.0, 0.0, 0.0]})
    np.testing.assert_allclose(model.frames.cloth, before, atol=1e-6)


def test_unstable_values_keep_the_previous_frames(model):
    before = model.frames.cloth.copy()
    values = dict(model.values)
    with pytest.raises(ValueError, match="unstable"):
        model.resimulate({"stretch": 1e9})
    np.testing.assert_array_equal(model.frames.cloth, before)
    assert model.values["stretch"] == values["stretch"]
    with pytest.raises(ValueError, match="unknown slider"):
        model.resimulate({"gravity": 1.0})


def test_camera_poses_come_back_from_the_matrices(model):
    from diffcloth import render
    from diffcloth.view.model import camera_pose

    eye, target = np.array([0.3, 1.6, 2.2]), np.array([0.1, 0.6, -0.2])
    cam = render.make_camera(eye, target, (0, 1, 0), width=8, height=8, fov_y=40.0)
    pose = camera_pose(cam)
    np.testing.assert_allclose(pose["eye"], eye, atol=1e-9)
    fwd = (target - eye) / np.linalg.norm(target - eye)
    np.testing.assert_allclose(pose["look_at"] - pose["eye"], fwd, atol=1e-9)
    assert pose["fov"] == pytest.approx(np.radians(40.0))
    assert len(model.cameras()) == 2


def test_push_and_thruster_change_only_the_frames_after_the_current_one(tmp_path, model):
    from diffcloth.view.model import load_view

    with pytest.raises(ValueError, match="no rigid bodies"):
        model.push(0, 0, [0.0, 1.0, 0.0])
    path = tmp_path / "ball.toml"
    path.write_text(BALL)
    m = load_view(path, level=3)
    base = m.frames.body_position.copy()
    t = 3
    m.push(0, t, [0.0, 2.0, 0.0])
    pos = m.frames.body_position
    np.testing.assert_array_equal(pos[: t + 1], base[: t + 1])
    # one frame after the push the ball is higher by about dv * dt (gravity acts on both runs)
    rise = pos[t + 1, 0, 1] - base[t + 1, 0, 1]
    assert rise == pytest.approx(2.0 * m.dt, rel=0.15)
    pushed = pos.copy()
    m.fire(0, t, [1.0, 0.0, 0.0], accel=30.0, frames=3)
    pos = m.frames.body_position
    np.testing.assert_array_equal(pos[: t + 1], pushed[: t + 1])
    assert pos[-1, 0, 0] - pushed[-1, 0, 0] > 0.5 * 30.0 * (3 * m.dt) ** 2 * 0.5
    with pytest.raises(ValueError, match="out of range"):
        m.push(3, 0, [0, 1, 0])
    with pytest.raises(ValueError, match="direction"):
        m.fire(0, 0, [0, 0, 0], 1.0, 1)


def test_fit_result_folder_shows_target_and_fit(tmp_path, scene_path):
    from diffcloth.view.model import load_view

    folder = tmp_path / "fit"
    folder.mkdir()
    (folder / "config.toml").write_text(
        SCENE + '\n[truth]\nbend = 2e-3\n\n[fit]\nfree = ["bend"]\nsteps = 3\n'
    )
    summary = {
        "params": {"bend": {"true": 2e-3, "initial": 1e-4, "fitted": 1.9e-3,
                            "relative_error": 0.05}},
        "loss": 1e-4, "iterations": 3, "wall_s": 1.0,
    }  # fmt: skip
    (folder / "result.json").write_text(json.dumps(summary))
    (folder / "metrics.jsonl").write_text(
        "\n".join(json.dumps({"step": k, "loss": 10.0**-k}) for k in range(3))
    )
    m = load_view(folder, level=6)
    assert m.values["bend"] == pytest.approx(1.9e-3)
    assert m.target is not None
    gap = np.abs(m.target.cloth[-1] - m.frames.cloth[-1]).max()
    assert 0 < gap < 0.05  # bend 2e-3 against 1.9e-3: close, not equal
    np.testing.assert_allclose(m.fit.loss, [1.0, 0.1, 0.01])
    table = m.fit.table_markdown()
    assert "| bend | 0.002 | 0.0001 | 0.0019 | 5 % |" in table
    with pytest.raises(ValueError, match="not a fit result"):
        load_view(tmp_path)


# ---- browser tests ------------------------------------------------------------------------------
def _chromium() -> str | None:
    for c in (os.environ.get("DIFFCLOTH_CHROMIUM"), "chromium", "chromium-browser", "chrome"):
        if c and (shutil.which(c) or Path(c).is_file()):
            return shutil.which(c) or c
    return None


@pytest.fixture(scope="module")
def browser():
    _need("viser", "the viewer needs the `view` extra: pip install viser")
    pw = _need(
        "playwright.sync_api", "browser tests need playwright: pip install -e '.[view-test]'"
    )
    exe = _chromium()
    with pw.sync_playwright() as p:
        if exe is None and not Path(p.chromium.executable_path).exists():
            _skip(
                "no Chromium found: apt-get install -y chromium (or set DIFFCLOTH_CHROMIUM, or "
                "python -m playwright install chromium)"
            )
        b = p.chromium.launch(
            executable_path=exe,
            args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
        )
        yield b
        b.close()


def _red_mask(png: bytes) -> np.ndarray:
    import io

    import imageio.v3 as iio

    img = iio.imread(io.BytesIO(png))[..., :3].astype(int)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    # red to pink (the lit cloth), not orange (the notification bar), white, grey or yellow
    return (r > 110) & (r - np.maximum(g, b) > 60) & (np.abs(g - b) < 40)


def _open(browser, url, *, offline=False):
    ctx = browser.new_context(viewport={"width": 640, "height": 480}, offline=offline)
    page = ctx.new_page()
    errors = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_selector("canvas", timeout=30_000)
    return ctx, page, errors


def _wait_for_red(page, min_pixels=300, timeout=30.0):
    t0 = time.perf_counter()
    while True:
        mask = _red_mask(page.screenshot(timeout=60_000))
        if mask.sum() >= min_pixels or time.perf_counter() - t0 > timeout:
            return mask
        time.sleep(0.5)


@pytest.mark.browser
def test_viewer_in_chromium_shows_the_cloth_and_a_slider_resimulates(browser, model, caplog):
    from diffcloth.view.app import Viewer

    viewer = Viewer(model, host="127.0.0.1", port=None, autoplay=False)
    ctx = None
    try:
        assert viewer.url.startswith("http://127.0.0.1:")
        ctx, page, errors = _open(browser, viewer.url)
        page.wait_for_selector("text=Connected", timeout=30_000)
        before = _wait_for_red(page)
        assert before.sum() >= 300, f"only {before.sum()} cloth-coloured pixels"
        assert not errors, errors

        runs = model.resim_count
        label = page.locator("label", has_text="log10 stretch")
        thumb = page.locator(f"[id='{label.get_attribute('for')}'] [role=slider]")
        with caplog.at_level(logging.INFO, logger="diffcloth.view"):
            thumb.focus()
            thumb.press("Home")  # stretch / 100: a much softer cloth
            t0 = time.perf_counter()
            while model.resim_count == runs and time.perf_counter() - t0 < 30:
                time.sleep(0.05)
            assert model.resim_count > runs, "no re-simulation after the slider moved"
            time.sleep(1.0)
            after = _red_mask(page.screenshot(timeout=60_000))
        assert model.values["stretch"] == pytest.approx(2.0, rel=0.05)
        assert any("re-simulated" in r.getMessage() for r in caplog.records)
        changed = (after != before).sum()
        assert changed > 100, f"the cloth barely changed on screen ({changed} pixels)"
        assert viewer.latencies and max(viewer.latencies) < 30
        assert not errors, errors
    finally:
        if ctx is not None:
            ctx.close()
        viewer.stop()
        model.resimulate({"stretch": 200.0})


@pytest.mark.browser
def test_exported_html_plays_offline(browser, model, tmp_path):
    from diffcloth.view.app import export_html

    path = export_html(model, tmp_path / "viewer.html")
    html = path.read_text()
    assert "__VISER_EMBED_DATA__" in html
    ctx, page, errors = _open(browser, path.as_uri(), offline=True)
    try:
        mask = _wait_for_red(page)
        assert mask.sum() >= 300, f"only {mask.sum()} cloth-coloured pixels in the recording"
        assert not errors, errors
        remote = [u for u in page.evaluate(
            "performance.getEntriesByType('resource').map(e => e.name)"
        ) if not u.startswith(("file:", "data:", "blob:"))]  # fmt: skip
        assert not remote, remote
    finally:
        ctx.close()


def test_fit_reports_link_the_viewer_recording(tmp_path):
    from diffcloth.fit.loop import FitResult, History
    from diffcloth.report import write_fit_report

    n = 3
    p = {"bend": np.array(1e-3)}
    hist = History(
        loss=np.geomspace(1.0, 1e-3, n), params={"bend": np.full(n, 1e-3)},
        grad_norm={"bend": np.ones(n)}, wall_s=np.linspace(0.0, 1.0, n),
    )  # fmt: skip
    result = FitResult(
        params=p, raw=p, loss=1e-3, initial=p, history=hist, iterations=n, wall_s=1.0,
        status="max_steps", message="", best_step=n, last_finite=p,
    )  # fmt: skip
    out = tmp_path / "fit"
    md = write_fit_report(out, result, plots=False)["report"].read_text()
    assert "[viewer.html](viewer.html)" in md
    assert "`diffcloth view DIR --export DIR/viewer.html`" in md
