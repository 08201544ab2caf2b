"""The drape-test workflow (diffcloth.drape): config checks, the simulated specimen's
differentiable measures against the exact shadow measures, imperfections, the CLI's refusals of
bad inputs (default tier: no equilibrium solve), and end-to-end fits of synthetic drapes (slow).
"""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.cli import main
from diffcloth.drape import CUSICK, polar_shadow_image, write_silhouette
from diffcloth.drape.config import DrapeConfigError, load_drape_config
from diffcloth.drape.model import imperfect_start, make_drape_model, rim_dc, rim_spectrum
from diffcloth.drape.outline import outline_spectrum
from diffcloth.physics.mesh import measure


@pytest.fixture(scope="module")
def model():
    return make_drape_model(CUSICK, edge=0.015)


def _config(tmp_path, body: str, images=("a.png",)):
    for name in images:
        theta = np.linspace(0, 2 * np.pi, 360, endpoint=False)
        img = polar_shadow_image(0.125 + 0.012 * np.cos(6 * theta), CUSICK, size=200,
                                 mm_per_pixel=1.6)  # fmt: skip
        write_silhouette(tmp_path / name, img)
    p = tmp_path / "drape.toml"
    p.write_text(body)
    return p


GOOD = """
[fabric]
density = 0.2
[images]
mm_per_pixel = 1.6
[[observations]]
file = "a.png"
"""


def test_config_defaults(tmp_path):
    cfg = load_drape_config(_config(tmp_path, GOOD))
    assert cfg.params == ("bend",) and cfg.density == 0.2 and cfg.seeds >= 1
    assert cfg.observations[0].mm_per_pixel == 1.6 and cfg.observations[0].side == "face"
    assert cfg.geometry == CUSICK


@pytest.mark.parametrize(
    "edit, key",
    [
        (lambda s: s.replace("density = 0.2", ""), "[fabric] density"),
        (lambda s: s.replace("density = 0.2", "density = -1"), "[fabric] density"),
        (lambda s: s + "[fit]\nparams = ['bend', 'bend_warp']\n", "[fit] params"),
        (lambda s: s + "[fit]\nparams = ['colour']\n", "[fit] params"),
        (lambda s: s + "[fit]\nseeds = 0\n", "[fit] seeds"),
        (lambda s: s + "[fit]\nedge = 0.05\n", "[fit] edge"),
        (lambda s: s.replace('file = "a.png"', 'file = "a.png"\nside = "up"'), "side"),
        (lambda s: s.replace('file = "a.png"', 'file = "missing.png"'), "file"),
        (lambda s: s + "[geometry]\nspecimen_radius = 0.05\n", "[geometry]"),
        (lambda s: "colour = 1\n" + s, "top level"),
    ],
)
def test_config_errors_name_the_key(tmp_path, edit, key):
    with pytest.raises(DrapeConfigError, match=re_escape(key)):
        load_drape_config(_config(tmp_path, edit(GOOD)))


def re_escape(s):
    import re

    return re.escape(s)


def test_rim_measures_match_the_exact_shadow(model):
    """On a flat disc warped radially by r -> r (1 - 0.15 s + e s^2 cos(k phi)) (s: 0 at the pedestal, 1
    at the rim), the rim polygon's DC equals the exact shadow's and its spectrum the image
    spectrum of the same outline."""
    x = np.asarray(model.cloth.rest, np.float64).copy()
    r = np.hypot(x[:, 0], x[:, 2])
    phi = np.arctan2(-x[:, 2], x[:, 0])
    s = np.clip((r - 0.09) / 0.06, 0, None)
    f = 1 - 0.15 * s + 0.03 * s**2 * np.cos(7 * phi + 0.4)  # no fold-over: r f(r) increases
    x[:, 0] *= f
    x[:, 2] *= f
    dc = float(rim_dc(model, jnp.asarray(x)))
    exact = measure.drape_coefficient(x, model.faces, 0.15, 0.09, resolution=2e-4).value
    assert abs(dc - exact) < 2e-3
    spec = np.asarray(rim_spectrum(model, jnp.asarray(x)))
    ref = outline_spectrum(measure.outline_radius(x, model.faces, 720))
    assert spec.shape == (16,)
    assert abs(spec[6] - ref[6]) < 0.003 and spec[6] > 0.02
    assert np.all(np.abs(np.delete(spec, 6)) < 0.01)


def test_imperfections_are_reproducible_and_spare_the_clamp(model):
    a = imperfect_start(model, 3)
    b = imperfect_start(model, 3)
    c = imperfect_start(model, 4)
    np.testing.assert_array_equal(a, b)
    assert np.max(np.abs(a - c)) > 1e-4
    pinned = np.asarray(model.cloth.pinned)
    rest = np.asarray(model.cloth.rest)
    np.testing.assert_array_equal(a[pinned], rest[pinned])
    k = imperfect_start(model, 0, mode=5, amplitude=3e-3)
    rim = model.rim
    dy = k[rim, 1] - rest[rim, 1]
    assert abs(np.max(np.abs(dy)) - 3e-3) < 2e-4
    spec = np.abs(np.fft.rfft(dy))
    assert int(np.argmax(spec)) == 5
    with pytest.raises(ValueError, match="mode"):
        imperfect_start(model, 0, mode=0)


def test_cli_refuses_bad_images_naming_the_file(tmp_path, capsys):
    cfg = _config(tmp_path, GOOD)
    np_blank = np.full((200, 200), 230, np.uint8)
    write_silhouette(tmp_path / "a.png", np_blank)  # empty: no cloth
    code = main(["drape", "fit", str(cfg), "--out", str(tmp_path / "out"), "--no-cache"])
    err = capsys.readouterr().err
    assert code == 2 and "a.png" in err
    assert not (tmp_path / "out").exists()


