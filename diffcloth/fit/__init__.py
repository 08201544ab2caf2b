"""diffcloth.fit: image losses, parameter constraints, the optax loop, identifiability.

The scene-level `fit(scene, targets, free=[...])` is built on these by the pipeline. Engines:
`fit_params` (optax), `fit_lm` (Levenberg-Marquardt on residuals), `fit_staged` (staged LM with
free subsets and scans).
"""

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
from diffcloth.fit.identifiability import Identifiability, format_identifiability, identifiability
from diffcloth.fit.interrupt import catch_interrupts
from diffcloth.fit.lm import fit_lm, fit_lm_multistart
from diffcloth.fit.loop import (
    FitResult,
    History,
    MultiStartResult,
    default_optimizer,
    fit_multistart,
    fit_params,
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
    fit,
    make_targets,
    scene_identifiability,
    video_loss,
)
from diffcloth.fit.settings import FitSettings
from diffcloth.fit.staged import ParamStage, StagedResult, fit_staged
from diffcloth.fit.ties import Ties, parse_ties

__all__ = [
    "FitSettings",
    "ParamStage",
    "StagedResult",
    "fit_lm",
    "fit_lm_multistart",
    "fit_staged",
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
    "fit_multistart",
    "fit_params",
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
