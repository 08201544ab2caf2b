"""The browser viewer on triangle-mesh cloth (`diffcloth view` of [cloth] shape configs,
diffcloth/view/mesh.py): frames of the shipped drape and tablecloth configs (coarser copies),
colliders, fabric sliders that re-solve the equilibrium, the render panel, the viser GUI and the
--export recording. All plain Python (no browser); the dynamic rollout is `slow` (its compile)."""

from __future__ import annotations

import re
from pathlib import Path

import jax
import numpy as np
import pytest
from viewer_deps import need as _need

ROOT = Path(__file__).resolve().parent.parent
SIZE = 24  # render panel size of every model here (one compiled render program)


@pytest.fixture(autouse=True)
def _allow_rank_promotion():
    """physics/mesh/hessian.py broadcasts (m, 3, 3, 1, 1) with (3, 3) (as in test_mesh_pipeline)."""
    with jax.numpy_rank_promotion("allow"):
        yield


def _coarse(tmp_path: Path, name: str, edge: float, extra: str = "") -> Path:
    """A copy of configs/NAME.toml with [cloth] edge_length = edge (and `extra` appended)."""
    text = (ROOT / "configs" / f"{name}.toml").read_text()
    text, n = re.subn(r"(?m)^edge_length = [0-9.]+", f"edge_length = {edge}", text)
    assert n == 1
    path = tmp_path / f"{name}.toml"
    path.write_text(text + extra)
    return path


@pytest.fixture(scope="module")
def cusick_path(tmp_path_factory):
    # 95 vertices instead of ~630: the same pedestal, clamp and fold seeding
    return _coarse(tmp_path_factory.mktemp("view_mesh"), "cusick", 0.03)


@pytest.fixture(scope="module")
def cusick(cusick_path):
    from diffcloth.view.model import load_view

    with jax.numpy_rank_promotion("allow"):
        return load_view(cusick_path, size=SIZE)


# ---- the drape: one frame, the pedestal, fabric sliders -------------------------------------------
def test_cusick_frames_are_the_rest_shape_on_the_pedestal(cusick):
    from diffcloth.view.mesh import MESH_SLIDERS

    m = cusick
    n = int(m.scene.net.rest.shape[0])
    assert m.kind == "mesh" and m.level is None
    assert m.num_frames == 1 and m.frames.cloth.shape == (1, n, 3) and bool(m.frames.ok)
    np.testing.assert_array_equal(m.faces, np.asarray(m.scene.net.faces))
    assert m.faces.min() == 0 and m.faces.max() == n - 1
    assert bool(m.mesh_status["converged"][0]) and m.mesh_status["iterations"][0] > 0
    assert "static equilibrium" in m.describe() and f"{n:,} vertices" in m.describe()
    x = m.frames.cloth[0]
    r = np.hypot(x[:, 0], x[:, 2])
    # the clamped middle stays on the pedestal top, the free rim hangs over its edge
    np.testing.assert_allclose(x[r < 0.08, 1], 0.0015, atol=1e-6)
    assert x[:, 1].min() < -0.03
    assert not np.any((r < 0.09 - 1e-4) & (x[:, 1] < -1e-4))  # nothing inside the pedestal
    # sliders: the fabric's fields (equilibrium: no wind, no damping), values from the preset
    assert list(m.sliders) == list(MESH_SLIDERS) and not m.has_wind and m.sliders_note is None
    assert m.values["density"] == pytest.approx(0.187) and "wind" not in m.values
    # colliders: the floor plane and the pedestal as a capped cylinder
    assert [(tuple(nrm), off) for nrm, off in m.planes()] == [((0.0, 1.0, 0.0), -0.3)]
    assert m.boxes() == [] and m.static_spheres() == []
    ((kind, v, f),) = m.collider_meshes()
    assert kind == "cylinder" and f.max() == len(v) - 1
    np.testing.assert_allclose(np.hypot(v[:-2, 0], v[:-2, 2]), 0.09)
    assert v[:, 1].max() == pytest.approx(0.0) and v[:, 1].min() == pytest.approx(-0.3)


def test_cylinder_mesh_faces_point_outwards():
    from diffcloth.view.mesh import cylinder_mesh

    v, f = cylinder_mesh((0.1, 0.0, -0.2), 0.05, 0.3, segments=16)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    normal = np.cross(b - a, c - a)
    out = (a + b + c) / 3 - np.array([0.1, -0.15, -0.2])  # from the cylinder's centre
    assert np.all(np.sum(normal * out, axis=1) > 0)
    # closed: every edge is shared by exactly two faces
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)


