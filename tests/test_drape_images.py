"""diffcloth.drape: drape-test images, outlines and scans (numpy only, no JAX compiles)."""

import math

import numpy as np
import pytest

from diffcloth.drape import (
    CUSICK,
    DrapeGeometry,
    SilhouetteError,
    align_rotation,
    align_scan_rotation,
    chamfer_distance,
    chamfer_polar,
    check_geometry,
    check_scan,
    check_silhouette,
    drape_coefficient_image,
    drape_features,
    iou_best_rotation,
    node_count,
    outline_radius_image,
    outline_spectrum,
    overlay_image,
    polar_shadow_image,
    read_drape_scan,
    read_silhouette,
    rotate_outline,
    shadow_image,
    write_silhouette,
)
from diffcloth.drape.images import OBSERVED_COLOUR, PEDESTAL_COLOUR, PREDICTED_COLOUR
from diffcloth.physics.mesh.builders import disc
from diffcloth.physics.mesh.measure import drape_coefficient, outline_radius

THETA = 2 * np.pi * np.arange(720) / 720
MM = 1e3 * 2 * CUSICK.specimen_radius / 256  # the default scale of a 256-pixel image


def analytic_dc(a, b, g=CUSICK):
    """DC of r = a + b cos(k theta + p): area pi (a^2 + b^2 / 2)."""
    ap = math.pi * g.pedestal_radius**2
    return (math.pi * (a * a + b * b / 2) - ap) / (math.pi * g.specimen_radius**2 - ap)


def random_drape(rng, dc=None, k=None):
    """A well-formed drape outline (720,): k nodes, slightly uneven in depth and spacing."""
    dc = rng.uniform(0.1, 0.95) if dc is None else dc
    k = int(rng.integers(3, 13)) if k is None else k
    area = math.pi * (0.09**2 + dc * (0.15**2 - 0.09**2))
    a0 = math.sqrt(area / math.pi)
    b = rng.uniform(0.3, 1.0) * max(min(a0 - 0.093, 0.148 - a0, 0.03), 0.0)
    ph, ps = rng.uniform(0, 2 * np.pi, 2)
    depth = 1 + rng.uniform(-0.2, 0.2) * np.cos(THETA - ps)
    rr = b * depth * np.cos(k * THETA + ph + rng.uniform(-0.15, 0.15) * np.sin(THETA + ps))
    a = -rr.mean() + math.sqrt(rr.mean() ** 2 - np.mean(rr**2) + area / math.pi)
    return a + rr, k


def write(tmp_path, name, img, quality=90):
    return str(write_silhouette(tmp_path / name, img, quality=quality))


def test_geometry_is_checked():
    assert check_geometry((0.15, 0.09)) == DrapeGeometry()
    with pytest.raises(ValueError, match="pedestal_radius must be finite and in"):
        check_geometry(DrapeGeometry(0.15, 0.2))
    with pytest.raises(ValueError, match="specimen_radius"):
        check_geometry((float("nan"), 0.09))


@pytest.mark.parametrize("k", range(3, 11))
def test_dc_and_node_count_of_analytic_outlines_through_jpeg(tmp_path, k):
    a, b = 0.118, 0.022
    r = lambda t: a + b * np.cos(k * t + 0.3 * k)
    path = write(tmp_path, f"k{k}.jpg", polar_shadow_image(r, CUSICK, seed=k), quality=85)
    sil = read_silhouette(path, CUSICK, mm_per_pixel=MM)
    assert abs(drape_coefficient_image(sil, CUSICK) - analytic_dc(a, b)) < 0.01
    r_img = outline_radius_image(sil, 360)
    assert np.abs(r_img - r(2 * np.pi * np.arange(360) / 360)).max() < 0.6 * MM / 1e3
    assert node_count(r_img) == k
    assert check_silhouette(sil, CUSICK) == []


def test_scale_from_the_specimen_and_frame(tmp_path):
    path = write(tmp_path, "d.png", polar_shadow_image(lambda t: 0.12 + 0 * t, size=200))
    sil = read_silhouette(path)
    assert sil.pixel == pytest.approx(0.3 / 200) and np.allclose(sil.center, 99.5)
    assert read_silhouette(path, frame_mm=330).pixel == pytest.approx(0.33 / 200)
    assert drape_coefficient_image(sil) == pytest.approx(analytic_dc(0.12, 0.0), abs=0.005)


