"""diffcloth.fit: one front door, `fit(scene, targets, free=[...], method="auto")`, and its parts.

`fit` runs every engine and schedule on a scene: method "auto" (the default: float64 with
contact, a scan when the start is far, coarse-to-fine Levenberg-Marquardt), "lm", "staged" or
"adam"; the result's summary names the knob to turn when a fit stalls. The engines themselves
(`engines.lm`, `engines.adam`, `engines.staged`, ...) fit any JAX function of a parameter dict.
Also here: image, footage and silhouette losses, constraints, ties, identifiability.
"""

import warnings as _warnings

from diffcloth.fit import engines
from diffcloth.fit.constraints import (
    Bounded,
    Constraint,
    Identity,
    Positive,
    make_constraint,
    make_constraints,
    to_physical,
    to_raw,
)
from diffcloth.fit.footage import (
    FootageLoss,
    FootageTargets,
    cloth_mask_by_color,
    footage_residuals,
    prepare_targets,
    scene_loss,
    scene_residuals,
)
from diffcloth.fit.front import fit
from diffcloth.fit.identifiability import Identifiability, format_identifiability, identifiability
from diffcloth.fit.interrupt import catch_interrupts
from diffcloth.fit.loop import (
    FitResult,
    History,
    MultiStartResult,
    default_optimizer,
    load_checkpoint,
    pack_tree,
    save_checkpoint,
    unpack_tree,
)
from diffcloth.fit.losses import (
    absolute_error,
    blur,
    charbonnier_error,
    downsample,
    gaussian_pyramid,
    image_loss,
    pyramid_loss,
    squared_error,
    validate_targets,
)
from diffcloth.fit.masks import (
    distance_transform_loss,
    iou_loss,
    mask_loss,
    mask_residuals,
    soft_iou,
    target_distances,
)
from diffcloth.fit.robust import ROBUST_KINDS, robust_residuals, robust_rho
from diffcloth.fit.scene_fit import (
    LOSSES,
    default_constraint,
    make_targets,
    scene_identifiability,
    video_loss,
)
from diffcloth.fit.settings import FitSettings
from diffcloth.fit.staged import ParamStage, StagedResult
from diffcloth.fit.ties import Ties, parse_ties

__all__ = [
    "engines",
    "FitSettings",
    "ParamStage",
    "StagedResult",
    "Ties",
    "parse_ties",
    "FootageLoss",
    "FootageTargets",
    "ROBUST_KINDS",
    "cloth_mask_by_color",
    "distance_transform_loss",
    "footage_residuals",
    "iou_loss",
    "mask_loss",
    "mask_residuals",
    "prepare_targets",
    "robust_residuals",
    "robust_rho",
    "scene_loss",
    "scene_residuals",
    "soft_iou",
    "target_distances",
    "LOSSES",
    "default_constraint",
    "fit",
    "make_targets",
    "scene_identifiability",
    "video_loss",
    "Bounded",
    "Constraint",
    "FitResult",
    "History",
    "Identifiability",
    "Identity",
    "MultiStartResult",
    "Positive",
    "absolute_error",
    "blur",
    "charbonnier_error",
    "default_optimizer",
    "downsample",
    "format_identifiability",
    "gaussian_pyramid",
    "identifiability",
    "image_loss",
    "load_checkpoint",
    "pack_tree",
    "save_checkpoint",
    "unpack_tree",
    "catch_interrupts",
    "make_constraint",
    "make_constraints",
    "pyramid_loss",
    "squared_error",
    "to_physical",
    "to_raw",
    "validate_targets",
]


def __getattr__(name: str):
    """The engine names this package used to export: still there, with a DeprecationWarning."""
    if name in engines.RENAMED:
        new = engines.RENAMED[name]
        _warnings.warn(
            f"diffcloth.fit.{name} is deprecated: use diffcloth.fit.fit(scene, targets, free=..., "
            f"method=...) for a scene, or diffcloth.fit.engines.{new} for your own function",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(engines, new)
    raise AttributeError(f"module 'diffcloth.fit' has no attribute {name!r}")
