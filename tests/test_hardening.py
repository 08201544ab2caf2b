"""Issue 15: every reproduced mistake ends in a clear message (exit 2) or a correct result.

Cases are numbered as in the issue (1 blow-ups ... 10 free fall). CLI cases go through
`diffcloth.cli.main` in-process (cheap: most are refused before anything is compiled) on a tiny
4 x 4 net, 16 x 16 px scene. The fuzz test of the configs is in test_config_fuzz.py, the PNG and
colour round trips in test_io_colour.py, the fit loop's resume in test_fit_resume.py.

Issue 35 (hardening, round two): each case and the test that proves it, in
tests/test_hardening_<file>.py (outdir, resume, signals, values, targets, checks,
cli_configs).

| class | case -> test |
|---|---|
| 1 | --out that is, holds or lies inside an input (config, targets, checkpoint), --overwrite too |
|   | -> outdir::test_out_holding_or_inside_an_input_is_refused_even_with_overwrite |
|   | -> outdir::test_init_from_checkpoint_and_resumed_config_copy_are_inputs |
|   | -> outdir::test_inputs_named_by_the_config_are_found |
| 1 | fuzz over --out layouts (equal, inside, parent, symlinks, files): inputs byte-identical |
|   | -> outdir::test_fuzz_output_layouts_never_change_an_input |
| 1 | two runs into one new --out: exactly one succeeds, the other exits 2 with a message |
|   | -> outdir::test_two_processes_into_one_new_out_exactly_one_succeeds |
|   | -> outdir::test_a_second_writer_is_refused_at_once_and_the_lock_goes_with_the_first |
|   | -> outdir::test_commit_refuses_a_folder_filled_meanwhile_and_stale_temporaries_go |
| 1 | a symlinked --out is written through (link kept; dangling, loop, link to an input) |
|   | -> outdir::test_symlinked_out_is_written_through_and_kept |
| 1 | a failed bench --out keeps the earlier result; bench --out holding its scripts |
|   | -> outdir::test_bench_out_is_an_output_folder |
| 1 | SIGTERM during simulate leaves no hidden temporary folder (and keeps an older result) |
|   | -> signals::test_simulate_sigint_in_a_long_compiled_call_and_sigterm_keep_old_results |
| 2 | --resume after the config changed: refused naming the keys (5 kinds of change) |
|   | -> resume::test_resume_after_the_config_changed_is_refused_naming_what |
| 2 | --resume after a target image changed: refused naming camera and image |
|   | -> resume::test_resume_after_a_target_image_changed_is_refused_naming_it |
| 2 | the record, --smoke; steps/patience may change; --init-from starts anew (real fit) |
|   | -> resume::test_checkpoint_records_the_problem, test_resume_may_change_the_steps |
|   | -> resume::test_resume_of_a_real_fit_continues_and_init_from_starts_anew |
|   | -> resume::test_init_from_mistakes |
| 2 | truncated, empty, garbage, odd-entry .npz; bad, missing, out-of-step sidecar: exit 2 |
|   | -> resume::test_a_damaged_checkpoint_names_the_file_exit_2 (10 cases) |
| 3 | Ctrl-C in a long compiled call exits 130, not 139; SIGTERM 143, nothing left behind |
|   | -> signals::test_simulate_sigint_in_a_long_compiled_call_and_sigterm_keep_old_results |
| 3 | a second Ctrl-C in a garbage-collector callback; a fit stopped twice writes nothing |
|   | -> signals::test_second_sigint_in_a_gc_callback_and_fit_double_sigint |
| 3 | one handler for every command: abort, cooperative fit, deferred commit, exit codes |
|   | -> signals::test_abort_discards_the_temporary_folder_and_exits_128_plus_signum |
|   | -> signals::test_cooperative_first_signal_sets_the_event_second_aborts |
|   | -> signals::test_a_signal_during_the_commit_waits_for_it |
|   | -> signals::test_fit_stopped_by_sigterm_exits_143, test_bench_sigterm_stops_its_benchmark_too |
|   | -> signals::test_fit_sigterm_writes_checkpoint_and_exits_143 (slow) |
| 3 | warmup interrupted: its temporary fit folder goes too (os._exit skips the cleanup) |
|   | -> signals::test_warmup_abort_removes_its_temporary_folder |
| 4 | width = 1e39, density = 1e-46, dt = 1e-46 (and 14 more keys) in float32: key named |
|   | -> values::test_simulate_refuses_values_that_leave_float32_naming_the_key |
| 4 | derived masses, rest lengths, spring weights, substep out of float32 |
|   | -> values::test_simulate_refuses_values_that_leave_float32_naming_the_key (DERIVED) |
| 4 | render and fit refuse the same; [truth], [fit.initial], [fit] values |
|   | -> values::test_render_and_fit_refuse_the_same_values |
|   | -> values::test_fit_values_are_checked_too |
| 4 | the check knows the dtype: --x64 accepts what float32 refuses |
|   | -> values::test_x64_run_accepts_what_float32_refuses |
|   | -> values::test_the_same_values_pass_in_float64 |
| 4 | apply_params checks the scene's dtype; so do the physics constructors |
|   | -> values::test_apply_params_checks_the_scene_dtype |
|   | -> values::test_constructors_check_their_dtype |
| 4 | one stability refusal in simulate, render, fit (and at [truth]/[fit.initial]) |
|   | -> values::test_stability_refusal_is_the_same_in_every_command |
|   | -> values::test_fit_refuses_a_truth_or_start_the_scene_cannot_step |
| 5 | interlaced (Adam7) 16-bit PNG read at full depth, not as dark 8-bit sRGB |
|   | -> targets::test_interlaced_16_bit_target_is_read_at_full_depth_not_as_dark_srgb |
|   | -> targets::test_adam7_round_trips_every_layout_exactly |
| 5 | palette and sub-8-bit PNGs by the same reader; bad headers name the file |
|   | -> targets::test_palette_and_sub_8_bit_pngs_are_read_by_the_same_reader |
|   | -> targets::test_invalid_png_headers_are_refused_naming_the_file |
| 5 | numbered sequence with a gap refused naming the missing frame |
|   | -> targets::test_fit_refuses_a_numbered_sequence_with_a_gap |
|   | -> targets::test_even_sequences_pass |
| 5 | float targets outside [0, 1] refused by validate_targets |
|   | -> targets::test_float_targets_outside_0_1_are_refused |
| 5 | a ragged list of frames names `targets` |
|   | -> targets::test_ragged_target_lists_name_targets |
|   | -> targets::test_fit_refuses_ragged_and_0_255_targets_before_compiling |
| 6 | warmup checks all its configs before compiling the first |
|   | -> checks::test_warmup_checks_every_config_before_compiling_the_first |
| 6 | warmup with an unusable cache folder exits 2 |
|   | -> checks::test_warmup_refuses_an_unusable_cache_folder |
| 6 | view --port 70000 (and bad --size, --level, --host) refused at once |
|   | -> checks::test_view_refuses_bad_options_at_once |
| 6 | view --export into a read-only folder refused before simulating |
|   | -> checks::test_view_export_that_cannot_be_written_is_refused_before_simulating |
| 6 | a FIFO (device, folder) config path refused by every command |
|   | -> checks::test_every_command_refuses_a_fifo_config |
|   | -> checks::test_fifo_config_in_a_fresh_process_exits_2_quickly |
| 7 | CLI fit of a Provot config (AttributeError 'stretch') |
|   | -> cli_configs::test_cli_simulate_render_fit_for_every_material_model |
| 7 | simulate, render, fit --smoke of every shipped config (slow) |
|   | -> cli_configs::test_cli_simulate_render_fit_for_every_shipped_config |
| 7 | the cross-engine recipe as a config (LM tolerances, x64) |
|   | -> cli_configs::test_the_cross_engine_recipe_is_a_config |
|   | -> cli_configs::test_new_fit_keys_are_validated |
"""

