"""Mesh cloth through the pipeline: [cloth] / [fabric] / mesh colliders in configs, the Scene,
simulate_and_render in both modes, fabric parameters by name, the CLI (issue 31)."""

import textwrap

import jax
import numpy as np
import pytest

import diffcloth as dc
from diffcloth import pipeline
from diffcloth.config import ConfigError, load_config, parse_config
from diffcloth.physics.mesh import ClothMesh, Fabric, cloth_surface, display_mesh, make_cloth
from diffcloth.physics.mesh.builders import disc
from diffcloth.scene import build_scene, cloth_kind

TINY = """
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
mode = "{mode}"
dt = 0.02
num_frames = 2
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


@pytest.fixture(autouse=True)
def _allow_rank_promotion():
    """physics/mesh/hessian.py broadcasts (m, 3, 3, 1, 1) with (3, 3) (to be fixed there)."""
    with jax.numpy_rank_promotion("allow"):
        yield


def _write(tmp_path, text, name="c.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def _parse(text):
    import tomllib

    return parse_config(tomllib.loads(text))


# ----------------------------------------------------------------------------- config


def test_grid_is_default_and_unchanged():
    config = parse_config({})
    assert config.cloth.shape == "grid" and not config.cloth.is_mesh
    assert config.sim.mode == "dynamic"


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ('[cloth]\nshape = "hexagon"', r"\[cloth\] shape = 'hexagon'; allowed values: grid"),
        ('[cloth]\nshape = "disc"\nradius = 0.1', "missing required key 'edge_length'"),
        ('[cloth]\nshape = "disc"\nedge_length = 0.02\nwidth = 1.0', "width.*rectangle"),
        (
            '[cloth]\nshape = "disc"\nedge_length = 0.02\n[fabric]\npreset = "silk"',
            r"\[fabric\] preset = 'silk' is not a known fabric; allowed: wang2011",
        ),
        (
            '[cloth]\nshape = "disc"\nedge_length = 0.02\n[fabric]\nbend_warp = -1.0',
            r"\[fabric\] fabric.bend_warp = -1.0 N m is out of range: allowed \(0, inf\)",
        ),
        (
            '[cloth]\nshape = "disc"\nedge_length = 0.02\n[fabric]\npoisson = 1.5',
            r"poisson.*allowed \[0, 1\)",
        ),
        (
            '[cloth]\nshape = "disc"\nedge_length = 0.02\n[fabric]\nbend_bias = 1e-9',
            "bend_bias",
        ),
        ('[cloth]\nshape = "disc"\nedge_length = 0.02\n[fabric]\nstiff = 1.0', "unknown key"),
        (
            '[cloth]\nshape = "obj"\npath = "nowhere.obj"',
            r"\[cloth\] path = 'nowhere.obj': no such",
        ),
        ("[fabric]\nbend = 1e-5", r"\[fabric\] apply to a mesh cloth only"),
        ('[sim]\nmode = "equilibrium"', r"\[sim\] mode apply to a mesh cloth only"),
        (
            '[cloth]\nshape = "disc"\nedge_length = 0.02\n[material]\nbend = 1.0',
            r"\[material\] do\(es\) not apply",
        ),
        (
            '[cloth]\nshape = "disc"\nedge_length = 0.02\n[[cylinders]]\ntop = [0, 0, 0]\n'
            "radius = -1.0\nheight = 0.1",
            r"\[cylinders #0\] radius = -1.0 is out of range",
        ),
        (
            '[cloth]\nshape = "disc"\nedge_length = 0.02\n[sim]\nperturb = {mode = 0, '
            "amplitude = 0.01}",
            r"\[sim.perturb\] mode = 0 is out of range",
        ),
        (
            '[cloth]\nshape = "disc"\nedge_length = 0.02\n[sim]\nmode = "equilibrium"\n'
            "[render]\nframe_stride = 2",
            "frame_stride and first_frame must be 1",
        ),
    ],
)
def test_config_errors(text, match):
    with pytest.raises(ConfigError, match=match):
        _parse(text)


def test_fabric_value_representable_in_run_dtype():
    config = _parse('[cloth]\nshape = "disc"\nedge_length = 0.05\n[fabric]\ndensity = 1e-40')
    with pytest.raises(ConfigError, match=r"\[fabric\] density = 1e-40 underflows"):
        build_scene(config, dtype=np.float32)


def test_preset_path_relative_to_config(tmp_path):
    (tmp_path / "mine.toml").write_text("[fabric]\ndensity = 0.5\nbend_warp = 3e-5\n")
    path = _write(tmp_path, TINY.format(mode="equilibrium").replace(
        'preset = "wang2011-gray-interlock"', 'preset = "mine.toml"\nbend_weft = 3e-5'))  # fmt: skip
    scene = build_scene(load_config(path))
    assert float(scene.material.density) == 0.5 and float(scene.material.bend_weft) == 3e-5


# ----------------------------------------------------------------------------- scene


@pytest.fixture(scope="module")
def scenes():
    return {m: build_scene(_parse(TINY.format(mode=m))) for m in ("equilibrium", "dynamic")}


def test_scene_holds_mesh_cloth(scenes):
    sc = scenes["equilibrium"]
    assert isinstance(sc.net, ClothMesh) and isinstance(sc.material, Fabric)
    assert cloth_kind(sc) == "mesh" and sc.num_frames == 1
    r = np.hypot(np.asarray(sc.net.rest)[:, 0], np.asarray(sc.net.rest)[:, 2])
    np.testing.assert_array_equal(np.asarray(sc.net.pinned), r <= 0.05 + 1e-9)
    assert scenes["dynamic"].num_frames == 2
    assert cloth_kind(dc.load_scene("configs/drape.toml")) == "grid"


def test_cloth_surface_uv_normals_tangents():
    cloth = make_cloth(disc(0.1, 0.03))
    for level in (0, 1):
        surf = cloth_surface(cloth, cloth.rest, display=display_mesh(cloth, level))
        uv = np.asarray(surf.uv)
        assert uv.min() >= -1e-12 and uv.max() <= 1 + 1e-12
        np.testing.assert_allclose(np.asarray(surf.normals), [[0, 1, 0]] * len(uv), atol=1e-9)
        np.testing.assert_allclose(np.asarray(surf.tangents), [[1, 0, 0]] * len(uv), atol=1e-9)
    assert surf.faces.shape[0] == 4 * cloth.num_faces


def test_fabric_parameters_by_name(scenes):
    sc = scenes["equilibrium"]
    assert float(pipeline.param_value(sc, "bend_warp")) == pytest.approx(23.2e-6)
    with pytest.raises(ValueError, match=r"poisson = 1.5 is out of range; allowed \[0, 1\)"):
        pipeline.apply_params(sc, {"poisson": 1.5})
    with pytest.raises(ValueError, match="'stretch' is a parameter of the grid net's"):
        pipeline.apply_params(sc, {"stretch": 10.0})
    grid = dc.load_scene("configs/drape.toml")
    with pytest.raises(ValueError, match="'bend_warp' is a parameter of a mesh cloth's"):
        pipeline.apply_params(grid, {"bend_warp": 1e-5})


# ----------------------------------------------------------------------------- pipeline


@pytest.mark.parametrize(
    "mode", ["equilibrium", pytest.param("dynamic", marks=pytest.mark.slow)]
)  # dynamic: ~3 min of compilation on the 2-core CI machine
def test_simulate_and_render(scenes, mode):
    sc = scenes[mode]
    video = np.asarray(jax.jit(dc.simulate_and_render)(sc))
    assert video.shape == sc.video_shape and np.isfinite(video).all()
    background = np.asarray(sc.background)
    cloth_px = np.abs(video[0, -1] - background).sum(-1) > 0.05
    assert cloth_px.mean() > 0.1  # the cloth fills the middle of the top view


@pytest.mark.slow  # compiles each stage on its own: 21 s idle, half of the test above
def test_diagnose_finds_no_broken_stage(scenes):
    assert pipeline.diagnose(scenes["equilibrium"]) is None


@pytest.mark.slow  # a second compile of the solve (max_iters is static)
def test_unconverged_equilibrium_is_an_error_not_a_shape(scenes):
    import dataclasses

    sc = scenes["equilibrium"]
    sim = dataclasses.replace(sc.sim, solver=dataclasses.replace(sc.sim.solver, max_iters=1))
    bad = dataclasses.replace(sc, sim=sim)
    video, ok = jax.jit(pipeline.simulate_and_render_checked)(bad)
    assert not bool(ok) and np.isnan(np.asarray(video)).all()
    assert "did not converge after 1 Newton iterations" in pipeline.diagnose(bad)


# ----------------------------------------------------------------------------- CLI


@pytest.mark.slow  # ~6 min: three commands, each compiling the float64 solve
def test_cli_simulate_render_fit_smoke(tmp_path):
    from diffcloth.cli import main

    text = TINY.format(mode="equilibrium") + textwrap.dedent("""
        [truth]
        bend_warp = 3e-5

        [fit]
        free = ["bend_warp"]
        steps = 2

        [fit.initial]
        bend_warp = 2e-5
        """)
    path = _write(tmp_path, text)
    assert main(["simulate", str(path), "--out", str(tmp_path / "sim")]) == 0
    data = np.load(tmp_path / "sim" / "trajectory.npz")
    assert data["x"].shape[0] == 1 and np.isfinite(data["x"]).all() and "faces" in data
    assert main(["render", str(path), "--out", str(tmp_path / "r"), "--format", "gif"]) == 0
    assert (tmp_path / "r" / "first.png").is_file()
    assert main(["fit", str(path), "--out", str(tmp_path / "f"), "--smoke"]) == 0


@pytest.mark.slow
@pytest.mark.gate  # the shipped configs' float64 equilibria must reach their tolerance (~20-40 s)
@pytest.mark.parametrize("name", ["cusick", "tablecloth"])
def test_cli_simulate_of_a_shipped_mesh_config_converges(tmp_path, name):
    from diffcloth.cli import main

    assert main(["simulate", f"configs/{name}.toml", "--out", str(tmp_path)]) == 0
    x = np.load(tmp_path / "trajectory.npz")["x"]
    assert x.shape[0] == 1 and np.isfinite(x).all()
