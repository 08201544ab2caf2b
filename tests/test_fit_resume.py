"""Interrupt a fit (the stop event, as SIGINT/SIGTERM set it), checkpoint it, resume it: the
resumed fit ends exactly where an uninterrupted fit of the same total steps ends (issue 15)."""

import os
import signal
import threading

import jax.numpy as jnp
import numpy as np
import optax
import pytest

from diffcloth.fit.constraints import Positive
from diffcloth.fit.interrupt import catch_interrupts
from diffcloth.fit.loop import fit_multistart, fit_params, load_checkpoint

T = jnp.linspace(0.0, 2.0, 30)
Y = 2.0 * jnp.exp(-1.5 * T)
CONS = {"amplitude": Positive(), "rate": Positive()}
INIT = {"amplitude": 1.0, "rate": 0.5}
STEPS = 40
OPT = optax.chain(
    optax.clip_by_global_norm(1.0), optax.adam(optax.cosine_decay_schedule(0.05, STEPS, 0.1))
)


def loss(p):
    return jnp.mean((p["amplitude"] * jnp.exp(-p["rate"] * T) - Y) ** 2)


class StopAt:
    """A stop event that becomes set once the loop has called the callback `k` times."""

    def __init__(self, k):
        self.k, self.calls = k, 0

    def callback(self, step, info):
        self.calls += 1

    def is_set(self):
        return self.calls >= self.k


def _run(**kw):
    return fit_params(loss, INIT, CONS, steps=STEPS, optimizer=OPT, progress=False,
                      patience=None, **kw)  # fmt: skip


def test_interrupt_writes_checkpoint_and_resume_matches_uninterrupted(tmp_path):
    full = _run()
    path = tmp_path / "ck.npz"
    stop = StopAt(13)
    part = _run(stop=stop, callback=stop.callback, checkpoint_path=path)
    assert part.status == "interrupted" and "interrupted after step 12" in part.message
    assert part.iterations == 13 and len(part.history) == 13
    ck = load_checkpoint(path)
    assert ck["step"] == 13 and ck["opt_state"] and set(ck["best"]) == set(INIT)
    assert ck["history"]["loss"].shape == (13, 1)
    assert ck["meta"]["status"] == "max_steps"  # saved before the stop was marked
    resumed = _run(resume=path, checkpoint_path=path)
    assert resumed.status == full.status == "max_steps"
    assert resumed.iterations == full.iterations == STEPS
    np.testing.assert_array_equal(resumed.history.loss, full.history.loss)
    for k in INIT:
        np.testing.assert_array_equal(resumed.params[k], full.params[k])
        np.testing.assert_array_equal(resumed.history.params[k], full.history.params[k])
    assert resumed.best_step == full.best_step and resumed.loss == full.loss


def test_multistart_resume_matches_and_bad_checkpoints_are_named(tmp_path):
    inits = [INIT, {"amplitude": 3.0, "rate": 2.5}]
    kw = dict(steps=STEPS, optimizer=OPT, progress=False, patience=5, tol=1e-3)
    full = fit_multistart(loss, inits, CONS, **kw)
    stop = StopAt(4)
    path = tmp_path / "m.npz"
    part = fit_multistart(loss, inits, CONS, stop=stop, callback=stop.callback,
                          checkpoint_path=path, **kw)  # fmt: skip
    assert "interrupted" in part.statuses
    res = fit_multistart(loss, inits, CONS, resume=path, **kw)
    assert res.statuses == full.statuses
    np.testing.assert_array_equal(res.losses, full.losses)
    with pytest.raises(ValueError, match="the checkpoint has 2 starts, this fit 1"):
        fit_params(loss, INIT, CONS, steps=STEPS, optimizer=OPT, progress=False, resume=path)
    with pytest.raises(ValueError, match="checkpoint fits"):
        fit_multistart(lambda p: jnp.sum(p["a"] ** 2), [{"a": 1.0}, {"a": 2.0}], resume=path,
                       steps=STEPS, progress=False)  # fmt: skip
    with pytest.raises(ValueError, match="cannot read checkpoint"):
        _run(resume=tmp_path / "missing.npz")


def test_sigterm_sets_the_stop_event_and_handlers_are_restored():
    before = signal.getsignal(signal.SIGTERM)
    with catch_interrupts(message=False) as stop:
        assert not stop.is_set()
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(100):  # the handler runs between bytecodes of the main thread
            if stop.is_set():
                break
        assert stop.is_set() and stop.signum == signal.SIGTERM
        with pytest.raises(KeyboardInterrupt):  # a second signal stops at once
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(100):
                pass
    assert signal.getsignal(signal.SIGTERM) is before
    assert isinstance(stop, threading.Event)
