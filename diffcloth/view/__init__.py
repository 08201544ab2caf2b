"""Interactive browser viewer (the `view` extra: viser). Not imported by `import diffcloth`.

    diffcloth view configs/drape.toml            # a scene config: live viewer on 127.0.0.1:8080
    diffcloth view results/drape_fit             # a fit result: target and fit, loss, table
    diffcloth view results/drape_fit --export results/drape_fit/viewer.html

`diffcloth.view.model` (frames, re-simulation, renders) needs only the core; `diffcloth.view.app`
(the viser server and the HTML export) needs viser. See docs/viewer.md.
"""

__all__ = ["ViewModel", "Viewer", "export_html", "load_view", "main"]


def __getattr__(name):
    if name in ("ViewModel", "load_view"):
        from diffcloth.view import model

        return getattr(model, name)
    if name in ("Viewer", "export_html"):
        from diffcloth.view import app

        return getattr(app, name)
    if name == "main":
        from diffcloth.view.cli import main

        return main
    raise AttributeError(f"module 'diffcloth.view' has no attribute {name!r}")
