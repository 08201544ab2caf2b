"""Run-time switches: XLA's small-loop threshold set at import, and the run environment record."""

import os
import subprocess
import sys

import pytest

from diffcloth import runtime
from diffcloth.runtime import SMALL_LOOP_BYTES, SMALL_LOOP_KEY, tune_xla_cpu


@pytest.fixture
def fresh_backend(monkeypatch):
    """tune_xla_cpu as if no JAX backend had started yet (this test process has started one)."""
    monkeypatch.setattr(runtime, "_backend_started", lambda: False)
    monkeypatch.delenv("DIFFCLOTH_XLA_TUNING", raising=False)


def test_adds_the_threshold_to_empty_flags(fresh_backend, monkeypatch):
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert tune_xla_cpu()
    assert os.environ["XLA_FLAGS"] == (
        f"--xla_backend_extra_options={SMALL_LOOP_KEY}={SMALL_LOOP_BYTES}"
    )


def test_extends_the_users_extra_options_and_keeps_other_flags(fresh_backend, monkeypatch):
    monkeypatch.setenv(
        "XLA_FLAGS", "--xla_force_host_platform_device_count=4 --xla_backend_extra_options=a=1"
    )
    assert tune_xla_cpu(1234)
    assert os.environ["XLA_FLAGS"] == (
        f"--xla_force_host_platform_device_count=4 "
        f"--xla_backend_extra_options=a=1,{SMALL_LOOP_KEY}=1234"
    )


@pytest.mark.parametrize(
    "env",
    [
        {"XLA_FLAGS": f"--xla_backend_extra_options={SMALL_LOOP_KEY}=77"},  # the user's value wins
        {"DIFFCLOTH_XLA_TUNING": "off", "XLA_FLAGS": ""},  # opted out
    ],
)
def test_leaves_flags_alone_when_told(fresh_backend, monkeypatch, env):
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    before = os.environ["XLA_FLAGS"]
    assert not tune_xla_cpu()
    assert os.environ["XLA_FLAGS"] == before


def test_no_change_once_a_backend_has_started(monkeypatch):
    import jax

    jax.devices()  # started: XLA has read its flags, a change would be silently ignored
    monkeypatch.delenv("DIFFCLOTH_XLA_TUNING", raising=False)
    monkeypatch.setenv("XLA_FLAGS", "")
    assert not tune_xla_cpu()
    assert os.environ["XLA_FLAGS"] == ""


SMALL_SCAN = """
import os, sys
import diffcloth  # sets the threshold unless told not to
import jax, jax.numpy as jnp

def run(x):
    def body(c, _):
        return 0.5 * c + jnp.roll(c, 1, 0), None
    return jax.lax.scan(body, x, None, length=50)[0]

text = jax.jit(run).lower(jnp.ones((130, 3))).compile().as_text()
print(os.environ.get("XLA_FLAGS", ""), "|", 'xla_cpu_small_call="true"' in text)
"""


@pytest.mark.parametrize("tuning", ["on", "off"])
def test_import_makes_small_scans_one_compiled_loop(tuning):
    """In a fresh process, `import diffcloth` makes XLA compile a small scan as one function."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["DIFFCLOTH_XLA_TUNING"] = tuning
    env["JAX_PLATFORMS"] = "cpu"
    out = subprocess.run(
        [sys.executable, "-c", SMALL_SCAN], env=env, capture_output=True, text=True, check=True
    ).stdout.strip()
    flags, hoisted = out.rsplit("|", 1)
    assert (SMALL_LOOP_KEY in flags) == (tuning == "on")
    assert hoisted.strip() == ("True" if tuning == "on" else "False")


def test_environment_records_the_xla_flags(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_extra_options=a=1")
    assert runtime.environment()["xla_flags"] == "--xla_backend_extra_options=a=1"
