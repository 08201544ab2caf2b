"""The footage loss of a fit config: [fit] loss = "footage" and its [fit.footage] table.

[fit]          loss = "footage"     compare with `diffcloth.fit.footage` (robust colour + cloth
                                    silhouette) instead of an image loss
[fit.footage]  color = "huber" ("l2", "huber", "charbonnier", "cauchy", "none"),
               color_scale = 0.05 (0, 1], color_weight = 1.0 [0, 1e6],
               mask = "iou" ("iou", "distance", "l2", "none"), mask_weight = 1.0 [0, 1e6],
               color_region = "cloth" ("cloth": colour only on the target's cloth pixels grown
                   by color_margin px; "all": every pixel), color_margin = 3 [0, 64],
               masks = "auto" (the target file's masks when it has them, else by colour),
                   "file" (the `masks` array of an .npz target file), "color" (a colour key:
                   `cloth_mask_by_color` with mask_color, default [appearance] diffuse, and
                   mask_tolerance = 0.1 (0, 1])
The defaults are the cross-engine recipe's (benchmarks/cross_engine/protocol.py).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from diffcloth.config import _fields as cfg

__all__ = ["FOOTAGE_KEYS", "FootageSpec", "parse_footage"]

COLORS = ("l2", "huber", "charbonnier", "cauchy", "none")
MASKS = ("iou", "distance", "l2", "none")
MASK_SOURCES = ("auto", "file", "color")
REGIONS = ("cloth", "all")


@dataclasses.dataclass(frozen=True)
class FootageSpec:
    """[fit.footage]: the footage loss's settings and the rule that makes the target masks."""

    color: str = "huber"
    color_scale: float = 0.05
    color_weight: float = 1.0
    mask: str = "iou"
    mask_weight: float = 1.0
    color_region: str = "cloth"
    color_margin: int = 3
    masks: str = "auto"
    mask_color: tuple[float, float, float] | None = None
    mask_tolerance: float = 0.1

    def loss(self):
        """The `diffcloth.fit.footage.FootageLoss` of these settings."""
        from diffcloth.fit.footage import FootageLoss

        return FootageLoss(
            color=self.color,
            color_scale=self.color_scale,
            color_weight=self.color_weight,
            mask=None if self.mask == "none" else self.mask,
            mask_weight=self.mask_weight,
            color_margin=self.color_margin if self.color_region == "cloth" else None,
        )

    @property
    def needs_masks(self) -> bool:
        """True when the loss reads target masks (a mask term, or colour on the cloth only)."""
        return self.mask != "none" or (self.color_region == "cloth" and self.color != "none")


FOOTAGE_KEYS = tuple(f.name for f in dataclasses.fields(FootageSpec))


def parse_footage(fit_table: Mapping[str, Any], loss: str) -> FootageSpec | None:
    """[fit.footage] of a [fit] table (None unless loss = "footage"); ConfigError names the key,
    the bad value and the allowed range."""
    where = "fit.footage"
    table = fit_table.get("footage")
    if loss != "footage":
        if table is not None:
            raise cfg.ConfigError(
                f'[fit.footage] needs [fit] loss = "footage" (got loss = {loss!r})'
            )
        return None
    table = {} if table is None else table
    if not isinstance(table, Mapping):
        raise cfg.ConfigError(f"[fit] footage = {table!r} must be a table ([fit.footage])")
    cfg.check_keys(table, FOOTAGE_KEYS, where)
    spec = FootageSpec(
        color=cfg.get_choice(table, "color", "huber", COLORS, where=where),
        color_scale=cfg.get_number(
            table, "color_scale", 0.05, where=where, lo=0, hi=1, lo_inclusive=False
        ),
        color_weight=cfg.get_number(table, "color_weight", 1.0, where=where, lo=0, hi=1e6),
        mask=cfg.get_choice(table, "mask", "iou", MASKS, where=where),
        mask_weight=cfg.get_number(table, "mask_weight", 1.0, where=where, lo=0, hi=1e6),
        color_region=cfg.get_choice(table, "color_region", "cloth", REGIONS, where=where),
        color_margin=cfg.get_number(
            table, "color_margin", 3, where=where, lo=0, hi=64, integer=True
        ),
        masks=cfg.get_choice(table, "masks", "auto", MASK_SOURCES, where=where),
        mask_color=None
        if "mask_color" not in table
        else cfg.get_vec3(table, "mask_color", where=where),
        mask_tolerance=cfg.get_number(
            table, "mask_tolerance", 0.1, where=where, lo=0, hi=1, lo_inclusive=False
        ),
    )
    if spec.color == "none" and spec.mask == "none":
        raise cfg.ConfigError(
            '[fit.footage] color = "none" and mask = "none" compare nothing: keep one of them'
        )
    if spec.color == "none" and spec.mask_weight == 0:
        raise cfg.ConfigError('[fit.footage] mask_weight = 0 with color = "none" compares nothing')
    if spec.mask_color is not None and not all(0 <= c <= 1 for c in spec.mask_color):
        raise cfg.ConfigError(
            f"[fit.footage] mask_color = {list(spec.mask_color)} is out of range; allowed: "
            "3 numbers in [0, 1] (a linear RGB colour)"
        )
    return spec
