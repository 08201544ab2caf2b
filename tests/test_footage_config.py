"""Issue 36: the footage recipe from a config. [fit] loss = "footage" with [fit.footage], .npz
target files (images + masks) with target_frames / target_stride / target_downsample, the
missing-footage error naming `targets_make`, the LM tolerances reaching the fit, the short scene
of a windowed staged stage, and a tiny `diffcloth fit` with the footage loss."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_hardening import TINY, run, write

from diffcloth.config import ConfigError, load_config, parse_config

jax.config.update("jax_enable_x64", True)

FOOT = """
[fit]
free = ["bend"]
steps = 3
patience = 100
identifiability = false
loss = "footage"
targets = "t.npz"
"""


#: a small cloth held at two corners, swinging down, seen from above (TINY's cloth covers a
#: few pixels); stretch shows from the first frame
DROP = """
[net]
rows = 5
cols = 5
width = 0.6
height = 0.6
center = [0.0, 0.4, 0.0]
plane = "xz"
pinned = [[0, 0], [0, 4]]

[material]
stretch = 20.0
shear = 5.0
bend = 1e-3

[sim]
num_frames = 3
num_substeps = 20

[render]
width = 16
height = 16
level = 2

[[cameras]]
eye = [0.0, 1.3, 0.6]
target = [0.0, 0.3, 0.0]
fov_y = 50.0
"""
BIG = DROP.replace("num_frames = 3", "num_frames = 6").replace(
    "width = 16\nheight = 16", "width = 32\nheight = 32"
)


@pytest.fixture(scope="module")
def footage7(tmp_path_factory):
    """Footage of the DROP scene (stretch 20): 6 frames at twice the size (32^2), float64, with
    cloth masks; (scene, video, masks). One compilation for the module."""
    from diffcloth.scene import build_scene

    d = tmp_path_factory.mktemp("big")
    sc = build_scene(load_config(write(d, BIG)), dtype=jnp.float64)
    video, m = footage_video(sc, 20.0)
    return sc, np.asarray(video), np.asarray(m)


def _synthetic(frames=6, size=32):
    """Footage-like arrays without a render: a grey background and a cloth-coloured square that
    moves one pixel a frame; (video (1, frames, size, size, 3), masks (1, frames, size, size))."""
    video = np.full((1, frames, size, size, 3), 0.1)
    masks = np.zeros((1, frames, size, size))
    for f in range(frames):
        masks[0, f, 8 + f : 20 + f, 6:22] = 1.0
    video[masks > 0] = (0.7, 0.15, 0.2)
    return None, video, masks


def _write_footage(tmp_path, footage7, frames=6, masks=True):
    """t.npz of the first `frames` frames (images, masks unless masks=False, nets)."""
    _, video, m = footage7
    arrays = {"images": video[:, :frames], "nets": np.zeros((frames + 1, 4, 4, 3))}
    if masks:
        arrays["masks"] = m[:, :frames]
    np.savez(tmp_path / "t.npz", **arrays)
    return arrays


def test_footage_keys_parse_with_the_recipe_defaults(tmp_path):
    c = parse_config({**_toml(TINY + FOOT)}, path=str(tmp_path / "c.toml"))
    spec = c.fit.footage
    assert c.fit.loss == "footage" and c.fit.targets == str(tmp_path / "t.npz")
    loss = spec.loss()
    assert (loss.color, loss.color_scale, loss.mask, loss.mask_weight, loss.color_margin) == (
        "huber",
        0.05,
        "iou",
        1.0,
        3,
    )
    c = parse_config(
        _toml(TINY + FOOT + '[fit.footage]\ncolor_region = "all"\nmask = "none"\n'),
        path=str(tmp_path / "c.toml"),
    )
    assert c.fit.footage.loss().color_margin is None and c.fit.footage.loss().mask is None
    assert not c.fit.footage.needs_masks


def _toml(text):
    import tomllib

    return tomllib.loads(text)


@pytest.mark.parametrize(
    "extra, match",
    [
        ("[fit.footage]\ncolor_scale = 0.0", r"\[fit.footage\] color_scale = 0.0 is out of range; "
         r"allowed range \(0, 1\]"),
        ("[fit.footage]\ncolor = \"l3\"", r"\[fit.footage\] color = 'l3'; allowed values: l2, huber"),
        ("[fit.footage]\nmask = \"dice\"", r"\[fit.footage\] mask = 'dice'; allowed values: iou"),
        ("[fit.footage]\ncolor_margin = 65", r"color_margin = 65 is out of range; allowed range "
         r"\[0, 64\]"),
        ("[fit.footage]\ncolor_margin = 1.5", r"color_margin = 1.5 must be an integer"),
        ("[fit.footage]\nmask_weight = -1.0", r"mask_weight = -1.0 is out of range"),
        ("[fit.footage]\nmasks = \"segment\"", r"masks = 'segment'; allowed values: auto, file"),
        ("[fit.footage]\ncolor_region = \"floor\"", r"color_region = 'floor'; allowed values"),
        ("[fit.footage]\nmask_color = [0.5, 0.2]", r"mask_color = \[0.5, 0.2\] must be a list of 3"),
        ("[fit.footage]\nmask_color = [2.0, 0.2, 0.1]", r"mask_color = \[2.0, 0.2, 0.1\] is out "
         r"of range"),
        ("[fit.footage]\nmask_tolerance = 0", r"mask_tolerance = 0 is out of range"),
        ("[fit.footage]\ncolour = \"l2\"", r"\[fit.footage\] unknown key 'colour'"),
        ("[fit.footage]\ncolor = \"none\"\nmask = \"none\"", r"compare nothing"),
        ("target_downsample = 0", r"\[fit\] target_downsample = 0 is out of range; allowed range "
         r"\[1, 64\]"),
        ("targets_make = 3", r"\[fit\] targets_make = 3 must be the command"),
    ],
)  # fmt: skip
def test_bad_footage_keys_name_the_key_and_range(tmp_path, extra, match):
    text = TINY + FOOT
    if extra.startswith("["):
        text += extra + "\n"
    else:
        text = text.replace('loss = "footage"', f'loss = "footage"\n{extra}')
    with pytest.raises(ConfigError, match=match):
        parse_config(_toml(text), path=str(tmp_path / "c.toml"))


def test_footage_loss_needs_footage_targets_and_the_table_needs_the_loss(tmp_path):
    no_targets = (TINY + FOOT).replace('targets = "t.npz"\n', "") + "[truth]\nbend = 2e-3\n"
    with pytest.raises(ConfigError, match=r'\[fit\] loss = "footage" compares with footage'):
        parse_config(_toml(no_targets))
    stray = (TINY + FOOT).replace('loss = "footage"\n', "") + '[fit.footage]\ncolor = "l2"\n'
    with pytest.raises(ConfigError, match=r'\[fit.footage\] needs \[fit\] loss = "footage"'):
        parse_config(_toml(stray), path=str(tmp_path / "c.toml"))
    make = 'targets_make = "python -m make_footage"\n'
    text = TINY + FOOT.replace('loss = "footage"\ntargets = "t.npz"\n', make)
    with pytest.raises(ConfigError, match=r"\[fit\] targets_make needs \[fit\] targets"):
        parse_config(_toml(text + "[truth]\nbend = 2e-3\n"))


def test_missing_footage_names_the_command_that_makes_it(tmp_path, capsys):
    text = TINY + FOOT.replace(
        'targets = "t.npz"', 'targets = "t.npz"\ntargets_make = "python -m make_footage --fast"'
    )
    cfg = write(tmp_path, text)
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert code == 2, err
    assert "t.npz' does not exist; make them with `python -m make_footage --fast`" in err, err


def test_npz_targets_frames_downsample_and_masks(tmp_path):
    from diffcloth.fit_targets import load_fit_targets
    from diffcloth.scene import build_scene

    big = _write_footage(tmp_path, _synthetic())
    text = DROP + FOOT.replace(
        'targets = "t.npz"', 'targets = "t.npz"\ntarget_frames = [0, 6]\ntarget_stride = 2'
    )
    c = load_config(write(tmp_path, text))
    sc = build_scene(c)
    with pytest.raises(ConfigError, match=r"32x32 pixels after target_downsample = 1; the scene "):
        load_fit_targets(c.fit, sc)
    c = load_config(write(tmp_path, text.replace("target_stride = 2", "target_stride = 2\n"
                                                 "target_downsample = 2")))  # fmt: skip
    video, masks = load_fit_targets(c.fit, sc)
    assert video.shape == (1, 3, 16, 16, 3) and masks.shape == (1, 3, 16, 16)
    want = big["images"][:, 0:6:2].reshape(1, 3, 16, 2, 16, 2, 3).mean(axis=(3, 5))
    np.testing.assert_allclose(video, np.clip(want, 0, 1))
    want_m = big["masks"][:, 0:6:2].reshape(1, 3, 16, 2, 16, 2).mean(axis=(3, 5))
    np.testing.assert_allclose(masks, want_m)
    c = load_config(write(tmp_path, text.replace("target_stride = 2", "target_stride = 3\n"
                                                 "target_downsample = 2")))  # fmt: skip
    with pytest.raises(ConfigError, match=r"gives 2 frames \(of 6, frames \[0, 6\) every 3\), but "
                       r"the scene renders 3 frames"):  # fmt: skip
        load_fit_targets(c.fit, sc)


def test_mask_rule_file_colour_and_auto(tmp_path):
    from diffcloth.fit_targets import load_fit_targets
    from diffcloth.scene import build_scene

    _, video, masks = _synthetic()
    _write_footage(tmp_path, (None, video, masks), frames=3, masks=False)
    base = DROP + FOOT.replace('targets = "t.npz"', 'targets = "t.npz"\ntarget_downsample = 2')
    c = load_config(write(tmp_path, base + '[fit.footage]\nmasks = "file"\n'))
    sc = build_scene(c)
    with pytest.raises(ConfigError, match=r'masks = "file" needs target masks: an .npz target'):
        load_fit_targets(c.fit, sc)
    for rule in ("auto", "color"):  # no masks in the file: a colour key of the footage
        c = load_config(write(tmp_path, base + f'[fit.footage]\nmasks = "{rule}"\n'
                              "mask_color = [0.7, 0.15, 0.2]\n"))  # fmt: skip
        got, m = load_fit_targets(c.fit, sc)
        assert m.shape == got.shape[:-1] and set(np.unique(m)) <= {0.0, 1.0}
        # frame 0's square is aligned with the 2 x 2 blocks: the key finds it exactly
        np.testing.assert_array_equal(m[0, 0], masks[0, 0].reshape(16, 2, 16, 2).mean(axis=(1, 3)))


def test_lm_tolerances_of_the_config_reach_the_fit():
    from diffcloth.experiment import _lm_tolerances

    c = load_config("configs/footage_example.toml")
    assert _lm_tolerances(c.fit) == {"lm_xtol": 1e-3, "lm_ftol": 1e-5, "lm_tau": 1.0,
                                     "lm_polish": 0}  # fmt: skip
    c = parse_config(_toml(TINY + '[fit]\nfree = ["bend"]\n[truth]\nbend = 2e-3\n'))
    assert _lm_tolerances(c.fit) == {}  # the defaults: method "staged" keeps its recipe's


def test_the_shipped_footage_example_is_the_protocols_recipe():
    c = load_config("configs/footage_example.toml")
    f = c.fit
    assert f.x64 and f.method == "staged" and f.loss == "footage" and f.steps == 12
    assert f.target_frames == (2, 60) and f.target_stride == 3 and f.target_downsample == 2
    assert f.targets.endswith("benchmarks/cross_engine/data/drape_soft.npz")
    assert "benchmarks.cross_engine.generate" in f.targets_make
    assert f.footage.loss().color_margin == 3 and f.footage.masks == "file"
    assert [st.get("free") for st in f.stages] == [["air_damping"], None]


@pytest.mark.slow  # two forward compilations: ~40 s on 2 loaded cores
def test_window_scene_residuals_equal_the_windowed_full_scene(footage7):
    """A windowed stage on the short scene gives the full scene's residuals inside the window."""
    from diffcloth.fit import footage
    from diffcloth.fit.scene_fit import window_scene

    sc, video, m = footage7
    spec = footage.FootageLoss(color="huber", mask="iou", color_margin=1)
    prep = footage.prepare_targets(sc, video, m, spec, value_range=(None, 2.0))
    fn = jax.jit(footage.footage_residual_fn(spec))
    fw = jnp.asarray([0.5, 0.5, 0, 0, 0, 0], jnp.float64)
    args, (cut, short) = window_scene((jnp.ones(1), fw), (prep, sc))
    assert short.num_frames == 2 and cut.video.shape[1] == 2 and cut.color_w.shape[1] == 2
    p = {"stretch": jnp.asarray(12.0)}
    full = np.asarray(fn(p, prep, sc, jnp.ones(1), fw))
    part = np.asarray(fn(p, cut, short, *args))
    # the same residuals (each the mean over the window's frames), without the zero ones
    np.testing.assert_allclose(full[full != 0], part[part != 0], rtol=1e-9)
    assert window_scene((jnp.ones(1), jnp.full(6, 1 / 6)), (prep, sc))[1] is None