import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffcloth as dc
from diffcloth.cli import main
from diffcloth.config import ConfigError
from diffcloth.io import save_png

ROOT = Path(__file__).resolve().parents[1]

TINY = """
[net]
rows = 4
cols = 4
width = 0.4
height = 0.4
center = [0.0, 0.5, 0.0]
plane = "xz"
pinned = [[0, 0], [0, 3]]
velocity = [0.0, 0.0, 0.0]

[material]
stretch = 20.0
shear = 5.0
bend = 1e-3

[sim]
num_frames = 3
num_substeps = 20

[[spheres]]
center = [0.0, 0.2, 0.0]
radius = 0.15

[render]
width = 16
height = 16
level = 2

[camera]
eye = [0.0, 1.2, 1.5]
target = [0.0, 0.4, 0.0]
"""

FIT = """
[fit]
free = ["bend"]
steps = 4
patience = 100
identifiability = false
"""

TRUTH = """
[truth]
bend = 2e-3
"""


def write(tmp_path, text, name="c.toml"):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def run(argv, capsys):
    code = main(argv)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def assert_usage_error(code, err, *needles):
    assert code == 2, err
    assert err.startswith("error: ") and "Traceback" not in err, err
    for n in needles:
        assert n in err, (n, err)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return dc.load_scene(write(tmp_path_factory.mktemp("tiny"), TINY))


# ----------------------------------------------------------------------------- 1 blow-ups


