"""What the wheel ships: the version, the py.typed marker, and the example configs as package data
that the CLI finds when a config path is not on disk (`cli_commands.resolve_config`). No compile."""

import re
import tomllib
from pathlib import Path

import pytest

import diffcloth as dc
from diffcloth import cli
from diffcloth.cli_commands import resolve_config, shipped_configs_dir

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_version_matches_pyproject_and_the_cli_prints_it(capsys):
    version = PYPROJECT["project"]["version"]
    # the fallback for a source tree that is not installed stays in step with pyproject.toml
    fallback = re.search(r'__version__ = "([^"]+)"', (ROOT / "diffcloth/__init__.py").read_text())
    assert fallback and fallback.group(1) == version
    assert isinstance(dc.__version__, str) and dc.__version__
    with pytest.raises(SystemExit) as exit_:
        cli.main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"diffcloth {dc.__version__}"


def test_py_typed_marker_and_configs_ship_in_the_wheel():
    assert (ROOT / "diffcloth/py.typed").is_file()
    include = PYPROJECT["tool"]["hatch"]["build"]["targets"]["wheel"]["force-include"]
    assert include == {"configs": "diffcloth/configs_data"}
    assert "docs" in PYPROJECT["project"]["optional-dependencies"]


def test_a_missing_config_path_reads_the_shipped_copy(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # outside the checkout: no configs/ here
    root = shipped_configs_dir()
    assert root is not None and (root / "drape_fit.toml").is_file()
    for given, rel in [
        ("configs/drape_fit.toml", "drape_fit.toml"),
        ("drape_fit.toml", "drape_fit.toml"),
        ("configs/experiments/joint.toml", "experiments/joint.toml"),
        ("somewhere/configs/hang.toml", "hang.toml"),
    ]:
        found = resolve_config(given)
        assert Path(found) == root / rel
        assert Path(found).read_bytes() == (ROOT / "configs" / rel).read_bytes()
        out = capsys.readouterr().out
        assert out.count("\n") == 1 and given in out and found in out
    # nothing shipped under that name, or not a config: unchanged, so the command reports it
    for given in ["configs/nope.toml", "other/drape_fit.toml", "configs/../drape_fit.toml"]:
        assert resolve_config(given) == given
    assert capsys.readouterr().out == ""


def test_a_config_on_disk_wins(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs/drape_fit.toml").write_text("# mine\n")
    assert resolve_config("configs/drape_fit.toml") == "configs/drape_fit.toml"
    assert capsys.readouterr().out == ""
    args = cli.build_parser().parse_args(["fit", "configs/hang.toml", "--out", "o"])
    cli._resolve_configs(args)  # what main() does before the command runs
    assert Path(args.config) == shipped_configs_dir() / "hang.toml"
