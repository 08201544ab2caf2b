"""Fit a fabric to drape-test observations: Levenberg-Marquardt on rotation-invariant features.

The folds of a drape point anywhere and their number changes from drape to drape, so no image is
compared pixel by pixel with a drape of other folds. Each observation gets its own simulated
drape(s), started from an imperfection shaped like its own outline (`outline_start`: the folds
form where the observed ones are), and the fit matches their features:
- dc: the drape coefficient (always);
- c2x, c2y: the outline's second harmonic in the warp frame (warp / weft bending, when the warp
  direction of every image is known), or a2, its amplitude alone (when it is not: then warp and
  weft can only be told apart up to which of them is stiffer);
- fold: the RMS of harmonics 3-12 of r(theta) over the mean radius (with stretch or shear).
Residuals are divided by the tester's error of each feature (DC 0.01). Parameters are fitted as
logarithms; the Jacobian comes from forward-mode differentiation through the equilibrium
(implicit function theorem). Between Levenberg-Marquardt steps each drape is warm-started (it
follows its branch of equilibria, a smooth objective); a new round re-solves from the observed
folds at the current values, until the values move by less than 1 %.

One drape is one sample of a distribution: at a fixed fabric, the DC of repeat drapes spreads by
0.01-0.05 with the fold pattern. So one image fixes the bending to about 5-10 %; the GN std
says so (it scales the tester's error by the residuals' own scatter), and several images
average it down.
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.drape.config import FIT_PARAMS, DrapeConfig
from diffcloth.drape.model import DrapeModel, imperfect_start, rim_dc, rim_harmonics
from diffcloth.drape.observe import ObservedSet
from diffcloth.physics.mesh import make_fabric

__all__ = ["DrapeFit", "DEFAULT_START", "fabric_values", "feature_names", "fit_drape"]

#: generic start values (SI): a mid-weight woven fabric
DEFAULT_START = {"bend": 2e-5, "bend_warp": 2e-5, "bend_weft": 2e-5, "stretch": 500.0,
                 "shear": 20.0}  # fmt: skip
#: floors of the per-observation spread of each feature (the drape tester's own error)
# (the second harmonic moves by about 0.01 with the arrangement of the folds alone)
SPREAD_FLOOR = {"dc": 0.01, "c2x": 0.01, "c2y": 0.01, "a2": 0.01, "fold": 0.01}


def feature_names(params, warp_known: bool) -> tuple[str, ...]:
    """The features a fit of `params` matches (see the module docstring)."""
    names = ["dc"]
    if {"bend_warp", "bend_weft"} & set(params):
        names += ["c2x", "c2y"] if warp_known else ["a2"]
    if {"stretch", "shear"} & set(params):
        names.append("fold")
    return tuple(names)


def fabric_values(cfg: DrapeConfig, values: dict) -> dict:
    """The full Fabric field dict: the config's fabric with the fitted `values` ("bend" sets
    warp, weft and bias; "stretch" both directions; with warp and weft fitted and no bias given,
    bias = sqrt(warp weft))."""
    out = dict(cfg.fabric)
    for name, v in values.items():
        if name == "bend":
            out.update(bend_warp=v, bend_weft=v, bend_bias=v)
        elif name == "stretch":
            out.update(stretch_warp=v, stretch_weft=v)
        else:
            out[name] = v
    if {"bend_warp", "bend_weft"} & set(values) and "bend_bias" not in cfg.fabric:
        warp = out.get("bend_warp", DEFAULT_START["bend_warp"])
        weft = out.get("bend_weft", DEFAULT_START["bend_weft"])
        out["bend_bias"] = (warp * weft) ** 0.5
    return out


def _sim_features(model: DrapeModel, x, names):
    c = rim_harmonics(model, x, 12)
    a = 2 * c / c[0].real
    table = {
        "dc": lambda: rim_dc(model, x),
        "c2x": lambda: a[2].real,
        "c2y": lambda: a[2].imag,
        "a2": lambda: jnp.abs(a[2]),
        "fold": lambda: jnp.sqrt(jnp.sum(jnp.abs(a[3:]) ** 2)),
    }
    return jnp.stack([table[n]() for n in names])


def observed_features(observed: ObservedSet, names) -> np.ndarray:
    """(N, F) the features of every accepted observation."""
    cols = []
    for n in names:
        if n == "dc":
            cols.append(observed.dc)
        elif n in ("c2x", "c2y"):
            c2 = observed.c2
            cols.append(c2.real if n == "c2x" else c2.imag)
        elif n == "a2":
            cols.append(observed.a2)
        else:
            spec = np.array([m.features["spectrum"] for m in observed.accepted])
            cols.append(np.sqrt(np.sum(spec[:, 2:12] ** 2, axis=1)))
    return np.stack(cols, axis=1)


@dataclasses.dataclass
class DrapeFit:
    """A fitted fabric. values: {param: value (SI)}; std: Gauss-Newton standard deviations (SI);
    population: {param: (N,) per-observation values} (each observation's own linearised fit: the
    spread of the fabric over its samples and drapes); correlation: (P, P); jacobian: (F, P)
    d(feature)/d(log param), averaged over the observations; names: the F features; features /
    sim_features: (N, F) each observation's and its simulated drapes' (the mean over the seeds
    of its node count); sigma: (F,) the residual scales; sim_spread: (N, F) the seeds' spread;
    history: per accepted step {loss, params}; states: the last simulated drapes (n, 3)."""

    values: dict
    std: dict
    population: dict
    correlation: np.ndarray
    jacobian: np.ndarray
    names: tuple
    features: np.ndarray
    sigma: np.ndarray
    sim_features: np.ndarray
    sim_spread: np.ndarray
    history: dict
    states: list
    seconds: float
    evaluations: int
    converged: bool
    identifiable: bool
    note: str


def _evaluator(model: DrapeModel, cfg: DrapeConfig, names):
    params = cfg.params

    def features(q, x0):
        vals = fabric_values(cfg, dict(zip(params, jnp.exp(q), strict=True)))
        fabric = make_fabric(None, dtype=q.dtype, validate=False, **vals)
        res = model.solve(fabric, x0)
        return _sim_features(model, res.x, names), (res.x, res.converged, res.iterations)

    @jax.jit
    def evaluate(q, x0):
        def with_aux(q):
            f, aux = features(q, x0)
            return f, (f, aux)

        jac, (f, aux) = jax.jacfwd(with_aux, has_aux=True)(q)
        return f, jac, aux

    return evaluate


def outline_start(model: DrapeModel, r_theta, amplitude: float, seed: int | None = None):
    """The flat specimen with an imperfection shaped like an observed outline: the hanging part
    lifted by amplitude s^2 w(phi), w = (r(phi) - mean r) / max |r - mean r| (a fold's crest
    reaches out and up), so that the simulated drape forms the observed folds where they are
    (their number and places are set by the imperfections of the real specimen, not by the
    fabric). A seed adds a random imperfection of a fifth of the amplitude (`imperfect_start`).
    Shapes: r_theta (k,) m at theta_j = 2 pi j / k (counter-clockwise from +x seen from above)
    -> (n, 3) m."""
    r = np.asarray(r_theta, np.float64)
    dev = r - r.mean()
    w_theta = dev / max(float(np.max(np.abs(dev))), 1e-12)
    x = (np.asarray(model.cloth.rest, np.float64) if seed is None
         else imperfect_start(model, seed, amplitude=0.2 * amplitude))  # fmt: skip
    rest = np.asarray(model.cloth.rest, np.float64)
    rad = np.hypot(rest[:, 0], rest[:, 2])
    phi = np.mod(np.arctan2(-rest[:, 2], rest[:, 0]), 2 * np.pi)
    k = r.size
    w = np.interp(phi / (2 * np.pi) * k, np.arange(k), w_theta, period=k)
    g = model.geometry
    s = np.clip((rad - g.pedestal_radius) / (g.specimen_radius - g.pedestal_radius), 0.0, None)
    x = x.copy()
    x[:, 1] += amplitude * s**2 * w
    return x


def _starts(model: DrapeModel, cfg: DrapeConfig, observed: ObservedSet) -> dict:
    """{observation index: [start (n, 3)] * cfg.seeds}, each shaped by that observation's
    outline (`outline_start`; seeds beyond the first add a small random imperfection)."""
    return {
        i: [jnp.asarray(outline_start(model, m.features["r_theta"], cfg.amplitude,
                                      None if s == 0 else s)) for s in range(cfg.seeds)]
        for i, m in enumerate(observed.accepted)
    }  # fmt: skip


def fit_drape(cfg: DrapeConfig, observed: ObservedSet, model: DrapeModel, *, log=print,
              steps: int | None = None) -> DrapeFit:  # fmt: skip
    """Fit cfg.params to the observations (see the module docstring). Raises ValueError when a
    simulated drape does not converge at the start."""
    t0 = time.perf_counter()
    names = feature_names(cfg.params, observed.warp_known)
    obs = observed_features(observed, names)  # (N, F)
    nodes = list(range(obs.shape[0]))  # each observation: its own simulated drape(s)
    sigma = np.array([SPREAD_FLOOR[n] for n in names])
    lo = np.log([FIT_PARAMS[p][0] for p in cfg.params])
    hi = np.log([FIT_PARAMS[p][1] for p in cfg.params])
    q = np.log([cfg.start.get(p, cfg.fabric.get(p, DEFAULT_START[p])) for p in cfg.params])
    evaluate = _evaluator(model, cfg, names)
    count = [0]

    def run(q, starts):
        """Simulate every start; residuals (N F,) of each observation against the simulated
        mean of its node count, their Jacobian (N F, P), the features and solutions per count."""
        sims, xs, ok = {}, {}, True
        for k, group in starts.items():
            fs, js, xk = [], [], []
            for x0 in group:
                f, j, (x, conv, its) = evaluate(jnp.asarray(q), x0)
                count[0] += 1
                ok = ok and bool(conv) and bool(np.all(np.isfinite(np.asarray(j))))
                fs.append(np.asarray(f))
                js.append(np.asarray(j))
                xk.append(x)
            sims[k] = (np.mean(fs, axis=0), np.mean(js, axis=0), np.array(fs))
            xs[k] = xk
        # a feature an observation lacks (NaN: a scan's c2) adds nothing
        r = np.concatenate([np.where(np.isnan(o), 0.0, (sims[k][0] - o) / sigma)
                            for k, o in zip(nodes, obs, strict=True)])  # fmt: skip
        jac = np.concatenate([np.where(np.isnan(o)[:, None], 0.0, sims[k][1] / sigma[:, None])
                              for k, o in zip(nodes, obs, strict=True)])  # fmt: skip
        return ok, 0.5 * float(r @ r), r, jac, sims, xs

    starts = _starts(model, cfg, observed)
    history = {"loss": [], "params": {p: [] for p in cfg.params}}
    converged, budget = False, steps or cfg.steps
    # rounds: solve afresh from the observed fold pattern at the current values (which picks
    # the branch of equilibria nearest the observation), then Levenberg-Marquardt with warm
    # starts (each drape followed continuously along its branch: a smooth objective); a new
    # round while the values still move by more than 1 %
    for round_ in range(3):
        ok, cost, r, jac, sims, xs = run(q, starts)
        if not ok:
            raise ValueError(
                f"{cfg.source}: the simulated drape at "
                f"{dict(zip(cfg.params, np.exp(q).round(8).tolist(), strict=True))} did not "
                "converge; give [fit] start values nearer the fabric, or a finer [fit] edge"
            )
        log(f"  round {round_ + 1}: fresh drapes from the observed folds, loss {cost:.4g}")
        q_round = q.copy()
        history["loss"].append(cost)
        for p, v in zip(cfg.params, q, strict=True):
            history["params"][p].append(float(np.exp(v)))
        lam = 1e-2
        while budget > 0:
            jtj = jac.T @ jac
            g = jac.T @ r
            if cost < 1e-4:  # every residual within about 1 % of the tester's error
                converged = True
                break
            budget -= 1
            delta = np.linalg.solve(jtj + lam * np.diag(np.diag(jtj) + 1e-12), -g)
            delta = np.clip(delta, -1.5, 1.5)  # at most a factor e^1.5 per step
            q_try = np.clip(q + delta, lo, hi)
            ok_t, cost_t, r_t, jac_t, sims_t, xs_t = run(q_try, xs)
            accepted = ok_t and cost_t < cost
            log("    " + ", ".join(f"{p} {np.exp(v):.4g}" for p, v in
                zip(cfg.params, q_try, strict=True)) + f"  loss {cost_t:.4g}"
                + ("" if accepted else "  (rejected)"))  # fmt: skip
            if accepted:
                stalled = cost - cost_t < 1e-3 * cost
                q, cost, r, jac, sims, xs = q_try, cost_t, r_t, jac_t, sims_t, xs_t
                lam = max(lam / 3, 1e-6)
                history["loss"].append(cost)
                for p, v in zip(cfg.params, q, strict=True):
                    history["params"][p].append(float(np.exp(v)))
                if np.max(np.abs(delta)) < 2e-3 or stalled:  # a 0.2 % step, or no progress
                    converged = True
                    break
            else:
                lam *= 8
                if lam > 1e6:  # no step lowers the loss: converged if Gauss-Newton's own step
                    # is below 0.2 % (the rest is the solver's tolerance)
                    gn = np.linalg.lstsq(jtj, -g, rcond=None)[0]
                    converged = bool(np.max(np.abs(gn)) < 2e-3)
                    break
        if np.max(np.abs(q - q_round)) < 0.01 or budget <= 0:
            break
    return _summarise(cfg, names, q, jac, r, sims, xs, obs, nodes, sigma, history,
                      time.perf_counter() - t0, count[0], converged)  # fmt: skip


def _summarise(cfg, names, q, jac, r, sims, xs, obs, nodes, sigma, history, secs, evals,
               converged) -> DrapeFit:  # fmt: skip
    jtj = jac.T @ jac
    cov = np.linalg.pinv(jtj)
    # the residuals' own scale when there are more residuals than parameters (the observations'
    # scatter beyond the floors), never below the floors
    dof = r.size - len(q)
    scale = max(2 * 0.5 * float(r @ r) / dof, 1.0) if dof > 0 else 1.0
    cov = cov * scale
    sd_q = np.sqrt(np.clip(np.diag(cov), 0, None))
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / np.outer(d, d)
    cond = np.linalg.cond(jtj) if jtj.size else 1.0
    worst = np.max(np.abs(corr - np.eye(len(q)))) if len(q) > 1 else 0.0
    identifiable = bool(np.isfinite(cond) and cond < 1e6 and worst < 0.98
                        and len(names) >= len(q))  # fmt: skip
    note = (
        ""
        if identifiable
        else (
            f"the features ({', '.join(names)}) do not determine {', '.join(cfg.params)} apart "
            f"(condition number {cond:.3g}, largest correlation {worst:.3f}): see the Jacobian table"
        )
    )
    values = {p: float(np.exp(v)) for p, v in zip(cfg.params, q, strict=True)}
    std = {p: float(np.exp(v) * s) for p, v, s in zip(cfg.params, q, sd_q, strict=True)}
    # a parameter at the end of its range with the residuals still large: the model cannot
    # reproduce the drapes with the parameters fitted
    sim_feats = np.array([sims[k][0] for k in nodes])
    misfit = np.nanmax(np.abs(sim_feats - obs) / sigma) if obs.size else 0.0
    for p, v in zip(cfg.params, q, strict=True):
        lo, hi = (math.log(b) for b in FIT_PARAMS[p])
        if misfit > 1.0 and min(v - lo, hi - v) < 1e-3:
            end = "lower" if v - lo < hi - v else "upper"
            dc_obs, dc_sim = float(np.mean(obs[:, 0])), float(np.mean(sim_feats[:, 0]))
            advice = (" For limp fabrics the drape is set by the membrane too: add 'shear' (and "
                      "'stretch') to [fit] params." if end == "lower" else "")  # fmt: skip
            note = (note + " " if note else "") + (
                f"{p} stopped at the {end} end of its range ({FIT_PARAMS[p][0 if end == 'lower' else 1]:g}"
                f") with the simulated drapes still {misfit:.1f} tester errors away (DC measured "
                f"{dc_obs:.3f}, simulated {dc_sim:.3f}): the fitted values are not a fabric that "
                f"reproduces the images.{advice}"
            )  # fmt: skip
            converged = False
    # each observation's own linearised fit: q_i = q - J_i^+ (F_sim - F_i) / sigma
    q_i = []
    for k, o in zip(nodes, obs, strict=True):
        f_sim, j_sim, _ = sims[k]
        use = ~np.isnan(o)
        q_i.append(q - np.linalg.pinv(j_sim[use] / sigma[use, None]) @ ((f_sim - o)[use]
                                                                        / sigma[use]))  # fmt: skip
    q_i = np.array(q_i)
    population = {p: np.exp(q_i[:, k]) for k, p in enumerate(cfg.params)}
    spread = np.array([sims[k][2].std(axis=0) for k in nodes])
    n_obs, n_f = obs.shape
    return DrapeFit(values=values, std=std, population=population, correlation=corr,
                    jacobian=jac.reshape(n_obs, n_f, -1).mean(axis=0) * sigma[:, None],
                    names=names, features=obs, sigma=sigma, sim_features=sim_feats,
                    sim_spread=spread, history=history,
                    states=[np.asarray(x) for k in sorted(xs) for x in xs[k]], seconds=secs,
                    evaluations=evals, converged=bool(converged), identifiable=identifiable,
                    note=note)  # fmt: skip