def test_spectrum_is_rotation_invariant(tmp_path):
    spectra = []
    for i, rot in enumerate((0.0, 0.9, 2.5)):
        r = 0.12 + 0.015 * np.cos(6 * (THETA - rot)) + 0.005 * np.cos(2 * (THETA - rot) + 1)
        path = write(tmp_path, f"s{i}.jpg", polar_shadow_image(r, seed=i))
        spectra.append(outline_spectrum(outline_radius_image(read_silhouette(path), 360)))
    assert np.argmax(spectra[0]) == 5 and spectra[0][5] == pytest.approx(0.125, abs=0.01)
    assert np.abs(spectra[1] - spectra[0]).max() < 0.005
    assert np.abs(spectra[2] - spectra[0]).max() < 0.005


def uneven(t):
    return (
        0.118
        + 0.016 * np.cos(5 * t)
        + 0.006 * np.cos(2 * t + 0.4)
        + 0.004 * np.cos(7 * t + 1.1)
        + 0.003 * np.cos(3 * t + 2.0)
    )


@pytest.mark.parametrize("mirrored", [False, True])
def test_align_rotation_recovers_rotation_and_mirror(tmp_path, mirrored):
    alpha = 1.1
    other = (lambda t: uneven(alpha - t)) if mirrored else (lambda t: uneven(t - alpha))
    sa = read_silhouette(write(tmp_path, "a.jpg", polar_shadow_image(uneven, seed=1)))
    sb = read_silhouette(write(tmp_path, "b.jpg", polar_shadow_image(other, seed=2)))
    ra, rb = outline_radius_image(sa, 360), outline_radius_image(sb, 360)
    angle, mir, iou = align_rotation(ra, rb)
    want = alpha if mirrored else 2 * np.pi - alpha  # rotate_outline(rb, angle, mir) ~ ra
    assert mir == mirrored and iou > 0.98
    assert abs(np.angle(np.exp(1j * (angle - want)))) < math.radians(1.0)
    assert iou_best_rotation(sa, rb) == pytest.approx(iou, abs=0.01)
    assert chamfer_polar(ra, rotate_outline(rb, angle, mir)) < MM / 1e3
    if mirrored:  # without the mirror no rotation fits as well
        assert align_rotation(ra, rb, allow_mirror=False)[2] < iou - 0.01


def test_check_silhouette_silent_on_well_formed_drapes(tmp_path):
    rng = np.random.default_rng(0)
    for i in range(32):
        r, k = random_drape(rng)
        path = write(tmp_path, f"w{i}.jpg", polar_shadow_image(r, seed=i), quality=80 + i % 15)
        sil = read_silhouette(path, CUSICK, mm_per_pixel=MM)
        assert check_silhouette(sil, CUSICK) == [], (i, k)
        f = drape_features(sil, CUSICK)
        dc = (np.mean(r**2) - 0.09**2) / (0.15**2 - 0.09**2)
        assert abs(f["dc"] - dc) < 0.01 and f["node_count"] == k
        assert f["off_centre_mm"] < 2.0 and sil.warnings == ()


@pytest.mark.parametrize("factor", [1.5, 0.6])
def test_check_silhouette_flags_a_mis_scaled_image(tmp_path, factor):
    rng = np.random.default_rng(1)
    for i, dc in enumerate((0.3, 0.55, 0.8)):
        r, _ = random_drape(rng, dc=dc)
        path = write(tmp_path, f"m{i}.jpg", polar_shadow_image(r, seed=i))
        problems = check_silhouette(read_silhouette(path, mm_per_pixel=factor * MM))
        assert problems and all(p.startswith(path) for p in problems)
        assert any("mis-scaled" in p for p in problems), problems


