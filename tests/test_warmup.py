"""`diffcloth warmup`: a one-step fit that fills the compilation cache for the real fit."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
from tiny_scenes import TINY_SCENE

from diffcloth.cli import main

ROOT = Path(__file__).resolve().parents[1]

TINY_FIT = (
    TINY_SCENE
    + """[truth]
bend = 2e-3

[fit]
free = ["bend"]
steps = 2

[fit.initial]
bend = 1e-3
"""
)


def test_warmup_needs_the_cache_and_a_valid_config(tmp_path, capsys, monkeypatch):
    cfg = tmp_path / "fit.toml"
    cfg.write_text(TINY_FIT)
    assert main(["warmup", str(cfg), "--no-cache"]) == 2
    assert "--no-cache" in capsys.readouterr().err
    monkeypatch.setenv("DIFFCLOTH_CACHE", "off")
    assert main(["warmup", str(cfg)]) == 2
    assert "DIFFCLOTH_CACHE=off" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text(TINY_FIT.replace('free = ["bend"]', 'free = ["nonsense"]'))
    assert main(["warmup", str(bad), "--cache", str(tmp_path / "cache")]) == 2
    assert "nonsense" in capsys.readouterr().err


@pytest.mark.slow
def test_fit_after_warmup_compiles_nothing_new(tmp_path):
    """Every program of the fit is in the cache after the warm-up: the fit adds no entry."""
    cfg = tmp_path / "fit.toml"
    cfg.write_text(TINY_FIT)
    cache, tmp = tmp_path / "cache", tmp_path / "tmp"
    tmp.mkdir()
    run = [sys.executable, "-m", "diffcloth"]
    res = subprocess.run(
        run + ["warmup", str(cfg), "--cache", str(cache)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "TMPDIR": str(tmp)},
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert "compiled in" in res.stdout
    before = sorted(p.name for p in cache.iterdir())
    assert len(before) > 3
    res = subprocess.run(
        run + ["fit", str(cfg), "--cache", str(cache), "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert (tmp_path / "out" / "report.md").is_file()
    assert not any(tmp.iterdir())  # the warm-up's one-step fit folder is gone
    assert sorted(p.name for p in cache.iterdir()) == before