def test_fabric_slider_resolves_the_drape_and_refuses_bad_values(cusick):
    from diffcloth.view.mesh import _SIMULATE_MESH

    m = cusick
    before, values = m.frames.cloth.copy(), dict(m.values)
    cache = _SIMULATE_MESH._cache_size()
    soft = {k: values[k] / 30.0 for k in ("bend_warp", "bend_weft", "bend_bias")}
    wall = m.resimulate(soft)
    assert _SIMULATE_MESH._cache_size() == cache  # new values, same compiled program
    assert wall > 0 and m.log[-1].startswith("re-simulation")
    # a 30th of the bending rigidity: the free part hangs lower
    drop = before[0, :, 1].mean() - m.frames.cloth[0, :, 1].mean()
    assert drop > 0.003, drop
    soft_frames = m.frames.cloth.copy()
    # bend_bias below (bend_warp + bend_weft) / 4: the fabric's own rule refuses it, nothing runs
    runs = m.resim_count
    with pytest.raises(ValueError, match="bend_bias"):
        m.resimulate({"bend_warp": 1e3 * values["bend_warp"]})
    assert m.resim_count == runs and m.values["bend_warp"] == soft["bend_warp"]
    np.testing.assert_array_equal(m.frames.cloth, soft_frames)
    with pytest.raises(ValueError, match="unknown slider 'stretch'"):
        m.resimulate({"stretch": 10.0})  # the grid's name; a mesh has stretch_warp / _weft
    with pytest.raises(ValueError, match="unknown slider 'wind'"):
        m.resimulate({"wind": [1.0, 0.0, 0.0]})  # an equilibrium feels no wind
    with pytest.raises(ValueError, match="no rigid bodies"):
        m.push(0, 0, [0.0, 1.0, 0.0])
    m.resimulate({k: values[k] for k in soft})
    np.testing.assert_allclose(m.frames.cloth, before, atol=1e-9)


def test_big_mesh_disables_the_sliders_with_a_note(cusick, monkeypatch):
    from diffcloth.view import mesh as vm

    assert vm.slider_note(cusick.scene) is None
    monkeypatch.setattr(vm, "MESH_SLIDER_MAX_VERTICES", 50)
    note = vm.slider_note(cusick.scene)
    assert note.startswith("Sliders disabled") and "edge_length" in note
    monkeypatch.setattr(cusick, "sliders_note", note)
    with pytest.raises(ValueError, match="Sliders disabled"):
        cusick.resimulate({"density": 0.3})


def test_render_panel_draws_the_mesh_cloth(cusick):
    img = cusick.render(0, camera=0)  # the top view: the drape's shadow, blue on dark
    assert img.shape == (SIZE, SIZE, 3) and img.dtype == np.uint8
    rgb = img.astype(int)
    cloth = (rgb[..., 2] > rgb[..., 0] + 40) & (rgb[..., 2] > 80)
    assert 0.2 * SIZE * SIZE < cloth.sum() < SIZE * SIZE  # the disc fills much of the view
    with pytest.raises(ValueError, match="camera = 5 out of range"):
        cusick.render(0, camera=5)


def test_viewer_gui_for_a_mesh_scene(cusick):
    _need("viser", "the viewer needs the `view` extra: pip install viser")
    from diffcloth.view.app import Viewer

    viewer = Viewer(cusick, host="127.0.0.1", port=None, autoplay=True)
    try:
        assert set(viewer.sliders) == set(cusick.sliders)  # no wind sliders
        assert viewer.frame_slider.disabled  # one frame
        assert "bend warp" in viewer._values_text() and "wind" not in viewer._values_text()
        np.testing.assert_allclose(viewer.scene3d.cloth.vertices, cusick.frames.cloth[0], atol=1e-6)
        assert viewer._slider_value("density") == pytest.approx(cusick.values["density"], 1e-2)
    finally:
        viewer.stop()


def test_cli_export_of_a_mesh_config(tmp_path, capsys, cusick_path, cusick):
    _need("viser", "the viewer needs the `view` extra: pip install viser")
    from diffcloth import cli

    out = tmp_path / "cusick.html"
    # same image size as the `cusick` fixture: the compiled programs are reused
    argv = ["view", str(cusick_path), "--export", str(out), "--size", str(SIZE), "--no-cache"]
    assert cli.main(argv) == 0
    html = out.read_text()
    assert "__VISER_EMBED_DATA__" in html and html.rstrip().endswith("</html>")
    assert f"wrote {out}" in capsys.readouterr().out


