"""The optax fitting loop, multi-start and the non-finite stop (ROBUSTNESS rows 28 and 30)."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from diffcloth.fit.constraints import Positive
from diffcloth.fit.loop import FitResult, fit_multistart, fit_params, load_checkpoint
from diffcloth.fit.losses import pyramid_loss

T = jnp.linspace(0.0, 2.0, 40)
TRUTH = {"amplitude": 2.0, "rate": 1.5}
CONS = {"amplitude": Positive(), "rate": Positive()}
TRACES = {"decay": 0}


def decay(p):
    return p["amplitude"] * jnp.exp(-p["rate"] * T)


Y = decay(TRUTH)


def decay_loss(p):
    TRACES["decay"] += 1
    return jnp.mean((decay(p) - Y) ** 2)


def cliff_loss(p):
    """(k - 5)^2 for k > 1; for k < 1 a slope that leads down to a NaN region below k = 0.1."""
    k = p["k"]
    return jnp.where(k > 1, (k - 5) ** 2, 8 + 8 * k) + 0.0 * jnp.sqrt(k - 0.1)  # NaN below 0.1


X = jnp.arange(24, dtype=jnp.result_type(float))


def blob(width):
    """A 1-D Gaussian stripe image (24 x 24 x 1) of the given width in pixels."""
    row = jnp.exp(-0.5 * ((X - 11.5) / width) ** 2)
    return (jnp.ones((24, 1)) * row[None, :])[:, :, None]


BLOB_TARGET = blob(3.0)


def blob_loss(p):
    return pyramid_loss(blob(p["width"]), BLOB_TARGET, num_levels=3)


@pytest.fixture(scope="module")
def decay_fit():
    return fit_params(
        decay_loss,
        {"amplitude": 1.0, "rate": 0.5},
        CONS,
        steps=400,
        learning_rate=0.05,
        patience=None,
        progress=False,
    )


def test_recovers_exponential_decay(decay_fit):
    r = decay_fit
    assert isinstance(r, FitResult) and r.ok and r.status == "max_steps"
    for name, true in TRUTH.items():
        assert abs(float(r.params[name]) - true) / true < 1e-3, (name, r.params[name])
    assert r.iterations == 400 and len(r.history) == 401
    assert r.history.loss[-1] < 1e-3 * r.history.loss[0]
    np.testing.assert_allclose(r.history.params["rate"][0], 0.5)
    assert r.history.grad_norm["rate"].shape == (401,) and r.history.grad_norm["rate"][0] > 0
    assert r.initial == {"amplitude": 1.0, "rate": 0.5}
    assert r.loss == pytest.approx(r.history.loss.min())
    assert r.wall_s > 0 and "max_steps" in r.summary()


def test_one_compile_for_repeated_fits(decay_fit):
    before = TRACES["decay"]
    r = fit_params(
        decay_loss,
        {"amplitude": 3.0, "rate": 2.5},
        CONS,
        steps=5,
        learning_rate=0.05,
        progress=False,
    )
    assert TRACES["decay"] == before  # same loss, constraints and optimizer: no retrace
    assert r.iterations == 5


def blob_loss_args(p, target):
    TRACES["blob_args"] = TRACES.get("blob_args", 0) + 1
    return pyramid_loss(blob(p["width"]), target, num_levels=3)


def test_loss_args_are_traced_not_baked_in():
    kw = dict(steps=200, learning_rate=0.05, patience=None, progress=False)
    r1 = fit_params(
        blob_loss_args, {"width": 6.0}, {"width": "positive"}, loss_args=(blob(2.0),), **kw
    )
    r2 = fit_params(
        blob_loss_args, {"width": 6.0}, {"width": "positive"}, loss_args=(blob(4.0),), **kw
    )
    assert TRACES["blob_args"] == 1  # a new target of the same shape: no recompilation
    assert abs(float(r1.params["width"]) - 2.0) < 1e-2
    assert abs(float(r2.params["width"]) - 4.0) < 1e-2
    m = fit_multistart(
        blob_loss_args,
        [{"width": 1.5}, {"width": 6.0}],
        {"width": "positive"},
        loss_args=(blob(4.0),),
        **kw,
    )
    assert abs(float(m.params["width"]) - 4.0) < 1e-2


def test_recovers_blob_width_from_image():
    r = fit_params(
        blob_loss,
        {"width": 6.0},
        {"width": Positive()},
        steps=300,
        learning_rate=0.05,
        patience=None,
        progress=True,
    )
    assert abs(float(r.params["width"]) - 3.0) / 3.0 < 1e-3


def test_nonfinite_stops_with_message_and_keeps_last_finite(tmp_path):
    path = tmp_path / "ckpt.npz"
    r = fit_params(
        cliff_loss,
        {"k": 0.5},
        {"k": Positive()},
        steps=300,
        learning_rate=0.1,
        progress=False,
        checkpoint_path=path,
    )
    assert r.status == "nonfinite" and not r.ok
    k = r.iterations  # updates applied before the bad step
    assert r.message.startswith(f"non-finite loss/grad at step {k}")
    assert f"last finite params saved to {path}" in r.message
    assert 0 < k < 300
    last = float(r.last_finite["k"])
    assert np.isfinite(last) and last == pytest.approx(float(r.history.params["k"][k - 1]))
    assert np.isfinite(r.history.loss[:k]).all() and not np.isfinite(r.history.loss[k])
    assert all(np.isfinite(float(v)) for v in r.params.values())
    ck = load_checkpoint(path)
    assert float(ck["last_finite"]["k"]) == pytest.approx(last)
    assert (tmp_path / "ckpt.json").exists()


def test_nonfinite_not_hidden_by_apply_if_finite():
    # Even with optax's own guard, the loop reports the non-finite step instead of carrying on.
    opt = optax.apply_if_finite(optax.adam(0.1), max_consecutive_errors=1000)
    r = fit_params(
        cliff_loss, {"k": 0.5}, {"k": Positive()}, steps=300, optimizer=opt, progress=False
    )
    assert r.status == "nonfinite" and "non-finite loss/grad" in r.message
    assert "FitResult.last_finite" in r.message


def test_multistart_one_diverging_start_does_not_poison_others():
    inits = [{"k": 0.5}, {"k": 2.0}, {"k": 9.0}]
    m = fit_multistart(
        cliff_loss,
        inits,
        {"k": Positive()},
        steps=250,
        learning_rate=0.05,
        patience=None,
        progress=False,
    )
    assert m.statuses[0] == "nonfinite"
    assert m.statuses[1:] == ["max_steps", "max_steps"]
    assert m.best_index in (1, 2)
    assert abs(float(m.params["k"]) - 5.0) / 5.0 < 1e-3
    for r in m.results[1:]:
        assert np.isfinite(r.history.loss).all()
        assert abs(float(r.params["k"]) - 5.0) < 1e-2
    # The diverging start froze at its last finite parameters.
    assert np.isfinite(float(m.results[0].last_finite["k"]))
    # The others match a single fit from the same start exactly.
    single = fit_params(
        cliff_loss,
        {"k": 2.0},
        {"k": Positive()},
        steps=250,
        learning_rate=0.05,
        patience=None,
        progress=False,
    )
    np.testing.assert_allclose(m.results[1].history.loss, single.history.loss, rtol=1e-10)


def test_multistart_stacked_batch_input():
    stacked = {"amplitude": jnp.array([1.0, 4.0]), "rate": jnp.array([0.5, 3.0])}
    m = fit_multistart(decay_loss, stacked, CONS, steps=20, learning_rate=0.05, progress=False)
    assert len(m.results) == 2 and m.losses.shape == (2,)
    assert m.results[1].initial["rate"] == pytest.approx(3.0)


def test_early_stopping_and_callback():
    r = fit_params(
        decay_loss,
        {"amplitude": 1.0, "rate": 0.5},
        CONS,
        steps=400,
        learning_rate=0.05,
        loss_tol=1e-4,
        progress=False,
    )
    assert r.status == "converged" and r.iterations < 400 and r.loss <= 1e-4
    seen = []

    def cb(step, info):
        seen.append((step, info["loss"]))
        return step == 4

    r = fit_params(
        decay_loss,
        {"amplitude": 1.0, "rate": 0.5},
        CONS,
        steps=400,
        learning_rate=0.05,
        callback=cb,
        progress=False,
    )
    assert r.status == "stopped" and r.iterations == 5 and len(seen) == 5
    flat = lambda p: (p["k"] - 1.0) ** 2 * 0.0 + 1.0  # noqa: E731  constant loss stalls at once
    r = fit_params(
        flat,
        {"k": 2.0},
        {"k": Positive()},
        steps=400,
        learning_rate=0.05,
        patience=10,
        progress=False,
    )
    assert r.status == "stalled" and r.iterations == 11


def test_array_parameters_and_float32():
    target = jnp.array([0.2, 0.5, 0.9], dtype=jnp.float32)

    def loss(p):
        return jnp.sum((p["color"] - target) ** 2)

    r = fit_params(
        loss,
        {"color": jnp.array([0.5, 0.5, 0.5], dtype=jnp.float32)},
        {"color": (0.0, 1.0)},
        steps=300,
        learning_rate=0.05,
        patience=None,
        progress=False,
    )
    assert r.params["color"].dtype == np.float32
    np.testing.assert_allclose(r.params["color"], target, atol=2e-3)
    assert r.history.params["color"].shape == (301, 3)


def test_bad_arguments():
    with pytest.raises(ValueError, match="rate"):
        fit_params(decay_loss, {"amplitude": 1.0, "rate": -1.0}, CONS, steps=3, progress=False)
    with pytest.raises(ValueError, match="unknown parameters"):
        fit_params(decay_loss, {"amplitude": 1.0}, CONS, steps=3, progress=False)
    with pytest.raises(ValueError, match="steps"):
        fit_params(decay_loss, {"amplitude": 1.0, "rate": 1.0}, CONS, steps=-1)
    with pytest.raises(ValueError, match="not both"):
        fit_params(
            decay_loss,
            {"amplitude": 1.0, "rate": 1.0},
            CONS,
            steps=3,
            optimizer=optax.sgd(0.1),
            learning_rate=0.1,
        )
    with pytest.raises(ValueError, match="must be finite"):
        fit_params(decay_loss, {"amplitude": float("nan"), "rate": 1.0}, None, steps=3)
    with pytest.raises(ValueError, match=r"inits\[1\] has names"):
        fit_multistart(decay_loss, [{"amplitude": 1.0, "rate": 1.0}, {"rate": 1.0}], CONS)
    with pytest.raises(ValueError, match="leading"):
        fit_multistart(decay_loss, {"amplitude": 1.0, "rate": 1.0}, CONS)


def test_grad_norms_are_raw_space(decay_fit):
    # the history's gradient norm at step 0 equals |d loss / d raw| computed directly
    raw0 = {k: jnp.log(jnp.asarray(v)) for k, v in {"amplitude": 1.0, "rate": 0.5}.items()}
    g = jax.grad(lambda r: decay_loss({k: jnp.exp(v) for k, v in r.items()}))(raw0)
    np.testing.assert_allclose(
        decay_fit.history.grad_norm["rate"][0], abs(float(g["rate"])), rtol=1e-8
    )


def _quadratic(p):
    return jnp.sum((p["a"] - 3.0) ** 2)


def test_fit_params_and_multistart_take_fit_settings():
    """settings=FitSettings(...) is the same as the keywords; a keyword overrides the settings'
    field; an unknown keyword is a TypeError naming the fields."""
    from diffcloth.fit import FitSettings

    st = FitSettings(steps=12, learning_rate=0.1, progress=False, patience=None)
    r1 = fit_params(_quadratic, {"a": 1.0}, settings=st)
    r2 = fit_params(_quadratic, {"a": 1.0}, steps=12, learning_rate=0.1, progress=False,
                    patience=None)  # fmt: skip
    assert r1.iterations == r2.iterations == 12
    np.testing.assert_array_equal(r1.history.loss, r2.history.loss)
    assert fit_params(_quadratic, {"a": 1.0}, settings=st, steps=4).iterations == 4
    multi = fit_multistart(_quadratic, [{"a": 1.0}, {"a": 2.5}], settings=st)
    assert multi.best_index == 1 and len(multi.results) == 2
    with pytest.raises(TypeError, match="unknown fit option"):
        fit_params(_quadratic, {"a": 1.0}, stepz=3)
