"""Loading a fit's target video from the folder a config's [fit] targets names: one image
sequence per camera, checked (sizes, gaps in the numbering, value range) before any work."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from diffcloth import config as cfg

__all__ = ["load_targets"]


def load_targets(settings, sc) -> np.ndarray:
    """(cameras, T, H, W, 3) linear RGB target video from the folder `settings.targets`, checked
    against the scene before any work; ConfigError names the folder, file and what is allowed.

    Layout ([fit] keys): one folder per camera: `target_cameras` (names or globs inside
    `targets`; default cam0, cam1, ..., or `targets` itself for one camera without cam0/). In each,
    the images matching `target_glob` (default "*.png"; may name a subfolder, "rgb/*.png"),
    sorted naturally (frame_2 before frame_10), whose numbering must run without gaps
    (`io.media.check_numbered_sequence`); of those, `target_frames = [first, stop]` (default
    all) every `target_stride`-th. The images left must be exactly the video's frames: image i
    shows the scene's rendered frame i, i.e. simulated frame (i + 1) * frame_stride with
    [render] first_frame = 1 (default: the initial state is not drawn) or i * frame_stride with
    first_frame = 0. `colorspace`: "auto" (default: the PNG's sRGB/gAMA chunk, else sRGB for 8-bit
    files and linear for 16-bit ones), "srgb" or "linear"; targets are converted to linear RGB.
    """
    from diffcloth.io import load_image
    from diffcloth.io.media import check_numbered_sequence, natural_key

    root = Path(settings.targets)
    if not root.is_dir():
        raise cfg.ConfigError(f"[fit] targets = {str(root)!r} is not a folder")
    n_cams = len(sc.cameras)
    if settings.target_cameras is not None:
        names = list(settings.target_cameras)
        if len(names) != n_cams:
            raise cfg.ConfigError(
                f"[fit] target_cameras names {len(names)} folder(s) {names}, but the scene has "
                f"{n_cams} camera(s)"
            )
    elif n_cams == 1 and not (root / "cam0").is_dir():
        names = ["."]
    else:
        names = [f"cam{i}" for i in range(n_cams)]
    _, T, H, W, _ = sc.video_shape
    videos = []
    for cam, name in enumerate(names):
        hits = [p for p in sorted(root.glob(name)) if p.is_dir()] if name != "." else [root]
        if len(hits) != 1:
            what = "no folder" if not hits else f"{len(hits)} folders ({[h.name for h in hits]})"
            raise cfg.ConfigError(
                f"[fit] targets: camera {cam} needs one folder {str(root / name)!r}, found {what}; "
                f"give one folder per camera (cam0, cam1, ... or [fit] target_cameras)"
            )
        folder = hits[0]
        files = sorted((p for p in folder.glob(settings.target_glob) if p.is_file()),
                       key=natural_key)  # fmt: skip
        if not files:
            raise cfg.ConfigError(
                f"[fit] targets: no files matching {settings.target_glob!r} in {str(folder)!r} "
                f"(camera {cam}); the folder is empty or the pattern ([fit] target_glob) is wrong"
            )
        try:  # a gap in frame_0, frame_1, frame_3 would misalign every later image
            check_numbered_sequence(
                files, f"[fit] targets: {str(folder)!r} ({settings.target_glob!r}, camera {cam})"
            )
        except ValueError as err:
            raise cfg.ConfigError(str(err)) from None
        first, stop = settings.target_frames or (0, len(files))
        if stop > len(files):
            raise cfg.ConfigError(
                f"[fit] target_frames = [{first}, {stop}] but {str(folder)!r} has only "
                f"{len(files)} matching images"
            )
        chosen = files[first : stop : settings.target_stride]
        if len(chosen) != T:
            more = "missing" if len(chosen) < T else "extra"
            raise cfg.ConfigError(
                f"[fit] targets: {str(folder)!r} gives {len(chosen)} images (of {len(files)} "
                f"matching {settings.target_glob!r}, frames [{first}, {stop}) every "
                f"{settings.target_stride}), but the scene renders {T} frames (num_frames "
                f"{sc.num_frames} // frame_stride {sc.frame_stride}): {abs(len(chosen) - T)} "
                f"{more}; image i must show rendered frame i (set target_frames/target_stride, or "
                "[sim] num_frames / [render] frame_stride)"
            )
        frames = []
        for p in chosen:
            try:
                img = load_image(p, colorspace=settings.colorspace)
            except (OSError, ValueError) as err:
                raise cfg.ConfigError(f"[fit] targets: cannot read {str(p)!r}: {err}") from None
            if img.shape[:2] != (H, W):
                raise cfg.ConfigError(
                    f"[fit] targets: {str(p)!r} is {img.shape[1]}x{img.shape[0]} pixels, the "
                    f"scene renders {W}x{H} ([render] width, height)"
                )
            if img.shape[2] != 3:
                kind = {1: "grey", 2: "grey + alpha", 4: "RGBA"}.get(img.shape[2], "odd")
                raise cfg.ConfigError(
                    f"[fit] targets: {str(p)!r} is a {kind} image ({img.shape[2]} channels); "
                    "targets must be RGB (3 channels, no alpha): convert them first"
                )
            if not np.all(np.isfinite(img)):
                raise cfg.ConfigError(f"[fit] targets: {str(p)!r} holds NaN/inf pixels")
            if img.min() < 0 or img.max() > 1:  # float files (TIFF, EXR): not an image's range
                raise cfg.ConfigError(
                    f"[fit] targets: {str(p)!r} holds values in [{img.min():g}, {img.max():g}]; "
                    "target images must be in [0, 1] (clip or convert them first)"
                )
            frames.append(img)
        videos.append(np.stack(frames))
    return np.stack(videos)
