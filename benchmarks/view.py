"""Viewer latency: slider moved -> re-simulated frames sent to the browser (JSON lines).

    python benchmarks/view.py [--config configs/drape.toml] [--moves 10] [--no-browser]

With a browser (playwright + chromium, as in tests/test_view.py) the slider is moved in headless
Chromium with the keyboard, so the time includes the websocket both ways; "server_ms" is the part
from the slider message reaching the server to the new frame being sent, "resim_ms" the jitted
re-simulation alone (physics + tessellation + collision of every frame). The compile happens once,
before the first move, and is reported separately ("compile_s").
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="configs/drape.toml")
    ap.add_argument("--moves", type=int, default=10)
    ap.add_argument("--no-browser", action="store_true")
    args = ap.parse_args()

    import jax
    from _timing import emit, meta

    emit(meta("view.py"))

    from diffcloth.view.app import Viewer
    from diffcloth.view.model import load_view

    t0 = time.perf_counter()
    model = load_view(args.config)
    compile_s = time.perf_counter() - t0
    viewer = Viewer(model, port=None, autoplay=False)
    net = model.scene.net.rest.shape
    base = {
        "bench": "view",
        "config": args.config,
        "net": f"{net[1]}x{net[0]}",
        "frames": model.num_frames,
        "substeps": model.scene.sim.num_substeps,
        "vertices": int(model.frames.cloth.shape[1]),
        "backend": jax.default_backend(),
        "compile_s": round(compile_s, 2),
        "load_1min": round(os.getloadavg()[0], 1),
    }
    exe = os.environ.get("DIFFCLOTH_CHROMIUM") or shutil.which("chromium")
    client_ms: list[float] = []
    try:
        if exe and not args.no_browser:
            from playwright.sync_api import sync_playwright

            with sync_playwright() as p:
                b = p.chromium.launch(
                    executable_path=exe,
                    args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
                )
                page = b.new_page(viewport={"width": 640, "height": 480})
                page.goto(viewer.url)
                page.wait_for_selector("text=Connected", timeout=60_000)
                label = page.locator("label", has_text="log10 stretch")
                thumb = page.locator(f"[id='{label.get_attribute('for')}'] [role=slider]")
                thumb.focus()
                for k in range(args.moves):
                    runs = model.resim_count
                    t = time.perf_counter()
                    thumb.press("ArrowLeft" if k % 2 == 0 else "ArrowRight")
                    while len(viewer.latencies) <= runs:
                        time.sleep(0.002)
                    client_ms.append(1e3 * (time.perf_counter() - t))
                b.close()
            mode = "browser"
        else:
            for k in range(args.moves):
                s = viewer.sliders["stretch"]
                s.value = s.value + (-0.05 if k % 2 == 0 else 0.05)
                viewer._slider_moved("stretch")
                while len(viewer.latencies) < k + 1:
                    time.sleep(0.002)
            mode = "server"
    finally:
        viewer.stop()
    server_ms = [1e3 * v for v in viewer.latencies]
    resim_ms = [float(line.split(" in ")[-1].split()[0]) for line in model.log if " in " in line]
    rows = {"server_ms": server_ms, "resim_ms": resim_ms}
    if client_ms:
        rows["slider_to_frames_ms"] = client_ms
    # the re-simulation per physics substep (tessellation included), to compare with the physics
    # benchmark's idle figure for the same net (benchmarks/results/physics.jsonl)
    steps = model.num_frames * model.scene.sim.num_substeps
    base["resim_us_per_substep"] = round(1e3 * statistics.median(resim_ms) / steps, 1)
    for name, values in rows.items():
        unit = name.removesuffix("_ms")
        emit(
            {
                **base,
                "mode": mode,
                "metric": unit,
                f"{unit}_ms": round(statistics.median(values), 1),
                f"{unit}_max_ms": round(max(values), 1),
                "n": len(values),
            }
        )


if __name__ == "__main__":
    main()
