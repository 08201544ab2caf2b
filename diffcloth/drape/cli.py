"""`diffcloth drape fit | predict | suite`: the drape test from the command line.

    diffcloth drape suite --out drape_suite                  # the synthetic suite (JPEGs + configs)
    diffcloth drape fit drape_suite/medium/drape.toml --out out/medium
    diffcloth drape predict drape_suite/medium/drape.toml --fabric out/medium/fabric.toml \
        --out out/medium_predict --seeds 12
"""

from __future__ import annotations

import json
import time
from pathlib import Path

__all__ = ["add_drape_parser"]


def add_drape_parser(sub, parents) -> None:
    """Add the `drape` command (with fit / predict / suite) to an argparse subparsers object."""
    d = sub.add_parser("drape", help="the Cusick drape test: fit a fabric to drape silhouettes, "
                       "predict its drapes, make the synthetic suite")  # fmt: skip
    dsub = d.add_subparsers(dest="drape_command", required=True)
    f = dsub.add_parser("fit", parents=parents, help="fit a fabric to a drape config's images")
    f.add_argument("config", help="drape TOML (docs/drape.md)")
    f.add_argument("--out", required=True, help="output folder")
    f.add_argument("--steps", type=int, default=None, help="override [fit] steps")
    f.add_argument("--seeds", type=int, default=None, help="override [predict] seeds")
    f.set_defaults(func=_fit)
    p = dsub.add_parser("predict", parents=parents, help="predict a fabric's drapes and compare "
                        "them with a drape config's images")  # fmt: skip
    p.add_argument("config", help="drape TOML (its images and geometry)")
    p.add_argument("--fabric", default=None, help="fabric TOML (e.g. a fit's fabric.toml) or "
                   "preset name; default: the config's [fabric]")  # fmt: skip
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seeds", type=int, default=None, help="override [predict] seeds")
    p.set_defaults(func=_predict)
    s = dsub.add_parser("suite", parents=parents, help="write the synthetic drape-test suite")
    s.add_argument("--out", required=True, help="output folder")
    s.add_argument("--fabrics", default=None, help="comma-separated subset of the suite's "
                   "fabrics (limp, medium, stiff, aniso)")  # fmt: skip
    s.add_argument("--seeds", type=int, default=6, help="drapes per fabric (default 6)")
    s.set_defaults(func=_suite)


def _start(args):
    import jax

    jax.config.update("jax_enable_x64", True)  # the drape solves and their tangents: float64
    from diffcloth.outdir import OutputDir, UsageError, config_inputs

    for name in ("steps", "seeds"):
        v = getattr(args, name, None)
        if v is not None and v < 1:
            raise UsageError(f"--{name} must be >= 1, got {v}")
    inputs = config_inputs(args.config) if getattr(args, "config", None) else []
    if getattr(args, "fabric", None) and Path(args.fabric).is_file():
        inputs.append(("--fabric", Path(args.fabric)))
    return OutputDir(args.out, overwrite=args.overwrite, inputs=inputs)


def _truth_beside(cfg):
    """A synthetic suite's truth.json beside the config, if any."""
    p = cfg.source.parent / "truth.json"
    return json.loads(p.read_text()) if p.is_file() else None


def _load(args):
    from diffcloth.drape.config import load_drape_config
    from diffcloth.drape.observe import measure_observations

    cfg = load_drape_config(args.config)
    print(f"diffcloth drape {args.drape_command} {args.config}: {len(cfg.observations)} image(s)",
          flush=True)  # fmt: skip
    observed = measure_observations(cfg)
    for m in observed.accepted:
        f = m.features
        print(f"  {m.obs.path.name}: DC {f['dc']:.4f}, {f['node_count']} nodes", flush=True)
    return cfg, observed


def _fit(args) -> int:
    out = _start(args)
    t0 = time.perf_counter()
    from diffcloth.drape.fit import fabric_values, fit_drape
    from diffcloth.drape.model import make_drape_model
    from diffcloth.drape.report import compare, predict_drapes, write_outputs

    cfg, observed = _load(args)
    model = make_drape_model(cfg.geometry, edge=cfg.edge)
    print(f"fitting {', '.join(cfg.params)} on a {model.num_vertices}-vertex specimen", flush=True)
    fit = fit_drape(cfg, observed, model, steps=args.steps)
    values = fabric_values(cfg, fit.values)
    print("fitted: " + ", ".join(f"{k} {v:.4g} +- {fit.std[k]:.2g}" for k, v in fit.values.items())
          + f" ({fit.seconds:.0f} s)", flush=True)  # fmt: skip
    if fit.note:
        print(f"note: {fit.note}", flush=True)
    seeds = range(args.seeds or cfg.predict_seeds)
    preds = predict_drapes(model, values, seeds)
    rows = compare(observed, preds)
    write_outputs(out.tmp, cfg, observed, preds, rows, fabric_values=values, fit=fit,
                  truth=_truth_beside(cfg))  # fmt: skip
    out.commit()
    print(f"wrote {args.out}/report.md, fabric.toml ({time.perf_counter() - t0:.0f} s)")
    return 0


def _predict(args) -> int:
    out = _start(args)
    from diffcloth.drape.model import make_drape_model
    from diffcloth.drape.report import compare, predict_drapes, write_outputs
    from diffcloth.physics.mesh import fabric_preset

    cfg, observed = _load(args)
    values = dict(cfg.fabric)
    if args.fabric:
        values.update(fabric_preset(args.fabric))
    values["density"] = cfg.density if "density" not in values else values["density"]
    model = make_drape_model(cfg.geometry, edge=cfg.edge)
    preds = predict_drapes(model, values, range(args.seeds or cfg.predict_seeds))
    rows = compare(observed, preds)
    write_outputs(out.tmp, cfg, observed, preds, rows, fabric_values=values,
                  truth=_truth_beside(cfg))  # fmt: skip
    out.commit()
    print(f"wrote {args.out}/report.md")
    return 0


def _suite(args) -> int:
    out = _start(args)
    from diffcloth.drape.suite import SUITE_FABRICS, make_suite
    from diffcloth.outdir import UsageError

    names = list(SUITE_FABRICS) if not args.fabrics else args.fabrics.split(",")
    bad = [n for n in names if n not in SUITE_FABRICS]
    if bad:
        raise UsageError(f"--fabrics: unknown {', '.join(bad)}; known: {', '.join(SUITE_FABRICS)}")
    make_suite(out.tmp, fabrics={n: SUITE_FABRICS[n] for n in names}, seeds=args.seeds)
    out.commit()
    print(f"wrote {args.out}/<fabric>/drape.toml, seed*.jpg, truth.json")
    return 0
