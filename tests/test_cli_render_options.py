"""LOD, [[deform]] waves and object culling reach `diffcloth render` (issue 14 acceptance 4):
the CLI entry `main` on tiny configs (16 px, 5 x 5 net, 2 frames, a pinned cloth so frames differ
only through the waves; no gravity, so the box body stays put)."""

import numpy as np
import pytest

from diffcloth import config as cfg
from diffcloth import scene, surface

BASE = """
[net]
rows = 5
cols = 5
width = 0.8
height = 0.8
center = [0.0, 0.5, 0.0]
pinned = "all"

[sim]
num_frames = 2
integrator = "implicit"
num_substeps = 1
gravity = [0.0, 0.0, 0.0]

[render]
width = 16
height = 16
{render}

[appearance]
diffuse = [0.1, 0.2, 0.9]
sphere_color = [0.9, 0.6, 0.1]

[[cameras]]
eye = [0.0, 1.4, 1.2]
target = [0.0, 0.5, 0.0]

[[cameras]]
eye = [0.0, 1.4, 1.2]
target = [0.0, 1.4, 6.0]
"""
WAVES = """
[[deform]]
kind = "waves"
amplitude = 0.08
wavelength = 0.5
speed = 6.0
"""
BOX = """
[[bodies]]
shape = "box"
mass = 1.0
half_extents = [0.12, 0.12, 0.12]
position = [0.25, 0.75, 0.1]
"""
# every option on: tessellation level from the projected size, culling, travelling waves (and
# a box body, which the CLI video must draw)
ALL_ON = BASE.format(render='lod = "auto"\ncull = true') + WAVES + BOX
# every option off: fixed level 8, no culling, no deformation
ALL_OFF = BASE.format(render="level = 8")


@pytest.mark.slow  # two CLI runs (simulate + render compiles, ~60 s CPU)
def test_lod_deform_and_cull_reach_the_cli(tmp_path, capsys):
    from diffcloth.cli import main

    videos, logs = {}, {}
    for name, text in (("on", ALL_ON), ("off", ALL_OFF)):
        path = tmp_path / f"{name}.toml"
        path.write_text(text)
        out = tmp_path / name
        argv = ["render", str(path), "--out", str(out), "--format", "gif", "--npy", "--chunk", "2"]
        assert main(argv) == 0
        logs[name] = capsys.readouterr().out
        videos[name] = np.load(out / "video.npy")
    on, off = videos["on"], videos["off"]
    assert on.shape == off.shape == (2, 2, 16, 16, 3)  # (cameras, frames, H, W, rgb)
    # lod: the auto level (about 4 px per mesh segment: 2 for a ~10 px cloth) is the one used and
    # logged instead of the fixed level 8, so the mesh has far fewer vertices
    sc = scene.build_scene(cfg.load_config(tmp_path / "on.toml"))
    level = sc.level
    assert level == 2 and sc.cull and len(sc.deform) == 1
    assert f"level {level} (lod auto), culling on, 1 deformations, 1 rigid bodies" in logs["on"]
    assert "level 8 (lod fixed), culling off, 0 deformations" in logs["off"]
    n_on = surface.tessellate(sc.state.x, level, sc.basis).positions.shape[0]
    n_off = surface.tessellate(sc.state.x, 8, sc.basis).positions.shape[0]
    assert n_on < n_off / 4
    # deform: the pinned cloth does not move, so without waves both frames are equal; the
    # travelling waves move pixels and differ between the frames
    seen_on, seen_off = on[0], off[0]
    assert np.abs(seen_off[1] - seen_off[0]).max() < 1e-6
    assert np.abs(seen_on[1] - seen_on[0]).max() > 0.02
    assert np.abs(seen_on[0] - seen_off[0]).max() > 0.02
    # the box body is drawn in the CLI video: orange pixels (its sphere_color) on the blue cloth
    orange = lambda v: (v[..., 0] > v[..., 2] + 0.2).sum()  # noqa: E731
    assert orange(seen_on[0]) >= 4 and orange(seen_off[0]) == 0
    # cull: camera 1 looks away from the cloth; with culling its triangles are dropped and the
    # image is the background, exactly as without culling
    bg = np.asarray(sc.background, np.float32)
    np.testing.assert_array_equal(on[1], off[1])
    np.testing.assert_allclose(on[1], np.broadcast_to(bg, on[1].shape), atol=1e-7)
