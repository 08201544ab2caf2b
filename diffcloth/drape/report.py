"""Predictions of a fabric's drapes and the drape test's outputs.

predict_drapes: the fabric's rest shapes from `seeds` random imperfections (a distribution: node
  counts and DC vary from drape to drape, as on the real tester).
compare: each observation against the predictions: measured and predicted DC and node count,
  and the silhouette IoU after the best rotation (and mirror) of the closest predicted drape.
write_outputs: fabric.toml (a preset simulate / render / view load), fit.json, report.md,
  overlays/*.png (observed outline red, predicted blue, pedestal green), loss and parameter
  plots.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from diffcloth.drape.images import overlay_image
from diffcloth.drape.model import DrapeModel, imperfect_start
from diffcloth.drape.outline import align_rotation, rotate_outline
from diffcloth.physics.mesh import (
    FABRIC_FIELDS,
    bending_length,
    fabric_to_dict,
    make_fabric,
    measure,
)

__all__ = ["compare", "predict_drapes", "write_outputs"]


def predict_drapes(model: DrapeModel, fabric_values: dict, seeds, *, amplitude=2e-3,
                   log=print) -> list[dict]:  # fmt: skip
    """Rest shapes of the fabric from the random imperfections `seeds` (ints): for each, a dict
    with seed, x (n, 3) m, dc, node_count, r_theta (360,) m, converged, iterations."""
    fabric = make_fabric(None, dtype=jnp.float64, **fabric_values)
    out = []
    for s in seeds:
        res = model.solve(fabric, jnp.asarray(imperfect_start(model, int(s), amplitude=amplitude)))
        x = np.asarray(res.x)
        ok = bool(res.converged) and bool(np.all(np.isfinite(x)))
        g = model.geometry
        dc = measure.drape_coefficient(x, model.faces, g.specimen_radius, g.pedestal_radius).value
        r = measure.outline_radius(x, model.faces, 360)
        out.append({"seed": int(s), "x": x, "dc": float(dc), "node_count": measure.node_count(r),
                    "r_theta": r, "converged": ok, "iterations": int(res.iterations)})  # fmt: skip
        log(f"  predicted drape, seed {s}: DC {dc:.4f}, {out[-1]['node_count']} nodes"
            + ("" if ok else "  (NOT converged)"))  # fmt: skip
    return out


def compare(observed, predictions: list[dict]) -> list[dict]:
    """Per accepted observation: file, sample, side, dc, node_count, the predicted DC mean and
    std, the best-rotation IoU with the closest predicted drape (its seed, rotation, mirror).
    Predicted drapes whose solve did not converge are left out (the report counts them)."""
    predictions = [p for p in predictions if p["converged"]] or predictions
    dcs = np.array([p["dc"] for p in predictions])
    rows = []
    for m in observed.accepted:
        r_obs = m.features["r_theta"]
        best = max(((align_rotation(r_obs, p["r_theta"]), p) for p in predictions),
                   key=lambda t: t[0][2])  # fmt: skip
        (angle, mirrored, iou), p = best
        chamfer = None
        if m.points is not None:  # a 3D scan: the surface distance after the best turn
            from diffcloth.drape.scan import align_scan_rotation

            chamfer = float(align_scan_rotation(m.points, p["x"])[1])
        rows.append({
            "file": m.obs.path.name, "sample": m.obs.sample, "side": m.obs.side,
            "dc": float(m.features["dc"]), "node_count": int(m.features["node_count"]),
            "dc_predicted": float(dcs.mean()), "dc_predicted_std": float(dcs.std()),
            "iou": float(iou), "iou_seed": p["seed"], "rotation_deg": math.degrees(angle),
            "mirrored": bool(mirrored), "chamfer_m": chamfer,
            "_overlay": rotate_outline(p["r_theta"], angle, mirrored), "_sil": m.sil,
        })  # fmt: skip
    return rows


def _fabric_toml(name: str, values: dict, fitted: dict, std: dict) -> str:
    lines = [f"# fabric {name!r} fitted by `diffcloth drape fit` (diffcloth.drape)",
             "# load it with [fabric] preset = \"<this file>\" in a scene config", "[fabric]"]  # fmt: skip
    for k in FABRIC_FIELDS:
        if k not in values:
            continue
        note = ""
        if k.startswith("bend_"):
            c_mm = 1e3 * float(bending_length(values[k], values["density"]))
            note = f"   # {values[k] * 1e6:.4g} uN m, bending length {c_mm:.1f} mm"
        if k in fitted or (k.startswith("bend_") and "bend" in fitted):
            src = k if k in fitted else "bend"
            note += f" (fitted, GN std {std[src] * (1e6 if 'bend' in src else 1):.3g}"
            note += " uN m)" if "bend" in src else ")"
        lines.append(f"{k} = {values[k]:.6g}{note}")
    return "\n".join(lines) + "\n"


def _bend_rows(fit, density) -> list[str]:
    rows = ["| parameter | fitted | GN std | bending length | per observation (mean +- std, "
            "min..max) |", "|---|---|---|---|---|"]  # fmt: skip
    for p, v in fit.values.items():
        pop = fit.population[p]
        if "bend" in p:
            unit, scale = "uN m", 1e6
            c = f"{1e3 * float(bending_length(v, density)):.1f} mm"
        else:
            unit, scale, c = "N/m", 1.0, "-"
        rows.append(f"| {p} | {v * scale:.4g} {unit} | {fit.std[p] * scale:.2g} {unit} | {c} | "
                    f"{pop.mean() * scale:.4g} +- {pop.std() * scale:.2g} "
                    f"({pop.min() * scale:.4g}..{pop.max() * scale:.4g}) |")  # fmt: skip
    return rows


def write_outputs(folder, cfg, observed, predictions, rows, *, fabric_values, fit=None,
                  truth=None) -> Path:  # fmt: skip
    """Write the drape test's outputs into `folder` (see the module docstring); returns
    report.md's path. truth: optional {"fabric": {...}, "seeds": [{seed, dc, node_count}]} of a
    synthetic drape (the suite's truth.json), shown beside the prediction."""
    folder = Path(folder)
    (folder / "overlays").mkdir(parents=True, exist_ok=True)
    # every Fabric field: the given values over the defaults
    fabric_values = {k: float(v) for k, v in fabric_to_dict(make_fabric(
        None, dtype=jnp.float64, validate=False, **fabric_values)).items()}  # fmt: skip
    import imageio.v3 as iio

    for row in rows:
        sil, r_pred = row.pop("_sil"), row.pop("_overlay")
        row["overlay"] = None
        if sil is not None:
            row["overlay"] = f"overlays/{Path(row['file']).stem}.png"
            iio.imwrite(folder / row["overlay"],
                        overlay_image(sil, predicted_r_theta=r_pred, geometry=cfg.geometry))  # fmt: skip
    fitted = fit.values if fit else {}
    (folder / "fabric.toml").write_text(
        _fabric_toml(cfg.name, fabric_values, fitted, fit.std if fit else {})
    )
    pred_nodes = Counter(p["node_count"] for p in predictions if p["converged"])
    obs_nodes = Counter(int(v) for v in observed.nodes)
    summary = {
        "name": cfg.name, "config": str(cfg.source), "fabric": fabric_values,
        "observations": rows,
        "rejected": [{"file": o.path.name, "reasons": list(r)} for o, r in observed.rejected],
        "predictions": [{k: v for k, v in p.items() if k not in ("x", "r_theta")}
                        for p in predictions],
        "node_counts": {"observed": dict(sorted(obs_nodes.items())),
                        "predicted": dict(sorted(pred_nodes.items()))},
    }  # fmt: skip
    if fit is not None:
        summary["fit"] = {
            "params": list(fitted), "values": fit.values, "std": fit.std,
            "population": {k: v.tolist() for k, v in fit.population.items()},
            "features": list(fit.names), "jacobian": fit.jacobian.tolist(),
            "correlation": fit.correlation.tolist(), "converged": fit.converged,
            "identifiable": fit.identifiable, "note": fit.note, "seconds": fit.seconds,
            "evaluations": fit.evaluations, "history": fit.history,
        }  # fmt: skip
        from diffcloth.plots import plot_loss, plot_params

        plot_loss(fit.history, folder / "loss.png", title=f"drape fit {cfg.name}: loss")
        t = {k: v for k, v in (truth or {}).get("fabric", {}).items() if k in fitted}
        if "bend" in fitted and truth and "bend" in truth.get("fabric", {}):
            t["bend"] = truth["fabric"]["bend"]
        plot_params(fit.history, folder / "params.png", truth=t or None)
    if truth is not None:
        summary["truth"] = truth
    (folder / "fit.json").write_text(json.dumps(summary, indent=1, default=float) + "\n")
    report = folder / "report.md"
    report.write_text(_markdown(cfg, observed, predictions, rows, fit, truth, obs_nodes,
                                pred_nodes, fabric_values))  # fmt: skip
    return report


def _markdown(cfg, observed, predictions, rows, fit, truth, obs_nodes, pred_nodes, values):
    failed = [p["seed"] for p in predictions if not p["converged"]]
    predictions = [p for p in predictions if p["converged"]] or predictions
    dcs = np.array([p["dc"] for p in predictions])
    md = [f"# Drape test: {cfg.name}", "",
          f"Config `{cfg.source.name}`; specimen radius {cfg.geometry.specimen_radius} m, pedestal "
          f"{cfg.geometry.pedestal_radius} m; density {cfg.density} kg/m^2 (weighed); "
          f"{len(observed.accepted)} image(s) used, {len(observed.rejected)} set aside.", ""]  # fmt: skip
    if fit is not None:
        md += ["## Fitted fabric", "", *_bend_rows(fit, cfg.density), "",
               f"{'Converged' if fit.converged else 'NOT converged'} in "
               f"{len(fit.history['loss']) - 1} accepted steps, {fit.evaluations} simulated "
               f"drapes, {fit.seconds:.0f} s. GN std: Gauss-Newton, residuals over the tester's "
               "error (DC 0.01) scaled by the observations' own scatter. Per observation: each "
               "image's own linearised fit (the spread of the fabric over samples and drapes).",
               "", "![loss](loss.png) ![parameters](params.png)", "",
               "Jacobian: each feature's change per unit change of log(parameter) (a column of "
               "zeros, or two proportional columns, is a parameter the drapes cannot tell):", "",
               "| feature | " + " | ".join(fit.values) + " |",
               "|---|" + "---|" * len(fit.values)]  # fmt: skip
        for name, jrow in zip(fit.names, fit.jacobian, strict=True):
            md.append(f"| {name} | " + " | ".join(f"{v:+.4f}" for v in jrow) + " |")
        if fit.note:
            md += ["", f"**Note:** {fit.note}"]
        md.append("")
    if truth is not None and fit is not None:
        md += ["| parameter | fitted | true | error |", "|---|---|---|---|"]
        tf = truth.get("fabric", {})
        for p, v in fit.values.items():
            tv = tf.get(p, tf.get("bend") if p.startswith("bend") else None)
            if tv:
                md.append(f"| {p} | {v:.4g} | {tv:.4g} | {100 * (v / tv - 1):+.2f} % |")
        md.append("")
    md += ["## Observations", "",
           "| image | sample | side | DC measured | DC predicted | nodes measured | IoU (best "
           "rotation) | overlay |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in rows:
        md.append(f"| {r['file']} | {r['sample']} | {r['side']} | {r['dc']:.4f} | "
                  f"{r['dc_predicted']:.4f} +- {r['dc_predicted_std']:.4f} | {r['node_count']} | "
                  f"{r['iou']:.3f} (seed {r['iou_seed']}, {r['rotation_deg']:.0f} deg"
                  f"{', mirrored' if r['mirrored'] else ''}) | "
                  + (f"![]({r['overlay']}) |" if r["overlay"] else
                     f"3D scan: chamfer {1e3 * r['chamfer_m']:.1f} mm |"))  # fmt: skip
    for o, reasons in observed.rejected:
        md.append(f"| {o.path.name} | {o.sample} | {o.side} | set aside: {'; '.join(reasons)} "
                  "| | | | |")  # fmt: skip
    md += ["", "## Prediction", "",
           f"{len(predictions)} drapes from random imperfections: DC {dcs.mean():.4f} +- "
           f"{dcs.std():.4f} ({dcs.min():.4f}..{dcs.max():.4f})."
           + (f" Left out, their solves not converged: seeds {failed}." if failed else ""), "",
           "| node count | observed | predicted |" + (" truth |" if truth else ""),
           "|---|---|---|" + ("---|" if truth else "")]  # fmt: skip
    t_nodes = Counter(s["node_count"] for s in (truth or {}).get("seeds", []))
    for k in sorted(set(obs_nodes) | set(pred_nodes) | set(t_nodes)):
        md.append(f"| {k} | {obs_nodes.get(k, 0)} | {pred_nodes.get(k, 0)} |"
                  + (f" {t_nodes.get(k, 0)} |" if truth else ""))  # fmt: skip
    if truth:
        md += ["", "| seed | DC predicted | DC truth | difference | nodes predicted | nodes truth |",
               "|---|---|---|---|---|---|"]  # fmt: skip
        by_seed = {s["seed"]: s for s in truth.get("seeds", [])}
        for p in predictions:
            t = by_seed.get(p["seed"])
            if t:
                md.append(f"| {p['seed']} | {p['dc']:.4f} | {t['dc']:.4f} | "
                          f"{p['dc'] - t['dc']:+.4f} | {p['node_count']} | {t['node_count']} |")  # fmt: skip
    md += ["", "Fabric written to `fabric.toml` (every field; bending also in uN m and as the "
           "cantilever bending length)."]  # fmt: skip
    return "\n".join(md) + "\n"