def test_case1_collider_leaves_nan_points_nan():
    """Row 12's fallback must not paint a NaN point onto the sphere (it did: distance 0 -> +y)."""
    from diffcloth.physics.collide import collide_points

    x = jnp.array([[[0.0, 0.0, 0.0], [jnp.nan, 0.0, 0.0], [jnp.inf, 1.0, 0.0]]])
    v = jnp.zeros_like(x).at[0, 1].set(jnp.nan)
    xp, vp = collide_points(x, v, dc.Sphere(jnp.zeros(3), jnp.asarray(0.5)), 0.3)
    np.testing.assert_allclose(np.asarray(xp[0, 0]), [0.0, 0.5, 0.0])  # centre: fallback +y
    assert np.isnan(np.asarray(xp[0, 1, 0])) and np.isinf(np.asarray(xp[0, 2, 0]))


BAD_TRACED = (("bend", jnp.nan), ("density", 0.0), ("stretch", -40.0), ("damping", -1.0))


def test_case1_traced_bad_params_are_flagged(tiny_scene):
    """The traced check behind simulate_and_render's NaN video (the whole pipeline: slow test)."""
    from diffcloth import pipeline

    flag = jax.jit(lambda sc, p: pipeline.params_in_range(dc.apply_params(sc, p)))
    for name, value in BAD_TRACED:
        assert not bool(flag(tiny_scene, {name: jnp.asarray(value)})), name
    assert bool(flag(tiny_scene, {"density": jnp.asarray(0.2)}))
    traj = dc.simulate(tiny_scene)
    status = jax.jit(pipeline.trajectory_status)
    assert bool(status(tiny_scene, traj))
    blown = type(traj)(traj.x.at[1, 2, 2, 0].set(jnp.nan), traj.v)
    assert not bool(status(tiny_scene, blown))
    far = type(traj)(traj.x.at[2, 1, 1, 1].set(-3e5), traj.v)  # 300 km in 0.1 s: exploded
    assert not bool(status(tiny_scene, far))


@pytest.mark.slow
def test_case1_jit_simulate_and_render_of_bad_params_is_nan(tiny_scene):
    video = jax.jit(dc.simulate_and_render)(tiny_scene, {"bend": jnp.asarray(jnp.nan)})
    assert np.isnan(np.asarray(video)).all()
    checked = jax.jit(dc.simulate_and_render_checked)
    for name, value in BAD_TRACED:
        v, ok = checked(tiny_scene, {name: jnp.asarray(value)})
        assert not bool(ok) and np.isnan(np.asarray(v)).all(), name
    v, ok = checked(tiny_scene, {"density": jnp.asarray(0.2)})
    assert bool(ok) and np.isfinite(np.asarray(v)).all()


@pytest.mark.parametrize(
    "name, value, allowed",
    [("bend", np.nan, "(0, inf)"), ("density", 0.0, "(0, inf)"), ("stretch", -40.0, "(0, inf)"),
     ("damping", -1.0, "[0, inf)")],
)  # fmt: skip
def test_case1_and_8_eager_bad_params_name_the_parameter(tiny_scene, name, value, allowed):
    with pytest.raises(ValueError, match=rf"parameter {name} = .* allowed {re_escape(allowed)}"):
        dc.simulate_and_render(tiny_scene, {name: value})


def re_escape(s):
    import re

    return re.escape(s)


def test_case1_render_of_a_blow_up_exits_1_and_writes_nothing(tmp_path, capsys):
    cfg = write(tmp_path, TINY.replace("velocity = [0.0, 0.0, 0.0]", "velocity = [0.0, 3e38, 0]"))
    code, out, err = run(["render", cfg, "--out", str(tmp_path / "o")], capsys)
    assert code == 1 and "unstable" in err and "blew up" in err, err
    assert not (tmp_path / "o").exists() and not list(tmp_path.glob(".o.tmp-*"))
    code, out, err = run(["simulate", cfg, "--out", str(tmp_path / "s"), "--allow-unstable"],
                         capsys)  # fmt: skip
    assert code == 1 and "blew up" in err and not (tmp_path / "s").exists()


@pytest.mark.slow  # 8 s; moved out of the default suite (10-minute budget)
def test_case1_truth_that_collapses_the_cloth_is_a_config_error(tmp_path, capsys):
    # Adam renders the targets with simulate_and_render; an LM fit would compile its whole
    # Jacobian step first (fit/lm_video.py), the same finiteness check at 3x the test's time
    fit = FIT.replace('["bend"]', '["density"]') + 'method = "adam"\n'
    cfg = write(tmp_path, TINY + fit + "[truth]\ndensity = 1e-6\n")
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert_usage_error(code, err, "[truth]", "density", "not usable")
    assert not (tmp_path / "o").exists()


# ----------------------------------------------------------------------------- 2 interrupt


