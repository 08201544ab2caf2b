"""Run-time switches: XLA's small-loop threshold set at import, and the run environment record."""

import functools
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from diffcloth import runtime
from diffcloth.runtime import (
    SMALL_LOOP_BYTES,
    SMALL_LOOP_KEY,
    YNN_FUSION_FLAG,
    YNN_NO_REDUCE,
    tune_xla_cpu,
)

SMALL_LOOP = f"--xla_backend_extra_options={SMALL_LOOP_KEY}={SMALL_LOOP_BYTES}"


@pytest.fixture
def fresh_backend(monkeypatch):
    """tune_xla_cpu as if no JAX backend had started yet (this test process has started one)."""
    monkeypatch.setattr(runtime, "_backend_started", lambda: False)
    monkeypatch.delenv("DIFFCLOTH_XLA_TUNING", raising=False)


@pytest.mark.parametrize("ynn", [True, False])
def test_adds_the_threshold_and_the_ynn_option_to_empty_flags(fresh_backend, monkeypatch, ynn):
    monkeypatch.setattr(runtime, "_jaxlib_has_ynn_flag", lambda: ynn)
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert tune_xla_cpu()
    assert os.environ["XLA_FLAGS"] == (f"{SMALL_LOOP} {YNN_NO_REDUCE}" if ynn else SMALL_LOOP)


def test_the_ynn_option_only_for_the_jaxlib_releases_checked(monkeypatch):
    import jaxlib.version

    for version, want in [("0.10.2", True), ("0.10.9", True), ("0.10.1", False),
                          ("0.11.0", False), ("0.4.30", False), ("0.10.2.dev2026", True),
                          ("0.11.0rc1", False)]:  # fmt: skip
        monkeypatch.setattr(jaxlib.version, "__version__", version)
        assert runtime._jaxlib_has_ynn_flag() == want, version
    monkeypatch.setattr(jaxlib.version, "__version__", "0.10.x")
    assert not runtime._jaxlib_has_ynn_flag()  # unparsable: XLA's defaults


def test_extends_the_users_extra_options_and_keeps_other_flags(fresh_backend, monkeypatch):
    monkeypatch.setattr(runtime, "_jaxlib_has_ynn_flag", lambda: True)
    monkeypatch.setenv(
        "XLA_FLAGS", "--xla_force_host_platform_device_count=4 --xla_backend_extra_options=a=1"
    )
    assert tune_xla_cpu(1234)
    assert os.environ["XLA_FLAGS"] == (
        f"--xla_force_host_platform_device_count=4 "
        f"--xla_backend_extra_options=a=1,{SMALL_LOOP_KEY}=1234 {YNN_NO_REDUCE}"
    )


def test_the_users_own_values_win(fresh_backend, monkeypatch):
    monkeypatch.setattr(runtime, "_jaxlib_has_ynn_flag", lambda: True)
    monkeypatch.setenv("XLA_FLAGS", f"--xla_backend_extra_options={SMALL_LOOP_KEY}=77")
    assert tune_xla_cpu()  # only the YNN option is added
    assert (
        os.environ["XLA_FLAGS"]
        == f"--xla_backend_extra_options={SMALL_LOOP_KEY}=77 {YNN_NO_REDUCE}"
    )


@pytest.mark.parametrize(
    "env",
    [
        {"XLA_FLAGS": f"--xla_backend_extra_options={SMALL_LOOP_KEY}=77 {YNN_FUSION_FLAG}=+dot"},
        {"DIFFCLOTH_XLA_TUNING": "off", "XLA_FLAGS": ""},  # opted out
    ],
)
def test_leaves_flags_alone_when_told(fresh_backend, monkeypatch, env):
    monkeypatch.setattr(runtime, "_jaxlib_has_ynn_flag", lambda: True)
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


