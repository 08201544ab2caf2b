"""diffcloth.drape: the image and measurement side of the Cusick drape test (numpy, scipy).

sil = read_silhouette("drape1.jpg", DrapeGeometry(0.15, 0.09), mm_per_pixel=1.2)
problems = check_silhouette(sil)                  # mis-scaled / off-centre, naming the file
features = drape_features(sil)                    # dc, node_count, r_theta, spectrum, ...
angle, mirrored, iou = align_rotation(features["r_theta"], r_sim)
points, warnings = read_drape_scan("drape1.obj")  # wrong units / rotated / off-centre
"""

from diffcloth.drape.images import (
    BACKGROUND_LEVEL,
    CLOTH_LEVEL,
    CUSICK,
    DEFAULT_FRAME,
    DrapeGeometry,
    Silhouette,
    SilhouetteError,
    check_geometry,
    check_silhouette,
    overlay_image,
    polar_shadow_image,
    read_silhouette,
    shadow_image,
    write_silhouette,
)
from diffcloth.drape.outline import (
    align_rotation,
    chamfer_polar,
    drape_coefficient_image,
    drape_features,
    iou_best_rotation,
    node_count,
    outline_centroid,
    outline_radius_image,
    outline_spectrum,
    polar_iou,
    rotate_outline,
    shadow_area,
)
from diffcloth.drape.scan import (
    align_scan_rotation,
    chamfer_distance,
    check_scan,
    read_drape_scan,
)

__all__ = [
    "BACKGROUND_LEVEL",
    "CLOTH_LEVEL",
    "CUSICK",
    "DEFAULT_FRAME",
    "DrapeGeometry",
    "Silhouette",
    "SilhouetteError",
    "align_rotation",
    "align_scan_rotation",
    "chamfer_distance",
    "chamfer_polar",
    "check_geometry",
    "check_scan",
    "check_silhouette",
    "drape_coefficient_image",
    "drape_features",
    "iou_best_rotation",
    "node_count",
    "outline_centroid",
    "outline_radius_image",
    "outline_spectrum",
    "overlay_image",
    "polar_iou",
    "polar_shadow_image",
    "read_drape_scan",
    "read_silhouette",
    "rotate_outline",
    "shadow_area",
    "shadow_image",
    "write_silhouette",
]