class _SetAfter:
    """Stands in for the signal event: becomes set after `n` checks (i.e. after step n-1)."""

    def __init__(self, n):
        self.n, self.checks, self.signum = n, 0, 2

    def is_set(self):
        self.checks += 1
        return self.checks >= self.n


@pytest.mark.slow  # three small fits: ~1 min on an idle 2-core machine
@pytest.mark.parametrize("method", ["adam", "lm"])
def test_case2_interrupt_checkpoints_reports_exits_130_and_resume_matches(
    tmp_path, capsys, monkeypatch, method
):
    import contextlib

    from diffcloth.fit import interrupt

    cfg = write(tmp_path, TINY + FIT.replace("[fit]\n", f'[fit]\nmethod = "{method}"\n') + TRUTH)
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "full")], capsys)
    assert code == 0, err
    full = json.loads((tmp_path / "full" / "result.json").read_text())

    @contextlib.contextmanager
    def fake(*a, **k):
        yield _SetAfter(2)

    monkeypatch.setattr(interrupt, "catch_interrupts", fake)
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "part")], capsys)
    assert code == 130 and err.count("\n") == 1 and "--resume" in err, err
    part = tmp_path / "part"
    res = json.loads((part / "result.json").read_text())
    assert res["status"] == "interrupted" and res["iterations"] == 2
    assert "interrupted" in (part / "report.md").read_text().splitlines()[0]
    ck = dc.fit.load_checkpoint(part / "checkpoint.npz")
    assert ck["step"] == 2 and "bend" in ck["best"]
    if method == "adam":  # the optax state travels; LM keeps only its iterate and best
        assert ck["opt_state"]
    else:
        assert ck["meta"]["method"] == "lm" and not ck["opt_state"]
    monkeypatch.undo()
    code, out, err = run(["fit", cfg, "--out", str(part), "--resume"], capsys)
    assert code == 0, err
    resumed = json.loads((part / "result.json").read_text())
    assert resumed["status"] == full["status"] and resumed["iterations"] == full["iterations"]
    if method == "adam":  # bitwise: the optax state and history travel in the checkpoint
        assert resumed["params"]["bend"]["fitted"] == full["params"]["bend"]["fitted"]
        assert resumed["loss"] == full["loss"]
        lines = (part / "metrics.jsonl").read_text().splitlines()
        assert len(lines) == len((tmp_path / "full" / "metrics.jsonl").read_text().splitlines())
    else:  # LM restarts its stages from the checkpoint's best (docs/fit.md): the same optimum
        fitted, ref = resumed["params"]["bend"]["fitted"], full["params"]["bend"]["fitted"]
        assert abs(fitted - ref) <= 1e-6 * abs(ref), (fitted, ref)
    # --resume without a checkpoint is a usage error
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "new"), "--resume"], capsys)
    assert_usage_error(code, err, "--resume", "checkpoint")


# ----------------------------------------------------------------------------- 3 sizes


def test_case3_sizes_are_refused_before_compiling_with_the_estimate(tmp_path, capsys, monkeypatch):
    cfg = write(tmp_path, TINY)
    code, out, err = run(["render", cfg, "--out", str(tmp_path / "a"), "--size", "100000"],
                         capsys)  # fmt: skip
    assert_usage_error(code, err, "needs about", "GiB", "limit", "--size")
    big = write(tmp_path, TINY.replace("width = 16", "width = 8192").replace(
        "height = 16", "height = 8192"), "big.toml")  # fmt: skip
    code, out, err = run(["render", big, "--out", str(tmp_path / "b")], capsys)
    assert_usage_error(code, err, "8192x8192", "needs about")
    many = write(tmp_path, TINY.replace("num_frames = 3", "num_frames = 1e9"), "many.toml")
    for cmd in ("render", "simulate", "fit"):
        code, out, err = run([cmd, many, "--out", str(tmp_path / cmd)], capsys)
        assert_usage_error(code, err, "num_frames", "integer")
    text = TINY.replace("rows = 4", "rows = 5000").replace("cols = 4", "cols = 5000")
    huge = write(tmp_path, text.replace("pinned = [[0, 0], [0, 3]]", 'pinned = "none"'), "h.toml")
    code, out, err = run(["simulate", huge, "--out", str(tmp_path / "h"), "--frames", "100000"],
                         capsys)  # fmt: skip
    assert_usage_error(code, err, "5000x5000", "needs about")
    monkeypatch.setenv("DIFFCLOTH_MEMORY_LIMIT", "1K")  # a documented limit is honoured
    code, out, err = run(["simulate", cfg, "--out", str(tmp_path / "l")], capsys)
    assert_usage_error(code, err, "DIFFCLOTH_MEMORY_LIMIT=1K")
    assert not any((tmp_path / d).exists() for d in ("a", "b", "h", "l", "render", "simulate"))


