"""The cross-engine benchmark's scenes: geometry, cameras, light, albedos and the two stiffness
regimes. Plain data (no diffcloth, no Warp, no Mitsuba), shared by the generator (Warp physics,
Mitsuba images) and the protocol (diffcloth fit).

Units: m, s, N. Frames at 30 fps; the Warp reference steps dt = 1/2400 s (80 substeps a frame).
"""

from __future__ import annotations

FPS = 30
DT = 1.0 / 2400.0
SUBSTEPS = 80  # per frame: 1/30 s
FIT_FRAMES = 60
PREDICT_FRAMES = 30
SIZE = 128  # image width = height, px

ROWS = COLS = 13
CLOTH_SIZE = (1.0, 1.0)  # m (width along the columns, depth along the rows)
CLOTH_ALBEDO = (0.7, 0.15, 0.2)
SPHERE_ALBEDO = (0.25, 0.45, 0.75)
FLOOR_ALBEDO = (0.5, 0.5, 0.5)
AMBIENT = 0.15  # radiance of the constant environment (Mitsuba) = diffcloth's ambient light
LIGHT_DIR = (0.4, 1.0, 0.3)  # toward the light
LIGHT_INTENSITY = 1.0  # diffcloth intensity; Mitsuba irradiance pi * intensity
FOV_Y = 40.0

#: Provot parameters that stay the same in both regimes (the truth; the fit does not see them)
BASE = {
    "d_struct": 0.02,
    "d_shear": 0.01,
    "d_flex": 0.002,
    "air_damping": 0.01,  # 0.002 makes the stiff drape chaotic: Warp float32 vs float64 7 cm apart
    "density": 0.2,
    "mass_lumping": "uniform",
    "friction": 0.3,
    "friction_rule": "coulomb",
    "contact_thickness": 0.005,
}

#: membrane stiffness regimes, 10x apart; shear and flexion scale with it
REGIMES = {
    "soft": {"k_struct": 40.0, "k_shear": 10.0, "k_flex": 2.0},
    "stiff": {"k_struct": 400.0, "k_shear": 100.0, "k_flex": 20.0},
}

SCENES = {
    # a flat cloth dropped onto a sphere above a floor
    "drape": {
        "warp": {"height": 1.0, "plane": "xz", "pins": None, "planes": [((0.0, 1.0, 0.0), 0.0)]},
        "sphere": ((0.0, 0.55, 0.0), 0.3),
        "cameras": [
            {"eye": (0.0, 1.6, 2.0), "target": (0.0, 0.55, 0.0)},
            {"eye": (1.9, 1.3, 0.6), "target": (0.0, 0.5, 0.0)},
        ],
    },
    # a horizontal cloth held at two corners, swinging down (no sphere)
    "hang": {
        "warp": {
            "height": 1.3,
            "plane": "xz",
            "pins": "top_corners",
            "planes": [((0.0, 1.0, 0.0), 0.0)],
        },
        "sphere": None,
        "cameras": [
            {"eye": (0.0, 1.2, 2.6), "target": (0.0, 0.8, 0.0)},
            {"eye": (2.4, 1.5, 0.8), "target": (0.0, 0.8, 0.0)},
        ],
    },
}


def warp_params(scene: str, regime: str) -> dict:
    """The full Warp parameter dict of a (scene, regime) case."""
    p = dict(BASE)
    p.update(REGIMES[regime])
    p.update(SCENES[scene]["warp"])
    return p


CASES = [(s, r) for s in SCENES for r in REGIMES]
