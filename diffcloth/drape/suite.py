"""A synthetic drape-test suite in the real-data format: drapes of known fabrics simulated by
diffcloth, written as top-view JPEG silhouettes (256 x 256, soft edges, noise, 1.2 mm/pixel)
with a drape config per fabric and the truth beside it.

    out/<fabric>/seed<k>.jpg     k = 0..seeds-1: one drape per imperfection seed
    out/<fabric>/drape.toml      a fit config naming seed0.jpg (face up) and the density
    out/<fabric>/truth.json      the fabric, and each seed's DC and node count

The drapes are simulated with the same `imperfect_start` seeds a prediction uses, so a fitted
fabric can be checked seed by seed (`diffcloth drape predict`), and at the resolution `edge`.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from diffcloth.drape.images import CUSICK, shadow_image, write_silhouette
from diffcloth.drape.model import DEFAULT_EDGE, imperfect_start, make_drape_model
from diffcloth.physics.mesh import check_equilibrium, make_fabric, measure

__all__ = ["SUITE_FABRICS", "SUITE_MM_PER_PIXEL", "make_suite"]

#: the suite's fabrics (SI): limp, medium, stiff (isotropic) and an anisotropic one (ratio 3)
SUITE_FABRICS = {
    "limp": {"density": 0.12, "bend": 3e-6},
    "medium": {"density": 0.19, "bend": 1.2e-5},
    "stiff": {"density": 0.26, "bend": 8e-5},
    "aniso": {"density": 0.20, "bend_warp": 4.5e-5, "bend_weft": 1.5e-5, "bend_bias": 2.6e-5},
}
SUITE_MM_PER_PIXEL = 1.2  # a 256-pixel image spans 0.307 m: the whole specimen with a margin
SUITE_FIT_PARAMS = {"aniso": ["bend_warp", "bend_weft"]}


def make_suite(out, *, fabrics=None, seeds: int = 6, size: int = 256, edge: float = DEFAULT_EDGE,
               log=print) -> Path:  # fmt: skip
    """Write the suite into folder `out` (created); returns it. fabrics: {name: fabric fields}
    (default SUITE_FABRICS)."""
    out = Path(out)
    fabrics = SUITE_FABRICS if fabrics is None else fabrics
    model = make_drape_model(CUSICK, edge=edge)
    for name, values in fabrics.items():
        folder = out / name
        folder.mkdir(parents=True, exist_ok=True)
        fabric = make_fabric(None, dtype=jnp.float64, **values)
        truth = {"fabric": values, "edge": edge, "seeds": []}
        for seed in range(seeds):
            res = model.solve(fabric, jnp.asarray(imperfect_start(model, seed)))
            x = np.asarray(check_equilibrium(res, f"suite drape {name} seed {seed}").x)
            dc = measure.drape_coefficient(x, model.faces, CUSICK.specimen_radius,
                                           CUSICK.pedestal_radius).value  # fmt: skip
            nodes = measure.node_count(measure.outline_radius(x, model.faces))
            img = shadow_image(x, model.faces, CUSICK, size=size,
                               mm_per_pixel=SUITE_MM_PER_PIXEL, seed=seed)  # fmt: skip
            write_silhouette(folder / f"seed{seed}.jpg", img)
            truth["seeds"].append({"seed": seed, "file": f"seed{seed}.jpg", "dc": round(dc, 5),
                                   "node_count": int(nodes)})  # fmt: skip
            log(f"{name} seed {seed}: DC {dc:.4f}, {nodes} nodes")
        (folder / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
        (folder / "drape.toml").write_text(_config_text(name, values))
    return out


def _config_text(name: str, values: dict) -> str:
    params = SUITE_FIT_PARAMS.get(name, ["bend"])
    return (
        f'# synthetic drape test "{name}" (diffcloth.drape.suite): fit from one face-up image\n'
        f'name = "{name}"\n\n[fabric]\ndensity = {values["density"]}   # kg/m^2, weighed\n\n'
        f"[images]\nmm_per_pixel = {SUITE_MM_PER_PIXEL}\nwarp_angle = 0.0   # warp along +x\n\n"
        '[[observations]]\nfile = "seed0.jpg"\nsample = "A"\nside = "face"\n\n'
        f"[fit]\nparams = {json.dumps(params)}\nseeds = 1\n\n[predict]\nseeds = 6\n"
    )
