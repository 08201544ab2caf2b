"""Issue 35, class 2: `fit --resume` resumes the same problem, and a damaged checkpoint names its
file (diffcloth.fit.problem, diffcloth.fit.checkpoint).

One real two-step fit (module fixture, to PNG targets) writes the checkpoint that every test
copies; the refusals happen before anything is compiled, and the runs that go on reuse the
fixture's compiled programs (same shapes), so they cost about a second each.
"""

import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from test_hardening import FIT, TINY, assert_usage_error, run

import diffcloth as dc
from diffcloth.fit.problem import check_same_problem, problem_record, read_checkpoint
from diffcloth.io import save_png

CONFIG = TINY + FIT.replace("steps = 4", 'steps = 2\nmethod = "adam"') + 'targets = "targets"\n'


def _stub_run_fit(config_path, settings, sc, targets, out, ckpt, *a, **k):
    """The fit replaced by its checkpoint: what a 2-step fit leaves (the folder and the record
    around it are real)."""
    dc.fit.save_checkpoint(out.tmp / "checkpoint.npz", {"step": 3, "best/bend": 1.2e-3,
                           "params/bend": 1.2e-3}, {"step": 3, "names": ["bend"]})  # fmt: skip
    (out.tmp / "result.json").write_text("{}")
    return {"status": "max_steps", "params": {}, "loss": 0.0, "iterations": 2, "total_s": 0.0}