def test_cli_sets_aside_a_misscaled_image_and_refuses_when_none_is_left(tmp_path, capsys):
    body = GOOD.replace("mm_per_pixel = 1.6", "mm_per_pixel = 0.8")  # twice too small
    cfg = _config(tmp_path, body)
    code = main(["drape", "fit", str(cfg), "--out", str(tmp_path / "out"), "--no-cache"])
    cap = capsys.readouterr()
    assert code == 2
    assert "set aside" in cap.out and "a.png" in cap.out
    assert "none of the 1 images passed" in cap.err


# ------------------------------------------------------------------------------- slow: fitting


@pytest.mark.slow
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_feature_jacobian_matches_central_differences():
    """d(DC, c2)/d(log bend) through the equilibrium (implicit function theorem) against central
    differences of warm-started solves (same fold branch), float64, solved to a force residual of
    1e-8 of the vertex weights (at the fit's 1e-3 the differences are noise-limited: c2 to
    about 20 %)."""
    model = make_drape_model(CUSICK, edge=0.015, tol=1e-8, max_iters=800)
    from diffcloth.drape.config import DrapeConfig
    from diffcloth.drape.fit import _evaluator

    cfg = DrapeConfig(source=None, name="t", geometry=CUSICK, density=0.2, fabric={"density": 0.2},
                      observations=(), scans=(), params=("bend_warp", "bend_weft"), start={},
                      seeds=1, steps=1, edge=0.015, amplitude=2e-3, predict_seeds=1)  # fmt: skip
    names = ("dc", "c2x", "c2y")
    ev = _evaluator(model, cfg, names)
    q = jnp.log(jnp.array([3e-5, 1e-5]))
    f, jac, (x, conv, _) = ev(q, jnp.asarray(imperfect_start(model, 1, mode=6)))
    assert bool(conv)
    h = 1e-2
    for i in range(2):
        dq = jnp.zeros(2).at[i].set(h)
        fp, _, (_, cp, _) = ev(q + dq, x)
        fm, _, (_, cm, _) = ev(q - dq, x)
        assert bool(cp) and bool(cm)
        fd = (np.asarray(fp) - np.asarray(fm)) / (2 * h)
        np.testing.assert_allclose(np.asarray(jac)[:, i], fd, rtol=5e-3, atol=5e-5)


@pytest.mark.slow
def test_cli_fit_recovers_the_bending_of_a_synthetic_drape(tmp_path):
    """A limp fabric draped by diffcloth, written as a 256-pixel JPEG, fitted from the generic
    start by `diffcloth drape fit`; its prediction of the other seeds' DC."""
    from diffcloth.drape.suite import make_suite

    fabric = {"density": 0.15, "bend": 6e-6}
    make_suite(tmp_path / "suite", fabrics={"t": fabric}, seeds=3, edge=0.015)
    cfg = tmp_path / "suite" / "t" / "drape.toml"
    cfg.write_text(cfg.read_text().replace("[fit]", "[fit]\nedge = 0.015").replace(
        "seeds = 6", "seeds = 3"))  # fmt: skip
    out = tmp_path / "out"
    assert main(["drape", "fit", str(cfg), "--out", str(out), "--no-cache"]) == 0
    res = json.loads((out / "fit.json").read_text())
    bend = res["fit"]["values"]["bend"]
    assert abs(bend / fabric["bend"] - 1) < 0.05, bend
    truth = {s["seed"]: s["dc"] for s in res["truth"]["seeds"]}
    for p in res["predictions"]:
        assert abs(p["dc"] - truth[p["seed"]]) < 0.02
    for name in ("report.md", "fabric.toml", "loss.png", "params.png", "overlays/seed0.png"):
        assert (out / name).is_file(), name
    assert res["observations"][0]["iou"] > 0.9
    assert math.isfinite(res["fit"]["std"]["bend"])
    jax.clear_caches()


def test_a_scan_in_centimetres_is_set_aside_naming_the_file(tmp_path):
    """A 3D scan of a drape written in cm instead of m: reported, not fitted; a good scan in m
    becomes an observation (its top-view DC)."""
    from diffcloth.drape.observe import measure_observations
    from diffcloth.physics.mesh import disc

    mesh = disc(0.15, 0.008, rings_at=(0.09,))
    v = mesh.vertices.copy()
    r = np.hypot(v[:, 0], v[:, 2])
    out = np.clip(r - 0.09, 0, None)
    scale = np.where(r > 0, (np.minimum(r, 0.09) + out * 0.6) / np.maximum(r, 1e-12), 1.0)
    v[:, 0] *= scale
    v[:, 2] *= scale
    v[:, 1] -= out * 0.8  # a cone: the hanging part turned down
    faces = "\n".join(f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces)
    for name, s in (("good.obj", 1.0), ("cm.obj", 100.0)):
        verts = "\n".join(f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in v * s)
        (tmp_path / name).write_text(verts + "\n" + faces + "\n")
    body = GOOD + '[[scans]]\nfile = "good.obj"\n[[scans]]\nfile = "cm.obj"\n'
    cfg = load_drape_config(_config(tmp_path, body))
    said = []
    obs = measure_observations(cfg, log=said.append)
    assert [m.obs.path.name for m in obs.accepted] == ["a.png", "good.obj"]
    assert [o.path.name for o, _ in obs.rejected] == ["cm.obj"]
    assert any("cm.obj" in s and "cm" in s.replace("cm.obj", "") for s in said), said
    dc_scan = obs.accepted[1].features["dc"]
    expected = ((0.09 + 0.06 * 0.6) ** 2 - 0.09**2) / (0.15**2 - 0.09**2)
    assert abs(dc_scan - expected) < 0.03
