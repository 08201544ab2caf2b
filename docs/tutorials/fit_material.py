"""Tutorial 2: fit a cloth material to a video.

The target is a synthetic video rendered by diffcloth itself from the main job's scene
(`configs/drape_fit.toml`: a 10 x 13 net falling onto a sphere; here one camera and 48 x 48
images) with the true bending stiffness 2e-3 N m and normal air drag 1.0 N s/m^3. The fit
starts from 8e-4 and 0.4 and recovers both with Levenberg-Marquardt (`dc.fit.fit`). Writes
`fit_material_target.png` (the target's frames), `fit_material_loss.png` (loss and parameters
per step) into the figures folder (`DIFFCLOTH_FIGURES`, default `docs/tutorials/figures/`).
"""

import os
import time
import tomllib
from pathlib import Path

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import diffcloth as dc  # noqa: E402
import diffcloth.config  # noqa: E402, F401  (dc.config.parse_config)

ROOT = Path(__file__).resolve().parents[2]
FIGURES = Path(os.environ.get("DIFFCLOTH_FIGURES", Path(__file__).parent / "figures"))
t0 = time.perf_counter()

# the main job's scene, made smaller for this tutorial: one camera (the first), 48 x 48 images
data = tomllib.loads((ROOT / "configs" / "drape_fit.toml").read_text())
data["cameras"] = data["cameras"][:1]
data["render"].update(width=48, height=48)
scene = dc.build_scene(dc.config.parse_config(data))
truth = {"bend": 2e-3, "drag_normal": 1.0}
target = jax.jit(dc.simulate_and_render)(scene, truth)  # (cameras, T, H, W, 3)
print("target video:", target.shape)

result = dc.fit.fit(
    scene,
    target,
    free=["bend", "drag_normal"],
    init={"bend": 8e-4, "drag_normal": 0.4},
    steps=20,
    stages="none",  # one stage at full size (the default goes coarse to fine)
    # the target was rendered by this float32 scene, so fit in float32 too: method "auto" would
    # fit in float64 (the sphere is contact: right for footage), and the float32 target's own
    # round-off, grown by the contact, would then be a model error
    x64=False,
    progress=False,
)
print(result.method, result.summary())
print(
    "auto:",
    {k: v for k, v in result.auto.items() if k != "scans"},
    [(s["name"], s["best"], s["moved"]) for s in result.auto.get("scans", [])],
)
errors = {k: float(result.params[k]) / v - 1 for k, v in truth.items()}
for k, e in errors.items():
    print(f"{k}: fitted {float(result.params[k]):.6g}, true {truth[k]:.6g}, error {e:+.4%}")

FIGURES.mkdir(parents=True, exist_ok=True)
frames = np.asarray(target[0, :: max(1, target.shape[1] // 4)])  # camera 0, four frames
dc.io.save_png(FIGURES / "fit_material_target.png", np.concatenate(list(frames), axis=1),
               colorspace="srgb")  # fmt: skip

h = result.history
fig, axes = plt.subplots(1, 3, figsize=(10, 3), layout="constrained")
axes[0].semilogy(h.loss)
axes[0].set(xlabel="evaluation", ylabel="loss", title="loss")
for ax, name in zip(axes[1:], truth, strict=True):
    ax.plot(h.params[name], label="fit")
    ax.axhline(truth[name], color="k", ls="--", label="truth")
    ax.set(xlabel="evaluation", title=name)
    ax.legend()
fig.savefig(FIGURES / "fit_material_loss.png", dpi=80)

# the fit must recover both parameters to 1 %
assert result.ok and all(abs(e) < 0.01 for e in errors.values()), errors
print(f"done in {time.perf_counter() - t0:.1f} s")
