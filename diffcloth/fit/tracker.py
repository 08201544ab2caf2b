"""Host-side bookkeeping of the Adam loop: stopping rules, history, best point, progress bar."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from diffcloth.fit.constraints import to_physical, to_raw
from diffcloth.fit.results import FitResult, History, _fmt


def _progress_bar(total: int, progress: bool, desc: str):
    from tqdm.auto import tqdm

    return tqdm(
        total=total,
        disable=None if progress else True,
        desc=desc,
        unit="step",
        dynamic_ncols=True,
        leave=True,
    )


def _check_stopping(steps, tol, patience, loss_tol):
    if not isinstance(steps, (int, np.integer)) or isinstance(steps, bool) or steps < 0:
        raise ValueError(f"steps={steps!r} must be an integer >= 0")
    if tol < 0 or not math.isfinite(tol):
        raise ValueError(f"tol={tol!r} must be finite and >= 0")
    if patience is not None and (not isinstance(patience, (int, np.integer)) or patience < 1):
        raise ValueError(f"patience={patience!r} must be None or an integer >= 1")
    if loss_tol is not None and not math.isfinite(loss_tol):
        raise ValueError(f"loss_tol={loss_tol!r} must be finite or None")


class _Tracker:
    """Host-side bookkeeping for n starts (n = 1 for a plain fit)."""

    def __init__(self, n, names, tol, patience, loss_tol):
        self.n, self.names = n, names
        self.tol, self.patience, self.loss_tol = tol, patience, loss_tol
        self.loss: list[np.ndarray] = []
        self.params: list[dict] = []
        self.grad_norm: list[dict] = []
        self.wall: list[float] = []
        self.active = np.ones(n, bool)
        self.status = ["max_steps"] * n
        self.message = [""] * n
        self.stop_step = np.full(n, -1)  # number of history entries of each start
        self.best_loss = np.full(n, np.inf)
        self.best_step = np.full(n, -1)
        self.ref_loss = np.full(n, np.inf)  # best loss at the last significant improvement
        self.stall = np.zeros(n, int)
        self.updates = np.zeros(n, int)
        self.best_raw: list[dict | None] = [None] * n
        self.last_finite_raw: list[dict | None] = [None] * n
        self.last_finite_phys: list[dict | None] = [None] * n

    def record(self, k, loss, phys, gnorm, finite, raw, wall, recording):
        self.loss.append(np.where(recording, loss, np.nan))
        self.params.append(phys)
        self.grad_norm.append(gnorm)
        self.wall.append(wall)
        for i in np.flatnonzero(recording & finite):
            if loss[i] < self.best_loss[i]:
                self.best_loss[i] = loss[i]
                self.best_step[i] = k
                self.best_raw[i] = {n: raw[n][i] for n in self.names}
            self.last_finite_raw[i] = {n: raw[n][i] for n in self.names}
            self.last_finite_phys[i] = {n: phys[n][i] for n in self.names}

    _FIELDS = ("active", "stop_step", "best_loss", "best_step", "ref_loss", "stall", "updates")

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The whole state as "history/..." and "tracker/..." arrays (see `save_checkpoint`)."""
        out: dict[str, np.ndarray] = {f"tracker/{f}": np.asarray(getattr(self, f)) for f in
                                      self._FIELDS}  # fmt: skip
        out["history/loss"] = np.asarray(self.loss, float).reshape(len(self.loss), self.n)
        out["history/wall"] = np.asarray(self.wall, float)
        for n in self.names:
            if self.params:
                out[f"history/params/{n}"] = np.stack([np.asarray(p[n]) for p in self.params])
                out[f"history/grad_norm/{n}"] = np.stack([np.asarray(g[n]) for g in self.grad_norm])
            for key, rows in (("best_raw", self.best_raw), ("last_raw", self.last_finite_raw),
                              ("last_phys", self.last_finite_phys)):  # fmt: skip
                ref = next((r[n] for r in rows if r is not None), None)
                if ref is None:
                    continue
                out[f"tracker/{key}/{n}"] = np.stack(
                    [np.asarray(r[n]) if r is not None else np.zeros_like(ref) for r in rows]
                )
        for key, rows in (("best_raw", self.best_raw), ("last_raw", self.last_finite_raw)):
            out[f"tracker/has_{key}"] = np.array([r is not None for r in rows])
        return out

    def restore(self, ck: Mapping[str, Any]) -> None:
        """Load the state written by `to_arrays` (a `load_checkpoint` dict)."""
        t, h = ck["tracker"], ck["history"]
        for f in self._FIELDS:
            setattr(self, f, np.array(t[f]))
        meta = ck.get("meta", {})
        self.status = list(meta.get("tracker_status", self.status))
        self.message = list(meta.get("tracker_message", self.message))
        K = int(np.shape(h["loss"])[0])
        self.loss = [np.asarray(h["loss"][k]) for k in range(K)]
        self.wall = [float(w) for w in h["wall"]]
        self.params = [{n: h["params"][n][k] for n in self.names} for k in range(K)]
        self.grad_norm = [{n: h["grad_norm"][n][k] for n in self.names} for k in range(K)]

        def rows(key, has):
            flags = t.get(f"has_{has}", np.zeros(self.n, bool))
            return [
                {n: t[key][n][i] for n in self.names} if flags[i] else None for i in range(self.n)
            ]

        self.best_raw = rows("best_raw", "best_raw")
        self.last_finite_raw = rows("last_raw", "last_raw")
        self.last_finite_phys = rows("last_phys", "last_raw")

    def update_stopping(self, k, loss, finite, grad_finite, path_msg):
        """After evaluation k of the active starts (whose update was applied if finite)."""
        for i in np.flatnonzero(self.active):
            if not finite[i]:
                bad = [n for n in self.names if not grad_finite[n][i]]
                what = f"loss={loss[i]:.4g}" + (f", non-finite gradient of {bad}" if bad else "")
                self.status[i] = "nonfinite"
                self.message[i] = (
                    f"non-finite loss/grad at step {k} ({what}); "
                    f"last finite params saved to {path_msg}"
                )
                self.active[i] = False
                self.stop_step[i] = k + 1
                continue
            self.updates[i] += 1
            if self.loss_tol is not None and loss[i] <= self.loss_tol:
                self.status[i] = "converged"
                self.message[i] = f"loss {loss[i]:.4g} <= loss_tol {self.loss_tol:g} at step {k}"
                self.active[i] = False
                self.stop_step[i] = k + 1
                continue
            ref = self.ref_loss[i]
            if not np.isfinite(ref) or loss[i] < ref - self.tol * abs(ref):
                self.ref_loss[i] = loss[i]
                self.stall[i] = 0
            else:
                self.stall[i] += 1
                if self.patience is not None and self.stall[i] >= self.patience:
                    self.status[i] = "stalled"
                    self.message[i] = (
                        f"no relative improvement > {self.tol:g} for {self.patience} steps "
                        f"(step {k})"
                    )
                    self.active[i] = False
                    self.stop_step[i] = k + 1

    def result(self, i, batched, initial, cons, wall_s, checkpoint_path) -> FitResult:
        m = int(self.stop_step[i]) if self.stop_step[i] >= 0 else len(self.loss)
        sel = (lambda a: np.asarray(a)[i]) if batched else (lambda a: np.asarray(a)[0])
        hist = History(
            loss=np.array([float(sel(l)) for l in self.loss[:m]]),
            params={n: np.stack([sel(p[n]) for p in self.params[:m]]) for n in self.names},
            grad_norm={
                n: np.array([float(sel(g[n])) for g in self.grad_norm[:m]]) for n in self.names
            },
            wall_s=np.asarray(self.wall[:m], float),
        )
        if self.best_raw[i] is None:  # not even the first evaluation was finite
            best_raw = {n: np.asarray(initial[n]) for n in self.names}
            raw_dict = {n: np.asarray(v) for n, v in to_raw(best_raw, cons).items()}
            params = best_raw
            last = best_raw
        else:
            raw_dict = {n: np.asarray(v) for n, v in self.best_raw[i].items()}
            params = {n: np.asarray(v) for n, v in to_physical(raw_dict, cons).items()}
            last = {n: np.asarray(v) for n, v in self.last_finite_phys[i].items()}
        status = self.status[i]
        msg = self.message[i] or {
            "max_steps": f"reached steps={self.updates[i]}",
        }.get(status, status)
        return FitResult(
            params=params,
            raw=raw_dict,
            loss=float(self.best_loss[i]),
            initial={n: np.asarray(initial[n]) for n in self.names},
            history=hist,
            iterations=int(self.updates[i]),
            wall_s=float(wall_s),
            status=status,
            message=msg,
            best_step=int(self.best_step[i]),
            last_finite=last,
            checkpoint_path=checkpoint_path,
        )


def _postfix(bar, tr, phys, batched):
    if batched:
        i = int(np.argmin(np.where(np.isfinite(tr.best_loss), tr.best_loss, np.inf)))
        bar.set_postfix_str(
            f"best loss={tr.best_loss[i]:.4g} active={int(tr.active.sum())}/{tr.n} "
            f"diverged={tr.status.count('nonfinite')}",
            refresh=False,
        )
        return
    loss = tr.loss[-1][0]
    vals = " ".join(f"{n}={_fmt(phys[n][0])}" for n in tr.names[:6])
    bar.set_postfix_str(f"loss={loss:.4g} {vals}", refresh=False)