# One script per fresh process, run with the settings on and off (each process's results cached
# for both tests below): a small net's float64 material gradient (XLA's small-loop option) and a
# float32 channel sum (the YNN option), with what XLA built and whether malloc was tuned.
FRESH = """
import json, os
import diffcloth  # sets XLA_FLAGS and the allocator unless told not to
import jax, jax.numpy as jnp
from diffcloth import physics, runtime

x = jnp.arange(64 * 64 * 3, dtype=jnp.float32).reshape(64, 64, 3) / 1000.0
f = jax.jit(lambda x: jnp.sum(jnp.sin(x) * x, axis=-1))  # a reduction over a 3-channel axis
ynn = f.lower(x).compile().as_text().count("__ynn_fusion")
channel_sum = f(x).tolist()

jax.config.update("jax_enable_x64", True)
net = physics.grid_net(5, 6, (0.5, 0.4), pinned="top_row")
sim = physics.make_sim(1 / 60, num_substeps=8)
s0 = physics.rest_state(net)

def loss(m):
    x = physics.rollout(net, sim, m, s0, num_frames=3).x[-1]
    return jnp.sum((x - net.rest - 0.01) ** 2)

grad = jax.jit(jax.grad(loss))
text = grad.lower(physics.make_material()).compile().as_text()
g = grad(physics.make_material())
print(json.dumps(dict(flags=os.environ.get("XLA_FLAGS", ""),
                      hoisted=text.count('xla_cpu_small_call="true"'),
                      grad={k: float(v) for k, v in vars(g).items() if jnp.ndim(v) == 0},
                      ynn=ynn, value=channel_sum, malloc=runtime.malloc_tuned())))
"""


@functools.cache
def _fresh(tuning: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["DIFFCLOTH_XLA_TUNING"] = env["DIFFCLOTH_MALLOC_TUNING"] = tuning
    env["JAX_PLATFORMS"] = "cpu"
    out = subprocess.run(
        [sys.executable, "-c", FRESH], env=env, capture_output=True, text=True, check=True
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def test_import_compiles_small_net_loops_as_one_function_with_the_same_gradient():
    """Fresh processes: with the option (the default), XLA compiles the small net's substep scans
    as one function; the material gradient equals the one from the thunk runtime (option off),
    which the physics tests check against finite differences."""
    on, off = _fresh("on"), _fresh("off")
    assert SMALL_LOOP_KEY in on["flags"] and SMALL_LOOP_KEY not in off["flags"]
    assert on["hoisted"] > off["hoisted"]  # XLA's own 1 kB threshold may take in a tiny loop
    assert on["grad"].keys() == off["grad"].keys() and len(on["grad"]) >= 5
    assert any(v != 0.0 for v in off["grad"].values())
    for k, v in off["grad"].items():
        assert on["grad"][k] == pytest.approx(v, rel=1e-9, abs=1e-15), k


def test_environment_records_the_xla_flags(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_extra_options=a=1")
    assert runtime.environment()["xla_flags"] == "--xla_backend_extra_options=a=1"


def test_import_keeps_reductions_out_of_ynn_fusions_and_tunes_malloc():
    """Fresh processes: with the options (the default) XLA builds no YNNPACK fusion for a
    channel sum and glibc's malloc keeps freed memory; the values equal XLA's defaults' to
    float32 rounding (the two sum in different orders)."""
    on, off = _fresh("on"), _fresh("off")
    np.testing.assert_allclose(on["value"], off["value"], rtol=1e-6)
    assert not off["malloc"] and YNN_FUSION_FLAG not in off["flags"]
    import platform

    assert on["malloc"] == (platform.system() == "Linux" and platform.libc_ver()[0] == "glibc")
    assert on["malloc"] == runtime._glibc()
    if runtime._jaxlib_has_ynn_flag():  # the jaxlib this was checked on: the flag is added
        assert YNN_NO_REDUCE in on["flags"]
        assert off["ynn"] > 0 and on["ynn"] == 0
    else:  # another jaxlib: XLA might not know the flag, so it is not added
        assert YNN_FUSION_FLAG not in on["flags"]
