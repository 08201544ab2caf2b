"""Level-of-detail helper: level from projected size in pixels."""

import math

import pytest

from diffcloth.surface import focal_length_pixels, projected_size_pixels, select_level


def test_focal_length_and_projected_size():
    f = focal_length_pixels(90.0, 200)
    assert f == pytest.approx(100.0)
    # small-angle limit: diameter ~ 2 f r / d
    assert projected_size_pixels(0.01, 10.0, f) == pytest.approx(2 * 100 * 0.01 / 10, rel=1e-4)
    assert math.isinf(projected_size_pixels(1.0, 0.5, f))


def test_level_decreases_with_distance_and_is_clamped():
    f = focal_length_pixels(45.0, 512)
    levels = [select_level(0.5, d, f, num_patches=10) for d in (0.6, 1.0, 2.0, 4.0, 8.0, 50.0)]
    assert levels == sorted(levels, reverse=True)
    assert levels[0] == 32 and levels[-1] == 2
    assert select_level(0.5, 0.1, f, num_patches=10) == 32  # camera inside the bound
    assert select_level(0.5, 3.0, f, num_patches=10) == 8
    lv = select_level(0.5, 3.0, f, num_patches=10, power_of_two=False, pixels_per_segment=2.0)
    assert lv == math.ceil(projected_size_pixels(0.5, 3.0, f) / 2.0 / 10)
    assert all(2 <= v <= 32 for v in levels)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"bounding_radius": -1.0}, "bounding_radius"),
        ({"distance": -1.0}, "distance"),
        ({"focal_pixels": 0.0}, "focal_pixels"),
        ({"num_patches": 0}, "num_patches"),
        ({"min_level": 1}, "min_level"),
        ({"pixels_per_segment": 0.0}, "pixels_per_segment"),
    ],
)
def test_bad_arguments_raise(kwargs, match):
    args = {"bounding_radius": 1.0, "distance": 3.0, "focal_pixels": 100.0, "num_patches": 4}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        select_level(
            args.pop("bounding_radius"), args.pop("distance"), args.pop("focal_pixels"), **args
        )
    with pytest.raises(ValueError, match="fov"):
        focal_length_pixels(0.0, 100)
