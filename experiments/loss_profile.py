"""Loss profile of a fit config over one parameter, the others at their true values.

    python experiments/loss_profile.py CONFIG PARAM LO HI [--points N] [--out DIR]

Renders the config's synthetic target ([truth]), then the fit's own loss ([fit] loss, all frames)
at N log-spaced values of PARAM in [LO, HI]. Prints a markdown table and writes DIR/profile_PARAM.png
and .json (DIR default: results/<config name>/). Shows whether a start lies in the truth's basin.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def profile(config_path, param: str, lo: float, hi: float, points: int = 25) -> dict:
    """{"values": (N,), "loss": (N,)} of the final-stage loss over `param`."""
    import jax
    import jax.numpy as jnp

    from diffcloth import config as cfg
    from diffcloth import pipeline, scene
    from diffcloth.fit.scene_fit import video_loss

    config = cfg.load_config(config_path)
    sc = scene.build_scene(config)
    render = jax.jit(lambda p: pipeline.simulate_and_render(sc, p))
    truth = {k: jnp.asarray(v, jnp.float32) for k, v in config.fit.truth.items()}
    target = render(truth)
    loss = jax.jit(lambda p: video_loss(render(p), target, config.fit.loss))
    values = np.geomspace(lo, hi, points)
    losses = [float(loss(dict(truth, **{param: jnp.float32(v)}))) for v in values]
    return {"param": param, "truth": float(truth[param]), "values": values.tolist(), "loss": losses}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config")
    ap.add_argument("param")
    ap.add_argument("lo", type=float)
    ap.add_argument("hi", type=float)
    ap.add_argument("--points", type=int, default=25)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    out = Path(a.out) if a.out else ROOT / "results" / Path(a.config).stem
    out.mkdir(parents=True, exist_ok=True)
    res = profile(a.config, a.param, a.lo, a.hi, a.points)
    (out / f"profile_{a.param}.json").write_text(json.dumps(res, indent=1) + "\n")
    print(f"| {a.param} | loss |\n|---|---|")
    for v, l in zip(res["values"], res["loss"], strict=True):
        print(f"| {v:.4g} | {l:.4g} |")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    ax.loglog(res["values"], res["loss"], "o-", ms=3)
    ax.axvline(res["truth"], color="k", lw=0.8, ls="--", label="truth")
    ax.set_xlabel(a.param)
    ax.set_ylabel("loss (others at the truth)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / f"profile_{a.param}.png", dpi=100)


if __name__ == "__main__":
    main()