# ---- the tablecloth: a box collider -----------------------------------------------------------
def test_tablecloth_box_collider_is_drawn(tmp_path):
    from diffcloth.config import load_config
    from diffcloth.scene import build_scene
    from diffcloth.view.mesh import collider_boxes, collider_meshes, collider_planes, mesh_faces

    scene = build_scene(load_config(_coarse(tmp_path, "tablecloth", 0.06)))
    ((box),) = collider_boxes(scene.colliders)
    np.testing.assert_allclose(box["center"], [0.0, -0.35, 0.0])
    np.testing.assert_allclose(box["half_extents"], [0.25, 0.35, 0.18])
    np.testing.assert_allclose(box["wxyz"], [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    assert collider_meshes(scene.colliders) == []
    assert [o for _, o in collider_planes(scene.colliders)] == [-0.7]
    assert mesh_faces(scene).max() == scene.net.rest.shape[0] - 1
    # [cloth] subdivide: the drawn faces are the Loop subdivision's (4x), as the renderer draws
    path = _coarse(tmp_path, "tablecloth", 0.06)
    path.write_text(path.read_text().replace("[cloth]\n", "[cloth]\nsubdivide = 1\n", 1))
    sub = build_scene(load_config(path))
    assert len(mesh_faces(sub)) == 4 * len(mesh_faces(scene))
    assert mesh_faces(sub).max() == sub.display.num_vertices - 1


@pytest.mark.slow  # a second equilibrium compile: ~30 s on the 2-core machine
def test_tablecloth_drapes_over_the_box(tmp_path):
    from diffcloth.view.model import load_view

    m = load_view(_coarse(tmp_path, "tablecloth", 0.06), size=SIZE)  # 188 vertices
    assert m.kind == "mesh" and m.num_frames == 1 and bool(m.frames.ok)
    ((box),) = m.boxes()
    np.testing.assert_allclose(box["center"], [0.0, -0.35, 0.0])
    np.testing.assert_allclose(box["half_extents"], [0.25, 0.35, 0.18])
    np.testing.assert_allclose(box["wxyz"], [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    assert m.collider_meshes() == []
    x = m.frames.cloth[0]
    over = (np.abs(x[:, 0]) > 0.26) | (np.abs(x[:, 2]) > 0.19)
    assert x[over, 1].max() < -0.01  # beyond the table top the cloth hangs down
    inside = (np.abs(x[:, 0]) < 0.25) & (np.abs(x[:, 2]) < 0.18) & (x[:, 1] < -1e-4)
    assert not inside.any()


# ---- a dynamic mesh rollout: frames to play, wind and damping sliders ------------------------------
DYNAMIC = """
[cloth]
shape = "disc"
radius = 0.1
edge_length = 0.04
rings_at = [0.05]
center = [0.0, 0.0015, 0.0]
pin_radius = 0.05

[fabric]
preset = "wang2011-gray-interlock"

[sim]
mode = "dynamic"
dt = 0.02
num_frames = 4
integrator = "implicit"
num_substeps = 1
collision_margin = 0.001

[[cylinders]]
top = [0.0, 0.0, 0.0]
radius = 0.05
height = 0.2

[render]
width = 16
height = 16

[[cameras]]
eye = [0.0, 0.4, 0.0001]
target = [0.0, 0.0, 0.0]
up = [0.0, 0.0, -1.0]
fov_y = 45.0
"""


@pytest.mark.slow  # the implicit rollout's compile: minutes on the 2-core machine
def test_dynamic_mesh_rollout_plays_and_exports(tmp_path):
    _need("viser", "the viewer needs the `view` extra: pip install viser")
    from diffcloth.view.app import export_html
    from diffcloth.view.model import load_view

    path = tmp_path / "dyn.toml"
    path.write_text(DYNAMIC)
    m = load_view(path, size=16)
    assert m.num_frames == 4 and m.frames.cloth.shape[0] == 4 and bool(m.frames.ok)
    assert "dynamic" in m.describe() and m.has_wind
    assert {"damping", "drag"} <= set(m.sliders)
    y = m.frames.cloth[:, :, 1].min(axis=1)
    assert np.all(np.diff(y) < 0)  # the free rim falls frame after frame
    before = m.frames.cloth.copy()
    m.resimulate({"wind": [0.0, 0.0, 0.0], "density": 2.0 * m.values["density"]})
    assert np.abs(m.frames.cloth - before).max() > 1e-5
    html = export_html(m, tmp_path / "dyn.html").read_text()
    assert "__VISER_EMBED_DATA__" in html