def test_check_silhouette_flags_an_off_centre_image(tmp_path):
    rng = np.random.default_rng(2)
    for i, dc in enumerate((0.2, 0.5, 0.85)):
        r, _ = random_drape(rng, dc=dc)
        path = write(tmp_path, f"c{i}.jpg", polar_shadow_image(r, seed=i))
        for d in ((15, 0), (0, -15), (-10.6, 10.6)):
            sil = read_silhouette(path, center_px=(127.5 + d[0], 127.5 + d[1]))
            problems = check_silhouette(sil)
            assert any("off-centre" in p and p.startswith(path) for p in problems), problems
        # the shadow drawn off the image centre, read with the default centre
        img = polar_shadow_image(r, center_px=(140.5, 120.5), seed=i)
        path = write(tmp_path, f"c{i}-shifted.jpg", img)
        assert any("off-centre" in p for p in check_silhouette(read_silhouette(path)))


@pytest.mark.parametrize(
    "name, img, match",
    [
        ("white.png", np.full((64, 64), 230, np.uint8), "empty"),
        ("black.jpg", np.full((64, 64), 8, np.uint8), "all dark"),
        ("grey.png", np.full((64, 64), 128, np.uint8), "uniform"),
        ("tiny.png", np.tile(np.uint8([[30, 220]]), (20, 10)), "at least 32"),
    ],
)
def test_bad_images_raise_naming_the_file(tmp_path, name, img, match):
    noisy = np.clip(img + np.random.default_rng(0).normal(0, 2, img.shape), 0, 255)
    path = write(tmp_path, name, noisy.astype(np.uint8))
    with pytest.raises(SilhouetteError, match=match) as e:
        read_silhouette(path)
    assert path in str(e.value)


def test_unreadable_images_raise_naming_the_file(tmp_path):
    (tmp_path / "junk.png").write_text("not an image")
    for p in (tmp_path / "junk.png", tmp_path / "missing.jpg"):
        with pytest.raises(SilhouetteError, match="cannot read") as e:
            read_silhouette(p)
        assert str(p) in str(e.value)


def test_rgb_light_cloth_and_no_background(tmp_path):
    img = polar_shadow_image(lambda t: 0.12 + 0.01 * np.cos(5 * t))
    rgb = np.repeat(255 - img[..., None], 3, axis=2)
    path = write(tmp_path, "light.png", rgb)
    sil = read_silhouette(path, cloth="light")
    assert abs(drape_coefficient_image(sil) - analytic_dc(0.12, 0.01)) < 0.01
    assert read_silhouette(path).warnings  # read as dark cloth: the border is 'cloth'
    edge = np.full((64, 64), 30, np.uint8)
    edge[:1] = 220  # a sliver of background only
    with pytest.raises(SilhouetteError, match="all dark") as e:
        read_silhouette(write(tmp_path, "dark.png", edge))
    assert "dark.png" in str(e.value)
    speck = np.full((64, 64), 220, np.uint8)
    speck[30:32, 30:32] = 30  # a speck of cloth only
    with pytest.raises(SilhouetteError, match="empty"):
        read_silhouette(write(tmp_path, "speck.png", speck))


def draped(mesh, k=5, phase=0.3, lopsided=0.15):
    """A disc mesh hung over the pedestal: radial lines from the pedestal edge at a hang angle
    that varies with the angle (k folds)."""
    v = mesh.vertices
    rho, phi = np.hypot(v[:, 0], v[:, 2]), np.arctan2(v[:, 2], v[:, 0])
    s = np.maximum(rho - 0.09, 0.0)
    beta = 0.9 + 0.4 * np.cos(k * phi + phase) + lopsided * np.cos(phi)
    h = np.where(rho > 0.09, 0.09 + s * np.cos(beta), rho)
    return np.stack([h * np.cos(phi), -s * np.sin(beta), h * np.sin(phi)], axis=1)