# ----------------------------------------------------------------------------- 4 tracebacks


@pytest.mark.parametrize(
    "extra, needles",
    [
        ("[fit.initial]\nbend = -8e-4\n", ["[fit.initial] bend", "(0, inf)"]),
        ("", ["[fit.initial] diffuse", "(0, 1)"]),
        ("[truth]\nwind = [1.0, 2.0]\n", ["[truth]", "wind", "shape (2,)", "(3,)"]),
        ("", ["[fit] initial = 5", "table"]),
    ],
    ids=["initial-bend-negative", "initial-diffuse-1.5", "truth-wrong-length", "initial-5"],
)
def test_case4_fit_config_mistakes_name_the_key(tmp_path, capsys, extra, needles):
    fit = FIT
    truth = TRUTH
    if "diffuse" in needles[0]:
        fit = FIT.replace('["bend"]', '["diffuse"]') + "[fit.initial]\ndiffuse = [1.5, 0.2, 0.2]\n"
        truth = "[truth]\ndiffuse = [0.5, 0.2, 0.2]\n"
    if "initial = 5" in needles[0]:
        fit = FIT + "initial = 5\n"
    if "wind" in extra:
        truth = ""
    cfg = write(tmp_path, TINY + fit + extra + truth)
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert_usage_error(code, err, *needles)
    assert not (tmp_path / "o").exists()  # 5: nothing written before the checks


@pytest.mark.parametrize(
    "old, new, needles",
    [
        ("num_frames = 3", "num_frames = 0", ["[sim] num_frames = 0", "[1, "]),
        ("level = 2", "level = 2\nframe_stride = 5", ["frame_stride = 5", "num_frames = 3"]),
    ],
)
def test_case4_frame_counts(tmp_path, capsys, old, new, needles):
    cfg = write(tmp_path, TINY.replace(old, new) + FIT + TRUTH)
    for cmd in ("render", "fit", "simulate"):
        code, out, err = run([cmd, cfg, "--out", str(tmp_path / cmd)], capsys)
        assert_usage_error(code, err, *needles)


def test_case4_bad_options(tmp_path, capsys):
    cfg = write(tmp_path, TINY + FIT + TRUTH)
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o"), "--steps", "0"], capsys)
    assert_usage_error(code, err, "--steps must be >= 1, got 0")
    code, out, err = run(["render", cfg, "--out", str(tmp_path / "o"), "--size", "0"], capsys)
    assert_usage_error(code, err, "--size must be >= 1")
    code, out, err = run(["simulate", str(tmp_path / "nope.toml"), "--out", "x"], capsys)
    assert_usage_error(code, err, "nope.toml")
    with pytest.raises(ValueError, match="--steps"):  # --debug: the exception itself
        main(["fit", cfg, "--out", str(tmp_path / "o"), "--steps", "0", "--debug"])


def test_case4_and_5_out_that_is_a_file_read_only_or_empty(tmp_path, capsys):
    cfg = write(tmp_path, TINY + FIT + TRUTH)
    afile = tmp_path / "file.txt"
    afile.write_text("x")
    for cmd in ("simulate", "render", "fit"):
        code, out, err = run([cmd, cfg, "--out", str(afile)], capsys)
        assert_usage_error(code, err, "--out", "existing file")
        code, out, err = run([cmd, cfg, "--out", "/proc/diffcloth-test"], capsys)
        assert_usage_error(code, err, "--out", "cannot write")
        code, out, err = run([cmd, cfg, "--out", ""], capsys)
        assert_usage_error(code, err, "--out must name a folder")
    assert afile.read_text() == "x"


def _targets(tmp_path, frames=3, size=16, channels=3, cams=("cam0",), bits=8):
    root = tmp_path / "targets"
    for cam in cams:
        (root / cam).mkdir(parents=True, exist_ok=True)
        for i in range(frames):
            img = np.full((size, size, channels), 0.25 + 0.1 * i)
            save_png(root / cam / f"frame_{i}.png", img, colorspace="srgb", bits=bits)
    return root


@pytest.mark.parametrize(
    "layout, needles",
    [
        (dict(size=20), ["20x20 pixels", "16x16"]),
        (dict(channels=1), ["grey image", "RGB"]),
        (dict(channels=4), ["RGBA image", "RGB"]),
        (dict(frames=2), ["gives 2 images", "renders 3 frames", "1 missing"]),
        (dict(frames=5), ["gives 5 images", "2 extra"]),
        (dict(frames=0), ["no files matching '*.png'", "cam0", "empty"]),
    ],
    ids=["size", "grey", "rgba", "missing", "extra", "empty"],
)
def test_case4_every_bad_target_folder(tmp_path, capsys, layout, needles):
    root = _targets(tmp_path, **layout)
    cfg = write(tmp_path, TINY + FIT + f'targets = "{root.name}"\n')
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert_usage_error(code, err, *needles)
    assert not (tmp_path / "o").exists()


