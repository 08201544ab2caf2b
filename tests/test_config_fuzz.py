"""Fuzz the configs (issue 15): random mutations of every shipped config, written back as TOML,
fed to `load_scene` and to the CLI's pre-work checks (`diffcloth.cli.check_config`). The only
allowed outcomes are a valid Scene or a ConfigError (MemoryLimitError for sizes over the limit,
UnstableStepError from the CLI's stability gate):
never a traceback from deeper code, never a silent NaN in the built scene."""

import json
import math
import os
import tomllib
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import diffcloth as dc
from diffcloth.cli import check_config
from diffcloth.config import ConfigError
from diffcloth.memory import MemoryLimitError
from diffcloth.physics import UnstableStepError

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted(p for p in (ROOT / "configs").rglob("*.toml") if not p.name.startswith("."))
BASES = {p.name: tomllib.loads(p.read_text()) for p in CONFIGS}


def _scalar(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_scalar(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_scalar(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def to_toml(data: dict, prefix: str = "") -> str:
    """A minimal TOML writer (tables, arrays of tables, inline values) for the fuzz inputs."""
    lines, tables = [], []
    for k, v in data.items():
        key = json.dumps(k)
        if isinstance(v, dict) and v and all(isinstance(x, dict) for x in v.values()):
            tables.append((k, v))
        elif isinstance(v, dict):
            tables.append((k, v))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            tables.append((k, v))
        else:
            lines.append(f"{key} = {_scalar(v)}")
    out = "\n".join(lines) + "\n"
    for k, v in tables:
        name = f"{prefix}{json.dumps(k)}"
        if isinstance(v, list):
            for item in v:
                out += f"\n[[{name}]]\n" + to_toml(item, name + ".")
        else:
            out += f"\n[{name}]\n" + to_toml(v, name + ".")
    return out


def _paths(data, path=()):
    for k, v in data.items():
        yield path + (k,)
        if isinstance(v, dict):
            yield from _paths(v, path + (k,))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for i, item in enumerate(v):
                yield from _paths(item, path + (k, i))


VALUES = st.one_of(
    st.integers(-(10**12), 10**12),
    st.sampled_from([0, 1, 2, -1, 3, 7, 100000, 10**9]),
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from([0.0, -0.0, 1e-12, -1e-3, 1e30, 1e300, float("nan"), float("inf")]),
    st.text(max_size=6),
    st.sampled_from(["none", "default", "xz", "xy", "phong", "bspline", "sphere", "box", ""]),
    st.booleans(),
    st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), max_size=4),
    st.lists(st.integers(-3, 20), max_size=4),
    st.lists(st.lists(st.integers(-2, 20), max_size=3), max_size=3),
    st.just({}),
    st.dictionaries(st.sampled_from(["a", "radius", "center"]), st.integers(-1, 2), max_size=2),
)


@st.composite
def mutated(draw):
    name = draw(st.sampled_from(sorted(BASES)))
    data = json.loads(json.dumps(BASES[name]))  # deep copy (configs hold no NaN)
    for _ in range(draw(st.integers(1, 3))):
        paths = list(_paths(data))
        op = draw(st.sampled_from(["set", "set", "set", "delete", "add"]))
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        parent = data
        for p in path[:-1]:
            parent = parent[p]
        if op == "delete":
            del parent[path[-1]]
        elif op == "add" and isinstance(parent, dict):
            parent[draw(st.sampled_from(["extra", "rows", "num_frames", "free", "x"]))] = draw(
                VALUES
            )
        else:
            parent[path[-1]] = draw(VALUES)
    return name, data


def _outcome(fn):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # stability/small-body warnings are fine outcomes
        try:
            return fn()
        except (ConfigError, MemoryLimitError, UnstableStepError) as err:  # refused before work
            assert str(err), "an error must say what is wrong"
            return err


EXAMPLES = int(os.environ.get("DIFFCLOTH_FUZZ_EXAMPLES", "40"))


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck),
          derandomize=True)  # fmt: skip
@given(case=mutated())
def test_mutated_configs_give_a_scene_or_a_config_error(tmp_path_factory, case):
    name, data = case
    try:
        text = to_toml(data)
        tomllib.loads(text)
    except (TypeError, tomllib.TOMLDecodeError):
        return  # not expressible as TOML (e.g. a table replaced inside an inline array)
    path = tmp_path_factory.mktemp("fuzz") / name
    path.write_text(text)
    got = _outcome(lambda: dc.load_scene(path))
    if isinstance(got, dc.Scene):
        for leaf in jax.tree_util.tree_leaves(got):
            a = np.asarray(leaf)
            if a.dtype.kind == "f":
                assert np.all(np.isfinite(a)), f"{name}: a non-finite value reached the Scene"
    for command in ("simulate", "render", "fit"):
        _outcome(lambda command=command: check_config(path, command))


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_the_writer_round_trips_the_shipped_configs(path):
    data = tomllib.loads(path.read_text())
    assert tomllib.loads(to_toml(data)) == data