def test_shadow_image_of_a_mesh_matches_the_mesh_measurements(tmp_path):
    mesh = disc(0.15, 0.02, rings_at=(0.09,))
    x = draped(mesh)
    path = write(tmp_path, "mesh.jpg", shadow_image(x, mesh.faces, CUSICK, size=256))
    sil = read_silhouette(path)
    dc = drape_coefficient(x, mesh.faces, 0.15, 0.09).value
    assert abs(drape_coefficient_image(sil) - dc) < 0.01
    r_mesh = outline_radius(x, mesh.faces, 360)
    r_img = outline_radius_image(sil, 360)
    angle, mirrored, iou = align_rotation(r_mesh, r_img)
    assert not mirrored and iou > 0.99 and min(angle, 2 * np.pi - angle) < math.radians(1)
    assert np.abs(r_img - r_mesh).max() < MM / 1e3
    assert check_silhouette(sil) == []
    # the mesh's centre drawn elsewhere: detected
    img = shadow_image(x, mesh.faces, CUSICK, center=(0.02, 0.0, 0.0))
    assert any(
        "off-centre" in p for p in check_silhouette(read_silhouette(write(tmp_path, "o.png", img)))
    )


def test_overlay_image_draws_the_outlines():
    img = polar_shadow_image(lambda t: 0.12 + 0.01 * np.cos(5 * t), noise=0)
    path = "mem.png"
    from diffcloth.drape import Silhouette

    sil = Silhouette(1 - (img.astype(float) - 35) / 190, MM / 1e3, np.array([127.5, 127.5]), path)
    out = overlay_image(sil, predicted_r_theta=np.full(360, 0.13))
    assert out.shape == (256, 256, 3) and out.dtype == np.uint8
    for colour in (OBSERVED_COLOUR, PREDICTED_COLOUR, PEDESTAL_COLOUR):
        assert np.all(out == colour, axis=-1).sum() > 100
    out2 = overlay_image(sil, predicted_coverage=sil.coverage)
    assert np.all(out2 == PREDICTED_COLOUR, axis=-1).sum() > 100


@pytest.fixture(scope="module")
def scan():
    mesh = disc(0.15, 0.008, rings_at=(0.09,))
    return draped(mesh, k=6, phase=0.0), mesh.faces


def rotation(axis, deg):
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    a = math.radians(deg)
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


def test_check_scan(scan):
    x, _ = scan
    assert check_scan(x, CUSICK, source="ok.obj") == []
    (cm,) = check_scan(x * 100, CUSICK, source="cm.obj")
    assert "cm.obj" in cm and "looks like cm" in cm and "0.01" in cm
    assert "looks like mm" in check_scan(x * 1000)[0]
    tilted = check_scan(x @ rotation((1, 0, 0), 15).T, CUSICK, source="t.obj")
    assert any("rotated" in p and "tilted 15.0 deg" in p for p in tilted), tilted
    flipped = check_scan(x @ rotation((0, 0, 1), 180).T)
    assert any("upside down" in p for p in flipped), flipped
    assert check_scan(x @ rotation((0, 1, 0), 40).T) == []  # about up: any fold orientation
    off = check_scan(x + [0.02, 0.0, 0.0], CUSICK, source="off.obj")
    assert len(off) == 1 and "off-centre" in off[0] and "20.0 mm" in off[0]
    # a z-up scan read with up = z is fine
    assert check_scan(x @ rotation((1, 0, 0), 90).T, up=(0, 0, 1)) == []


def test_read_drape_scan_flags_units_from_an_obj(tmp_path, scan):
    x, faces = scan
    path = tmp_path / "scan_cm.obj"
    lines = [f"v {a:.6f} {b:.6f} {c:.6f}" for a, b, c in x * 100]
    lines += [f"f {a} {b} {c}" for a, b, c in faces + 1]
    path.write_text("\n".join(lines) + "\n")
    points, warnings = read_drape_scan(path)
    assert points.shape == x.shape and len(warnings) == 1
    assert str(path) in warnings[0] and "scale by 0.01" in warnings[0]


def test_align_scan_rotation_recovers_a_rotation(scan):
    x, _ = scan
    sim = draped(disc(0.15, 0.008, rings_at=(0.09,)), k=5, phase=0.4, lopsided=0.3)
    turned = sim @ rotation((0, 1, 0), 37).T
    assert chamfer_distance(turned, sim) > 2e-3
    angle, dist, rotated = align_scan_rotation(turned, sim)
    assert abs(math.degrees(angle) - 323) < 0.5 and dist < 1e-4
    assert np.allclose(rotated, sim, atol=1e-3)