def test_case4_missing_camera_folder_and_layout_keys(tmp_path, capsys):
    two = TINY.replace("[camera]", "[[cameras]]") + "\n[[cameras]]\neye = [1.0, 1.0, 1.0]\n"
    root = _targets(tmp_path, cams=("cam0",))
    cfg = write(tmp_path, two + FIT + f'targets = "{root.name}"\n')
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert_usage_error(code, err, "camera 1", "cam1", "no folder")
    # a subfolder glob, a frame range and a stride select exactly the 3 rendered frames
    from diffcloth.experiment import load_targets

    sc = dc.load_scene(write(tmp_path, TINY, "s.toml"))
    for i in range(9):
        save_png(tmp_path / "t2" / "left" / "rgb" / f"f{i}.png", np.full((16, 16, 3), i / 10),
                 colorspace="linear", bits=16)  # fmt: skip
    (tmp_path / "t2" / "left" / "notes.txt").write_text("ignored")
    settings = dc.config.load_config(write(tmp_path, TINY + FIT + (
        'targets = "t2"\ntarget_cameras = ["le*"]\ntarget_glob = "rgb/f*.png"\n'
        "target_frames = [2, 8]\ntarget_stride = 2\n"), "l.toml")).fit  # fmt: skip
    video = load_targets(settings, sc)
    assert video.shape == (1, 3, 16, 16, 3)
    np.testing.assert_allclose(video[0, :, 0, 0, 0], [0.2, 0.4, 0.6], atol=1e-4)  # 16-bit linear


# ----------------------------------------------------------------------------- 5 results folders


def test_case5_results_are_protected(tmp_path, capsys):
    cfg = write(tmp_path, TINY)
    out = tmp_path / "res"
    assert run(["simulate", cfg, "--out", str(out)], capsys)[0] == 0
    (out / "identifiability.json").write_text("{}")  # a stale file of an older run
    before = (out / "trajectory.npz").read_bytes()
    code, _, err = run(["simulate", cfg, "--out", str(out)], capsys)
    assert_usage_error(code, err, "not empty", "--overwrite")
    assert (out / "trajectory.npz").read_bytes() == before
    bad = write(tmp_path, TINY.replace("velocity = [0.0, 0.0, 0.0]", "velocity = [0.0, 3e38, 0]"),
                "bad.toml")  # fmt: skip
    code, _, err = run(["simulate", bad, "--out", str(out), "--overwrite"], capsys)
    assert code == 1, err
    assert (out / "trajectory.npz").read_bytes() == before  # a failed rerun leaves it intact
    assert run(["simulate", cfg, "--out", str(out), "--overwrite", "--frames", "2"], capsys)[0] == 0
    assert sorted(p.name for p in out.iterdir()) == ["trajectory.npz"]  # no stale file
    assert np.load(out / "trajectory.npz")["x"].shape[0] == 2
    assert not list(tmp_path.glob(".res.*"))  # no temporary folders left behind


# ----------------------------------------------------------------------------- 6 NaN stop


@pytest.mark.slow  # a fit plus the stage check's compilations
def test_case6_nonfinite_stop_is_status_nonfinite_exit_1_strict_json(tmp_path, capsys):
    adam = 'method = "adam"\nsteps = 6\nlearning_rate = 200.0\nschedule = "constant"'
    cfg = write(tmp_path, TINY + FIT.replace("steps = 4", adam) + TRUTH)
    code, out, err = run(["fit", cfg, "--out", str(tmp_path / "o")], capsys)
    assert code == 1 and "non-finite" in err, (out, err)
    res = json.loads((tmp_path / "o" / "result.json").read_text())
    assert res["status"] == "nonfinite"
    assert "learning_rate" in res.get("diagnosis", ""), res.get("diagnosis")
    for line in (tmp_path / "o" / "metrics.jsonl").read_text().splitlines():
        json.loads(line, parse_constant=lambda c: pytest.fail(f"bare {c} in metrics.jsonl"))
    assert "null" in (tmp_path / "o" / "metrics.jsonl").read_text()


# ----------------------------------------------------------------------------- 7 targets read