def footage_video(sc, stretch):
    """(video, cloth masks) of the scene with this stretch (jitted)."""
    import functools

    from diffcloth import pipeline

    fn = jax.jit(functools.partial(pipeline.simulate_and_render, with_mask=True))
    return fn(sc, {"stretch": jnp.asarray(stretch, sc.material.density.dtype)})


@pytest.mark.slow  # an LM compilation: ~60 s on 2 loaded cores
def test_front_door_takes_a_footage_loss_and_refuses_masks_without_it(footage7):
    import diffcloth as dc
    from diffcloth.fit import footage

    sc, video, m = footage7
    with pytest.raises(ValueError, match="masks are for a footage loss"):
        dc.fit.fit(sc, video, ["stretch"], masks=m, steps=1)
    spec = footage.FootageLoss(color="huber", mask=None, color_margin=2)
    with pytest.raises(ValueError, match=r"FootageLoss.color_margin=2 needs target_masks"):
        dc.fit.fit(sc, video, ["stretch"], loss=spec, steps=1, method="lm", progress=False)
    # colour on the cloth pixels only: its minimum is the truth (a soft-IoU term's is not
    # exactly, on masks with fractional edge pixels)
    r = dc.fit.fit(sc, video, ["stretch"], loss=spec, masks=m, steps=8, method="lm",
                   init={"stretch": 12.0}, progress=False, stages="none")  # fmt: skip
    assert r.method == "lm" and abs(float(r.params["stretch"]) / 20.0 - 1) < 0.01, r.params