def _project(root: Path) -> Path:
    (root / "targets").mkdir(parents=True)
    for i in range(3):
        save_png(root / "targets" / f"frame_{i}.png", np.full((16, 16, 3), 0.3 + 0.1 * i))
    (root / "c.toml").write_text(CONFIG)
    return root


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A project folder: c.toml, targets/frame_{0,1,2}.png and res/ (a fit's folder, written by
    run_fit_config around a stub fit: the refusals below happen before any fitting)."""
    from diffcloth import experiment
    from diffcloth.cli import main

    root = _project(tmp_path_factory.mktemp("resume"))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(experiment, "_run_fit", _stub_run_fit)
        assert main(["fit", str(root / "c.toml"), "--out", str(root / "res")]) == 0
    return root


@pytest.fixture
def project(fitted, tmp_path):
    dest = tmp_path / "p"
    shutil.copytree(fitted, dest, symlinks=True)
    return dest


def _files(folder: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def test_checkpoint_records_the_problem(project):
    ck = read_checkpoint(project / "res" / "checkpoint.npz")
    rec = ck["meta"]["problem"]
    assert rec["config"]["material.stretch"] == 20.0 and "fit.steps" not in rec["config"]
    assert len(rec["targets"]) == 1 and len(rec["targets"][0]) == 3 and not rec["smoke"]
    from diffcloth.experiment import load_targets

    cfg = dc.config.load_config(project / "c.toml")
    targets = load_targets(cfg.fit, dc.load_scene(project / "c.toml"))
    now = problem_record(project / "c.toml", targets)
    check_same_problem(ck, project / "res" / "checkpoint.npz", now, "c.toml")  # the same: fine
    with pytest.raises(ValueError, match="ran without --smoke"):
        check_same_problem(ck, "ck.npz", problem_record(project / "c.toml", targets, smoke=True),
                           "c.toml")  # fmt: skip


@pytest.mark.parametrize(
    "old, new, needles",
    [
        ("stretch = 20.0", "stretch = 30.0", ["[material] stretch 20.0 -> 30.0"]),
        ("num_substeps = 20", "num_substeps = 25", ["[sim] num_substeps 20 -> 25"]),
        ('free = ["bend"]', 'free = ["bend", "shear"]', ["[fit] free"]),
        ("[fit]", '[fit.initial]\nbend = 3e-3\n[fit]', ["[fit.initial] bend (absent) -> 0.003"]),
        ("radius = 0.15", "radius = 0.15\n[[spheres]]\ncenter = [1.0, 0.0, 0.0]\nradius = 0.1",
         ["[spheres[1]] radius (absent) -> 0.1"]),
    ],
    ids=["material", "sim", "free", "initial", "sphere-added"],
)  # fmt: skip
def test_resume_after_the_config_changed_is_refused_naming_what(project, capsys, old, new, needles):
    text = CONFIG.replace(old, new, 1)
    assert text != CONFIG
    (project / "c.toml").write_text(text)
    before = _files(project / "res")
    code, _, err = run(["fit", str(project / "c.toml"), "--out", str(project / "res"),
                        "--resume"], capsys)  # fmt: skip
    assert_usage_error(code, err, "checkpoint.npz", "another problem", "config changed",
                       "--init-from", *needles)  # fmt: skip
    assert _files(project / "res") == before


def test_resume_after_a_target_image_changed_is_refused_naming_it(project, capsys):
    save_png(project / "targets" / "frame_1.png", np.full((16, 16, 3), 0.9))
    code, _, err = run(["fit", str(project / "c.toml"), "--out", str(project / "res"),
                        "--resume"], capsys)  # fmt: skip
    assert_usage_error(code, err, "targets changed", "camera 0: image(s) 1 of 3")
    assert "config changed" not in err
    # the same images under another name and folder: the config changed, the targets did not
    shutil.copytree(project / "targets", project / "t2")
    save_png(project / "t2" / "frame_1.png", np.full((16, 16, 3), 0.4))
    (project / "c.toml").write_text(CONFIG.replace('"targets"', '"t2"'))
    code, _, err = run(["fit", str(project / "c.toml"), "--out", str(project / "res"),
                        "--resume"], capsys)  # fmt: skip
    assert_usage_error(code, err, '[fit] targets "targets" -> "t2"')
    assert "targets changed" not in err


def test_resume_of_a_real_fit_continues_and_init_from_starts_anew(tmp_path, capsys):
    """The one real fit of this file (about 25 s): its checkpoint is stamped, --resume of the same
    problem goes on, and --init-from starts a fit of a changed config at the old best values."""
    root = _project(tmp_path)
    args = ["fit", str(root / "c.toml"), "--out", str(root / "res")]
    assert run(args, capsys)[0] == 0
    ck = read_checkpoint(root / "res" / "checkpoint.npz")
    assert ck["meta"]["problem"]["targets"] and ck["step"] == 3
    code, _, err = run([*args, "--resume"], capsys)  # the same problem: continued (and done)
    assert code == 0, err
    best = read_checkpoint(root / "res" / "checkpoint.npz")["best"]["bend"]
    (root / "c.toml").write_text(CONFIG.replace("stretch = 20.0", "stretch = 30.0"))
    code, _, err = run([*args, "--resume"], capsys)
    assert_usage_error(code, err, "[material] stretch 20.0 -> 30.0")
    new = [
        "fit",
        str(root / "c.toml"),
        "--out",
        str(root / "new"),
        "--init-from",
        str(root / "res"),
    ]
    code, _, err = run([*new, "--resume"], capsys)
    assert_usage_error(code, err, "--init-from", "--resume")
    code, out, err = run(new, capsys)
    assert code == 0, err
    result = json.loads((root / "new" / "result.json").read_text())
    assert result["params"]["bend"]["initial"] == pytest.approx(float(best), rel=1e-6)
    assert "--init-from" in (root / "new" / "report.md").read_text()
    rec = read_checkpoint(root / "new" / "checkpoint.npz")["meta"]["problem"]
    assert rec["config"]["material.stretch"] == 30.0  # the new fit records its own problem


def test_resume_may_change_the_steps(project, capsys, monkeypatch):
    """[fit] steps, patience, ... are not part of the problem (the stub stands in for the fit)."""
    from diffcloth import experiment

    monkeypatch.setattr(experiment, "_run_fit", _stub_run_fit)
    text = CONFIG.replace("\nsteps = 2\n", "\nsteps = 5\n").replace(
        "patience = 100", "patience = 7"
    )
    (project / "c.toml").write_text(
        text.replace("identifiability = false", "identifiability = true")
    )
    code, _, err = run(["fit", str(project / "c.toml"), "--out", str(project / "res"),
                        "--resume", "--steps", "9"], capsys)  # fmt: skip
    assert code == 0, err


def _truncate(p: Path):
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])


def _unexpected_key(p: Path):
    with zipfile.ZipFile(p, "a") as z:
        z.writestr("oops.npy", p.read_bytes()[:0])


def _object_array(p: Path):
    np.savez(p.with_suffix(".tmp.npz"), step=np.array([{"a": 1}], dtype=object))
    p.with_suffix(".tmp.npz").replace(p)


DAMAGE = {
    "npz-truncated": ("checkpoint.npz", _truncate, ["truncated, damaged"]),
    "npz-empty": ("checkpoint.npz", lambda p: p.write_bytes(b""), ["checkpoint.npz"]),
    "npz-garbage": ("checkpoint.npz", lambda p: p.write_bytes(b"PK\x03\x04" + b"x" * 100),
                    ["checkpoint.npz"]),
    "npz-unexpected-entry": ("checkpoint.npz", _unexpected_key, ["checkpoint.npz"]),
    "npz-object-array": ("checkpoint.npz", _object_array, ["checkpoint.npz"]),
    "json-truncated": ("checkpoint.json", _truncate, ["sidecar", "checkpoint.json"]),
    "json-not-object": ("checkpoint.json", lambda p: p.write_text("[1, 2]"),
                        ["checkpoint.json", "not a JSON object"]),
    "json-other-step": ("checkpoint.json", lambda p: p.write_text(json.dumps(
        {**json.loads(p.read_text()), "step": 99})), ["at step 3", "at step 99"]),
    "json-missing": ("checkpoint.json", lambda p: p.unlink(), ["sidecar is missing",
                                                             "--init-from"]),
    "json-no-record": ("checkpoint.json", lambda p: p.write_text(json.dumps(
        {k: v for k, v in json.loads(p.read_text()).items() if k != "problem"})),
        ["records no config"]),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(DAMAGE))
def test_a_damaged_checkpoint_names_the_file_exit_2(project, capsys, case):
    name, damage, needles = DAMAGE[case]
    damage(project / "res" / name)
    before = _files(project / "res")
    code, _, err = run(["fit", str(project / "c.toml"), "--out", str(project / "res"),
                        "--resume"], capsys)  # fmt: skip
    assert_usage_error(code, err, "--resume", *needles)
    assert "internal error" not in err and _files(project / "res") == before
    if name == "checkpoint.npz":  # --init-from reads the same file: the same kind of message
        code, _, err = run(["fit", str(project / "c.toml"), "--out", str(project / "new"),
                            "--init-from", str(project / "res")], capsys)  # fmt: skip
        assert_usage_error(code, err, "--init-from", "checkpoint.npz")
        assert not (project / "new").exists()


def test_init_from_mistakes(project, capsys):
    args = ["fit", str(project / "c.toml"), "--out", str(project / "new"), "--init-from"]
    code, _, err = run([*args, str(project / "nowhere")], capsys)
    assert_usage_error(code, err, "--init-from: no checkpoint", "nowhere")
    dc.fit.save_checkpoint(project / "ck" / "checkpoint.npz", {"step": 1, "best/density": 0.2},
                           {"step": 1})  # fmt: skip
    code, _, err = run([*args, str(project / "ck")], capsys)
    assert_usage_error(code, err, "values for ['density']", "none of this fit's free")
    dc.fit.save_checkpoint(project / "ck" / "checkpoint.npz", {"step": 1, "best/bend": [1.0, 2]},
                           {"step": 1})  # fmt: skip
    code, _, err = run([*args, str(project / "ck")], capsys)
    assert_usage_error(code, err, "value of bend has shape (2,)")
    assert not (project / "new").exists()