def test_case7_targets_16_bit_exact_srgb_default_for_8_bit(tmp_path):
    from diffcloth.experiment import load_targets
    from diffcloth.io.png import write_png

    sc = dc.load_scene(write(tmp_path, TINY))
    vals16 = np.array([0, 1, 257, 32768, 65534, 65535], np.uint16)
    img16 = np.broadcast_to(np.resize(vals16, (16, 16))[..., None], (16, 16, 3)).copy()
    img8 = np.full((16, 16, 3), 188, np.uint8)
    for name, img in (("t16", img16), ("t8", img8)):
        (tmp_path / name).mkdir()
        for i in range(3):
            write_png(tmp_path / name / f"f{i}.png", img)  # no colour chunk: the default rule

    def targets(extra, fname):
        config = dc.config.load_config(write(tmp_path, TINY + FIT + extra, fname))
        return load_targets(config.fit, sc)

    v16 = targets('targets = "t16"\n', "a.toml")  # 16-bit: linear by default, every bit kept
    np.testing.assert_array_equal(np.round(v16[0, 0] * 65535).astype(np.uint16), img16)
    v8 = targets('targets = "t8"\n', "b.toml")  # 8-bit: sRGB by default, decoded to linear
    np.testing.assert_allclose(v8[0, 0, 0, 0, 0], ((188 / 255 + 0.055) / 1.055) ** 2.4, rtol=1e-6)
    lin = targets('targets = "t8"\ncolorspace = "linear"\n', "c.toml")
    np.testing.assert_allclose(lin[0, 0, 0, 0, 0], 188 / 255, rtol=1e-6)


# ----------------------------------------------------------------------------- 8 silent acceptance

BALL = (
    TINY
    + """
[[bodies]]
shape = "sphere"
radius = 0.15
mass = 0.1
position = [0.0, 0.9, 0.0]
"""
)


@pytest.mark.parametrize(
    "params, needles",
    [
        ({"body_restitution": 1.5}, ["body_restitution", "[0, 1]"]),
        ({"body_mass": -0.15}, ["body_mass", "(0, inf)"]),
        ({"body_position": [[np.nan, 0.0, 0.0]]}, ["body_position", "finite"]),
        ({"wind": [1.0, 2.0]}, ["parameter wind", "shape (2,)", "(3,)"]),
        ({"diffuse": np.ones((2, 3))}, ["parameter diffuse", "(2, 3)"]),
    ],
)
def test_case8_apply_params_validates_like_the_configs(tmp_path, params, needles):
    sc = dc.load_scene(write(tmp_path, BALL))
    with pytest.raises(ValueError) as exc:
        dc.apply_params(sc, params)
    for n in needles:
        assert n in str(exc.value), (n, str(exc.value))


def test_case8_params_table_is_the_configs_table():
    from diffcloth.physics.material import MATERIAL_FIELDS
    from diffcloth.pipeline import PARAMETER_RANGES, PARAMETERS

    assert set(MATERIAL_FIELDS) <= set(PARAMETER_RANGES) <= set(PARAMETERS)
    for name, (lo, inclusive, _, default) in MATERIAL_FIELDS.items():
        r = PARAMETER_RANGES[name]
        assert r.contains(default) and r.contains(lo) == inclusive


@pytest.mark.parametrize(
    "extra, needles",
    [
        ("[output]\nfolder = 'x'\n", ["unknown key 'output'"]),
        ("", ["multistart = 0", "[1, 64]"]),
        ("", ["[fit.initial] shear is not a free parameter"]),
        ("", ["[fit] free must be a non-empty list"]),
    ],
    ids=["output-section", "multistart-0", "initial-not-free", "free-string"],
)
def test_case8_silently_accepted_config_keys(tmp_path, extra, needles):
    fit = FIT
    if "multistart" in needles[0]:
        fit = FIT + "multistart = 0\n"
    if "shear" in needles[0]:
        fit = FIT + "[fit.initial]\nshear = 5.0\n"
    if "free must" in needles[0]:
        fit = FIT.replace('["bend"]', '"bend"')
    with pytest.raises(ConfigError) as exc:
        dc.config.load_config(write(tmp_path, TINY + extra + fit + TRUTH))
    for n in needles:
        assert n in str(exc.value)


def test_case8_make_body_half_extents_for_a_sphere():
    from diffcloth.physics.rigid import make_body

    with pytest.raises(ValueError, match="half_extents"):
        make_body("sphere", radius=0.1, half_extents=(0.1, 0.1, 0.1), mass=1.0)


# ----------------------------------------------------------------------------- 9, 10


def test_case9_dc_io_load_image_after_import_diffcloth(tmp_path):
    p = save_png(tmp_path / "a.png", np.full((2, 2, 3), 0.5))
    code = f"import diffcloth as dc; print(dc.io.load_image({str(p)!r}).shape)"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0 and "(2, 2, 3)" in res.stdout, res.stderr[-2000:]


