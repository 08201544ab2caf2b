"""Batching: mismatched sizes, per-element finite flags, sharded == unsharded on 4 CPU devices."""

import os
import subprocess
import sys
import textwrap

import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import batch


def test_mismatched_batch_sizes_name_the_leaves():
    with pytest.raises(ValueError, match=r"\['bend'\]: 2, \['stretch'\]: 3"):
        batch.batch_size({"stretch": jnp.ones(3), "bend": jnp.ones(2)})
    with pytest.raises(ValueError, match="scalar"):
        batch.batch_size({"stretch": jnp.ones(())})


def test_one_diverging_element_does_not_poison_the_others():
    def f(p, x):
        return jnp.log(p["a"]) * x  # a <= 0 diverges

    out, ok = batch.vmap_batched(f, {"a": jnp.array([1.0, -1.0, 2.0])}, jnp.ones(2))
    np.testing.assert_array_equal(np.asarray(ok), [True, False, True])
    assert np.all(np.isfinite(np.asarray(out)[[0, 2]]))


SHARDED_SCRIPT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    from diffcloth import batch
    assert len(jax.devices()) == 4, jax.devices()
    def f(p):
        x = jnp.linspace(0.0, 1.0, 64)
        return jnp.sum(jnp.sin(p["k"] * x) ** 2) + p["b"]
    params = {"k": jnp.linspace(1.0, 8.0, 8), "b": jnp.arange(8.0)}
    ref = jax.jit(jax.vmap(f))(params)
    sharded = batch.shard_batch(params, batch.make_mesh(4))
    out = jax.jit(jax.vmap(f))(sharded)
    assert len(out.sharding.device_set) == 4, out.sharding
    np.testing.assert_allclose(np.asarray(out), np.asarray(ref), rtol=1e-6)

    # engines.adam_multistart(devices=4): the starts are sharded, equal to the one-device fit
    from diffcloth.fit.engines import adam_multistart as fit_multistart
    loss = lambda q: (jnp.log(q["k"]) - 0.7) ** 2 + 0.1 * jnp.sin(3.0 * q["k"]) ** 2
    inits = [{"k": v} for v in (0.5, 1.0, 2.0, 4.0)]
    kw = dict(steps=25, learning_rate=0.1, progress=False, patience=None)
    one = fit_multistart(loss, inits, {"k": "positive"}, **kw)
    four = fit_multistart(loss, inits, {"k": "positive"}, devices=4, **kw)
    np.testing.assert_allclose(four.losses, one.losses, rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(four.params["k"], one.params["k"], rtol=1e-5)
    assert four.best_index == one.best_index
    try:
        fit_multistart(loss, inits[:3], {"k": "positive"}, devices=4, **kw)
    except ValueError as err:
        assert "multiple of devices (4)" in str(err), err
    else:
        raise AssertionError("3 starts on 4 devices must raise")
    print("SHARDED_OK")
    """
)


def test_sharded_batch_equals_unsharded_on_four_cpu_devices():
    env = dict(
        os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu"
    )
    res = subprocess.run(
        [sys.executable, "-c", SHARDED_SCRIPT], env=env, capture_output=True, text=True
    )
    assert "SHARDED_OK" in res.stdout, res.stderr[-2000:]


def test_make_mesh_rejects_too_many_devices():
    with pytest.raises(ValueError, match="devices must be in"):
        batch.make_mesh(10_000)
