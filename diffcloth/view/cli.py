"""`diffcloth view CONFIG_OR_RESULT_DIR [--export out.html]` (called by diffcloth.cli)."""

from __future__ import annotations

import logging
import sys
import time

import viser  # noqa: F401  (fail here, with ImportError, when the `view` extra is missing)


def run(args) -> int:
    """Serve the viewer until Ctrl-C, or write the --export recording. Returns the exit code."""
    from diffcloth.config import ConfigError
    from diffcloth.view.app import Viewer, export_html
    from diffcloth.view.model import load_view

    logger = logging.getLogger("diffcloth.view")
    if not logger.handlers:  # the re-simulation log lines go to stdout
        handler = logging.StreamHandler(sys.stdout)
        handler.setFormatter(logging.Formatter("%(asctime)s %(message)s", "%H:%M:%S"))
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
    print(f"diffcloth view {args.path}: simulating and compiling ...", flush=True)
    t0 = time.perf_counter()
    try:
        model = load_view(args.path, level=args.level, size=args.size)
    except (ConfigError, OSError, ValueError) as err:  # ValueError: a mesh solve that failed
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"  ready in {time.perf_counter() - t0:.1f} s", flush=True)
    if args.export:
        path = export_html(model, args.export, side_by_side=not args.overlay)
        size = path.stat().st_size / 1e6
        print(f"wrote {path} ({size:.1f} MB): open it in a browser, no server or network needed")
        return 0
    viewer = Viewer(model, host=args.host, port=args.port, autoplay=not args.paused)
    print(f"viewer at {viewer.url}  (Ctrl-C to stop)", flush=True)
    try:
        viewer.serve_forever()
    except KeyboardInterrupt:  # a second Ctrl-C while shutting down
        viewer.stop()
    print("viewer stopped")
    return 0
