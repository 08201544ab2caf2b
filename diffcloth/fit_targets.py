"""Loading a fit's target video from what a config's [fit] targets names: a folder (one image
sequence per camera) or an .npz file (images and cloth masks, e.g. the cross-engine benchmark's
footage), checked (sizes, gaps in the numbering, value range) before any work; and the target
cloth masks of the footage loss ([fit.footage] masks)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from diffcloth import config as cfg

__all__ = ["box_downsample", "load_fit_targets", "load_targets"]


def _missing(settings, root: Path, what: str) -> cfg.ConfigError:
    make = f"; make them with `{settings.targets_make}`" if settings.targets_make else ""
    return cfg.ConfigError(f"[fit] targets = {str(root)!r} {what}{make}")


def box_downsample(a: np.ndarray, k: int, name: str = "targets") -> np.ndarray:
    """Average k x k pixel blocks of (..., H, W) or (..., H, W, 3) images (what a camera with k
    times fewer pixels and a box filter sees); H and W must be multiples of k.

    Shapes: (..., H, W[, 3]) -> (..., H / k, W / k[, 3])."""
    if k == 1:
        return a
    rgb = a.ndim >= 3 and a.shape[-1] == 3
    h, w = a.shape[-3:-1] if rgb else a.shape[-2:]
    if h % k or w % k:
        raise cfg.ConfigError(
            f"[fit] target_downsample = {k}: the {name} are {w}x{h} pixels, not multiples of {k}"
        )
    if rgb:
        return a.reshape(*a.shape[:-3], h // k, k, w // k, k, 3).mean(axis=(-4, -2))
    return a.reshape(*a.shape[:-2], h // k, k, w // k, k).mean(axis=(-3, -1))


def load_fit_targets(settings, sc) -> tuple[np.ndarray, np.ndarray | None]:
    """(video (cameras, T, H, W, 3) linear RGB, masks (cameras, T, H, W) in [0, 1] or None) of
    `settings.targets`, a folder (`load_targets`) or an .npz file, box-averaged by
    `target_downsample`. The masks are those the footage loss needs ([fit.footage] masks:
    "file" the .npz's `masks` array, "color" a colour key of the video, "auto" the file's
    when it has them); None without a footage loss, or when it needs none."""
    root = Path(settings.targets)
    if root.suffix == ".npz" or root.is_file():
        video, masks = _load_npz(settings, sc, root)
    else:
        video, masks = load_targets(settings, sc), None
    spec = settings.footage
    if spec is None or not spec.needs_masks:
        return video, None
    if spec.masks == "file" and masks is None:
        raise cfg.ConfigError(
            f'[fit.footage] masks = "file" needs target masks: an .npz target file with a '
            f"`masks` array (cameras, frames, H, W); {str(root)!r} has none. Use masks = "
            '"color" (a colour key) instead'
        )
    if spec.masks == "color" or masks is None:
        from diffcloth.fit.footage import cloth_mask_by_color

        color = spec.mask_color
        if color is None:
            color = np.asarray(sc.appearance.diffuse, np.float64)
        masks = cloth_mask_by_color(video, color, spec.mask_tolerance)
    return video, masks


def _load_npz(settings, sc, root: Path):
    """(video, masks or None) of an .npz target file: `images` (cameras, F, H, W, 3) linear RGB
    and optionally `masks` (cameras, F, H, W), frame i of the file = image index i (selected by
    target_frames / target_stride as a folder's images)."""
    if not root.is_file():
        raise _missing(settings, root, "does not exist")
    try:
        with np.load(root, allow_pickle=False) as z:
            if "images" not in z.files:
                raise cfg.ConfigError(
                    f"[fit] targets = {str(root)!r} has no `images` array (it has "
                    f"{sorted(z.files)}); an .npz target holds images (cameras, frames, H, W, 3) "
                    "and optionally masks (cameras, frames, H, W)"
                )
            images = np.asarray(z["images"], np.float64)
            masks = np.asarray(z["masks"], np.float64) if "masks" in z.files else None
    except (OSError, ValueError) as err:
        if isinstance(err, cfg.ConfigError):
            raise
        raise cfg.ConfigError(f"[fit] targets: cannot read {str(root)!r}: {err}") from None
    n_cams = len(sc.cameras)
    _, T, H, W, _ = sc.video_shape
    if images.ndim != 5 or images.shape[-1] != 3 or images.shape[0] != n_cams:
        raise cfg.ConfigError(
            f"[fit] targets: {str(root)!r} images have shape {images.shape}; expected (cameras = "
            f"{n_cams}, frames, H, W, 3)"
        )
    if masks is not None and masks.shape != images.shape[:-1]:
        raise cfg.ConfigError(
            f"[fit] targets: {str(root)!r} masks have shape {masks.shape}; expected the images' "
            f"{images.shape[:-1]} (cameras, frames, H, W)"
        )
    F = images.shape[1]
    first, stop = settings.target_frames or (0, F)
    if stop > F:
        raise cfg.ConfigError(
            f"[fit] target_frames = [{first}, {stop}] but {str(root)!r} has only {F} frames"
        )
    sel = slice(first, stop, settings.target_stride)
    images = images[:, sel]
    masks = None if masks is None else masks[:, sel]
    if images.shape[1] != T:
        more = "missing" if images.shape[1] < T else "extra"
        raise cfg.ConfigError(
            f"[fit] targets: {str(root)!r} gives {images.shape[1]} frames (of {F}, frames "
            f"[{first}, {stop}) every {settings.target_stride}), but the scene renders {T} frames "
            f"(num_frames {sc.num_frames} // frame_stride {sc.frame_stride}): "
            f"{abs(images.shape[1] - T)} {more}; set [fit] target_frames / target_stride"
        )
    if not np.all(np.isfinite(images)) or (masks is not None and not np.all(np.isfinite(masks))):
        raise cfg.ConfigError(f"[fit] targets: {str(root)!r} holds NaN/inf values")
    k = settings.target_downsample
    images = box_downsample(images, k)
    masks = None if masks is None else box_downsample(masks, k, "target masks")
    if images.shape[2:4] != (H, W):
        raise cfg.ConfigError(
            f"[fit] targets: {str(root)!r} images are {images.shape[3]}x{images.shape[2]} pixels "
            f"after target_downsample = {k}; the scene renders {W}x{H} ([render] width, height)"
        )
    # a path tracer's linear values exceed 1 at highlights: a camera saturates there
    return np.clip(images, 0.0, 1.0), None if masks is None else np.clip(masks, 0.0, 1.0)


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
    if root.suffix == ".npz" or root.is_file():
        return _load_npz(settings, sc, root)[0]
    if not root.is_dir():
        raise _missing(settings, root, "is not a folder (nor an .npz file)")
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
            if img.shape[2] != 3:
                kind = {1: "grey", 2: "grey + alpha", 4: "RGBA"}.get(img.shape[2], "odd")
                raise cfg.ConfigError(
                    f"[fit] targets: {str(p)!r} is a {kind} image ({img.shape[2]} channels); "
                    "targets must be RGB (3 channels, no alpha): convert them first"
                )
            k = settings.target_downsample
            if k > 1:
                img = box_downsample(img, k, f"images of {str(folder)!r}")
            if img.shape[:2] != (H, W):
                after = f" after target_downsample = {k}" if k > 1 else ""
                raise cfg.ConfigError(
                    f"[fit] targets: {str(p)!r} is {img.shape[1]}x{img.shape[0]} pixels{after}, "
                    f"the scene renders {W}x{H} ([render] width, height)"
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
