"""Tutorial 4: mesh cloth and the drape test.

A 30 cm disc of a measured fabric (the preset `wang2011-gray-interlock`, docs/fabrics.md) is held
on an 18 cm pedestal, the Cusick drape tester, as a triangle mesh (`diffcloth.physics.mesh`, a
coarse 15 mm edge). From a small seeded imperfection the static-equilibrium solve (Newton,
float64) finds the drape; its drape coefficient (DC) is measured twice: from the simulated rim
(differentiable) and, as a lab would, from a synthetic top-view photo of its shadow read back
with `diffcloth.drape` (DC and node count). Last, the derivative of the DC with respect to the
bending rigidity, by the implicit function theorem through the equilibrium. Writes
`drape_test_shadow.png` (the top-view photo) and `drape_test_side.png` (an oblique view of the
mesh) into the figures folder (`DIFFCLOTH_FIGURES`, default `docs/tutorials/figures/`).
"""

import dataclasses
import os
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)  # the mesh solver and the drape test run in float64

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import diffcloth as dc  # noqa: E402
from diffcloth import drape  # noqa: E402
from diffcloth.drape.model import imperfect_start, make_drape_model, rim_dc  # noqa: E402
from diffcloth.physics import mesh  # noqa: E402

FIGURES = Path(os.environ.get("DIFFCLOTH_FIGURES", Path(__file__).parent / "figures"))
t0 = time.perf_counter()

model = make_drape_model(drape.CUSICK, edge=0.015)  # 0.15 m disc on a 0.09 m pedestal
fabric = mesh.make_fabric("wang2011-gray-interlock", dtype=jnp.float64)
print(f"{model.num_vertices} vertices; bending {float(fabric.bend_warp) * 1e6:.1f} uN m, "
      f"density {float(fabric.density) * 1e3:.0f} g/m^2")  # fmt: skip

x0 = jnp.asarray(imperfect_start(model, seed=0))
res = model.solve(fabric, x0)
dc_rim = float(rim_dc(model, res.x))
print(f"equilibrium: converged {bool(res.converged)} in {int(res.iterations)} Newton steps, "
      f"DC from the rim {dc_rim:.3f}")  # fmt: skip

# the lab's way: a top-view photo of the shadow (256 px, 1.2 mm per pixel), read back
FIGURES.mkdir(parents=True, exist_ok=True)
photo = drape.shadow_image(np.asarray(res.x), model.faces, size=256, mm_per_pixel=1.2)
dc.io.save_png(FIGURES / "drape_test_shadow.png", photo.astype(np.float64) / 255.0)
sil = drape.read_silhouette(FIGURES / "drape_test_shadow.png", mm_per_pixel=1.2)
features = drape.drape_features(sil)
print(f"from the photo: DC {features['dc']:.3f}, {features['node_count']} nodes")

# an oblique view of the mesh (matplotlib; `diffcloth render configs/cusick.toml` renders it)
x = np.asarray(res.x)
fig = plt.figure(figsize=(4, 3), layout="constrained")
ax = fig.add_subplot(projection="3d")
ax.plot_trisurf(x[:, 0], x[:, 2], x[:, 1], triangles=model.faces, color="#c8505a",
                edgecolor="k", linewidth=0.1)  # fmt: skip
ax.set(xlabel="x (m)", ylabel="z (m)", zlabel="y (m)", aspect="equal")
ax.view_init(elev=25, azim=-60)
fig.savefig(FIGURES / "drape_test_side.png", dpi=80)


# d DC / d bending, through the equilibrium (implicit function theorem; warm start at the drape)
def drape_dc(bend):
    f = dataclasses.replace(fabric, bend_warp=bend, bend_weft=bend, bend_bias=bend)
    return rim_dc(model, model.solve(f, res.x).x)


slope = float(jax.jvp(drape_dc, (fabric.bend_warp,), (fabric.bend_warp,))[1])
print(f"d DC / d log(bending) = {slope:.3f} (a stiffer fabric drapes less: DC rises)")

# checks: converged, the two DC measurements agree, a drape with folds, DC rises with bending
assert bool(res.converged)
assert 0.2 < dc_rim < 0.95 and abs(features["dc"] - dc_rim) < 0.03, (dc_rim, features["dc"])
assert 3 <= features["node_count"] <= 12 and slope > 0
print(f"done in {time.perf_counter() - t0:.1f} s")