def test_case10_long_free_fall_is_not_a_blow_up(tmp_path, capsys):
    """15 s at 1000 m/s^2: the cloth falls 112 km, further than the old 1e5 m box."""
    text = (TINY.split("[[spheres]]")[0]
            .replace("[sim]", "[sim]\ngravity = [0.0, -1000.0, 0.0]\ndt = 1.0")
            .replace("bend = 1e-3", "bend = 1e-3\ndrag_normal = 0.0\ndrag_tangent = 0.0")
            .replace("pinned = [[0, 0], [0, 3]]", 'pinned = "none"')
            .replace("num_frames = 3", "num_frames = 15")
            .replace("num_substeps = 20", "num_substeps = 400"))  # fmt: skip
    cfg = write(tmp_path, text)
    sc = dc.load_scene(cfg)
    traj = dc.physics.checked_rollout(sc.net, sc.sim, sc.material, sc.state, num_frames=15)
    assert float(np.min(np.asarray(traj.x)[..., 1])) < -1e5
    assert bool(dc.physics.trajectory_ok(sc.net, traj, sc.sim, sc.state))
    assert not bool(dc.physics.trajectory_ok(sc.net, traj))  # the bare 1e5 m box would reject it
    code, out, err = run(["simulate", cfg, "--out", str(tmp_path / "o"), "--chunk", "5"], capsys)
    assert code == 0, err


def test_first_frame_states_which_simulated_frame_image_0_shows(tmp_path):
    """[render] first_frame = 1 (default): images show frames k, 2k, ... (the initial state is not
    drawn); first_frame = 0: frames 0, k, 2k, ... The number of images is the same."""
    from diffcloth import pipeline

    text = BALL.replace("num_frames = 3", "num_frames = 6").replace("level = 2", "level = 2\n"
                        "frame_stride = 2")  # fmt: skip
    one = dc.load_scene(write(tmp_path, text, "one.toml"))
    text0 = text.replace("level = 2\n", "level = 2\nfirst_frame = 0\n")
    zero = dc.load_scene(write(tmp_path, text0, "zero.toml"))
    assert one.first_frame == 1 and zero.first_frame == 0
    traj, bodies = pipeline.simulate_all(one)
    xs1, sp1 = pipeline.rendered_states(one, traj, bodies)
    xs0, sp0 = pipeline.rendered_states(zero, traj, bodies)
    assert xs1.shape == xs0.shape == (3, 4, 4, 3)
    np.testing.assert_array_equal(xs1, traj.x[1::2])  # frames 2, 4, 6
    np.testing.assert_array_equal(xs0[0], zero.state.x)  # frame 0: the initial state
    np.testing.assert_array_equal(xs0[1:], traj.x[1:4:2])  # frames 2, 4
    np.testing.assert_array_equal(sp0.center[0, -1], zero.bodies[0].position)
    np.testing.assert_array_equal(sp0.center[1:, -1], bodies[0].position[1:4:2])
    np.testing.assert_array_equal(sp1.center[:, -1], bodies[0].position[1::2])


def test_case6_report_of_a_nonfinite_fit_is_strict_json_with_status(tmp_path):
    """The cheap half of case 6 (the CLI run is the slow test above): result.json carries the
    status and metrics.jsonl writes null, never a bare NaN."""
    from diffcloth.fit.loop import FitResult, History
    from diffcloth.report import write_fit_report

    h = History(
        loss=np.array([1.0, np.nan]),
        params={"bend": np.array([1.0, np.inf])},
        grad_norm={"bend": np.array([1.0, np.nan])},
        wall_s=np.array([0.0, 1.0]),
    )
    r = FitResult(params={"bend": np.array(1.0)}, raw={"bend": np.array(0.0)}, loss=1.0,
                  initial={"bend": np.array(1.0)}, history=h, iterations=1, wall_s=1.0,
                  status="nonfinite", message="non-finite loss/grad at step 1", best_step=0,
                  last_finite={"bend": np.array(1.0)})  # fmt: skip
    write_fit_report(tmp_path, r, plots=False)
    assert json.loads((tmp_path / "result.json").read_text())["status"] == "nonfinite"
    rows = [json.loads(line, parse_constant=lambda c: pytest.fail(f"bare {c}"))
            for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]  # fmt: skip
    assert rows[1]["loss"] is None and rows[1]["params"]["bend"] is None
    assert "**nonfinite**" in (tmp_path / "report.md").read_text()


def test_case5_out_may_not_be_the_current_folder_or_a_parent(tmp_path, capsys, monkeypatch):
    cfg = write(tmp_path, TINY)
    monkeypatch.chdir(tmp_path)
    for bad in (".", "..", str(tmp_path)):
        code, out, err = run(["simulate", cfg, "--out", bad, "--overwrite"], capsys)
        assert_usage_error(code, err, "current folder")
    assert (tmp_path / "c.toml").exists()