def test_diffcloth_fit_smoke_with_the_footage_loss(tmp_path, capsys):
    """A tiny `diffcloth fit` with the footage loss from a config (synthetic footage file: it
    runs and writes the report, nothing is fitted)."""
    _, video, masks = _synthetic(frames=2, size=16)
    np.savez(tmp_path / "t.npz", images=video, masks=masks)
    text = DROP.replace("num_frames = 3", "num_frames = 2") + FOOT.replace(
        'free = ["bend"]', 'free = ["stretch"]\nmethod = "lm"\nstages = "none"'
    ).replace("steps = 3", "steps = 1")
    code, out, err = run(["fit", write(tmp_path, text), "--out", str(tmp_path / "o")], capsys)
    assert code == 0, err
    result = json.loads((tmp_path / "o" / "result.json").read_text())
    assert result["method"] == "lm" and np.isfinite(result["loss"]), result
    assert "## Footage loss" in (tmp_path / "o" / "report.md").read_text()


@pytest.mark.slow  # three LM / video compilations: ~100 s on 2 loaded cores
def test_diffcloth_fit_with_the_footage_loss(tmp_path, capsys, footage7):
    """The footage loss from a config: a staged fit (stretch alone on its window's short scene,
    then stretch and shear), the report's footage section, the comparison GIF. The footage is
    the scene's own (its first 3 frames), colour on the cloth pixels only: its minimum is the
    truth."""
    _write_footage(tmp_path, footage7, frames=3)
    fit = FOOT.replace(
        'free = ["bend"]',
        'free = ["stretch", "shear"]\nmethod = "staged"\n'
        'x64 = true\nstages = [{ frames = 0.5, free = ["stretch"] }]',
    )
    fit += '[fit.footage]\nmask = "none"\n[fit.initial]\nstretch = 12.0\n'
    fit += "[truth]\nstretch = 20.0\nshear = 5.0\n"  # fmt: skip
    cfg = write(tmp_path, BIG.replace("num_frames = 6", "num_frames = 3") + fit)
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert code == 0, err
    result = json.loads((tmp_path / "o" / "result.json").read_text())
    assert result["method"] == "staged", result
    assert result["status"] in ("converged", "stalled", "max_steps"), result["status"]
    fitted = result["params"]["stretch"]["fitted"]
    assert abs(fitted / 20.0 - 1) < 0.01, result["params"]
    assert result["stages"][0]["name"].startswith("levels>=0, frames 1-2 (free: stretch)")
    report = (tmp_path / "o" / "report.md").read_text()
    assert "## Footage loss" in report and "Silhouette IoU of the fit" in report
    assert (tmp_path / "o" / "compare.gif").is_file() and (tmp_path / "o" / "loss.png").is_file()
