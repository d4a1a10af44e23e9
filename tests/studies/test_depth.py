"""Thesis §5.1-5.2 depth study, reduced: three or four depths per case instead of 21.

The full study (``pipelines/validate_depth.py``) fits 21 depths; here four symmetric depths,
Z = ±6 and ±10 mm, away from the ~4 mm (effective) around the focal plane where single depths
scatter most (up to ~0.5 mm, 4 voxels, in the full study: the blur spot there spans only a few
lenslet footprints). At these depths single particles are off by ≲ 0.12 mm (window, physical
back side) and ≲ 0.25 mm (thesis back side, whose effective depths reach ±15 mm), so a fitted
slope is uncertain by at most Σ|Z| e / Σ Z² = 32 mm · e / 272 mm²: ≈ 0.014 and ≈ 0.03,
typically a third of that. The grids keep 1 mm (8 voxels) beyond the expected depths instead
of the study's 2 mm, and the soft-mask diagnostic is off, to stay well under a minute.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.studies.depth import (
    corrected_depths,
    exact_thesis_inverse,
    expected_effective_depth,
    focus_crossing_depth,
    focus_region,
    image_distance_of,
    linear_fit,
    measure_depths,
    micro_image_f_number,
    study_cases,
)
from plenopiv.camera.corrections import DepthCorrection
from plenopiv.synthetic.images import particle_image

pytestmark = pytest.mark.study

DEPTHS = np.array([-10.0, -6.0, 6.0, 10.0]) * 1e-3
N_PLATE = 1.46


@pytest.fixture(scope="module")
def cases():
    return {c.name: c for c in study_cases(diagnostics=False)}


def slopes(case, depths=DEPTHS):
    """Fitted slope of reconstructed against true depth for each of the case's corrections."""
    m = measure_depths(case, depths, margin=1e-3, mask_diagnostic=False)
    assert not m["errors"], m["errors"]
    assert (m["n_particles"] >= 1).all()
    assert np.nanmax(m["lateral_vox"]) <= 0.25          # on-axis particle stays on the axis
    return {name: linear_fit(m["depth_m"], z)["slope"]
            for name, z in corrected_depths(case, m).items()}, m


# ---- geometry (no reconstruction) ----------------------------------------------------------


def test_thesis_geometry(cases):
    """§5.1's distances: l2 = 69.92 mm (Eq. 4.3), l3 = 95.68 mm (Eq. 4.4 with t/n)."""
    assert cases["external"].camera.interface_distance == pytest.approx(69.925e-3, abs=1e-5)
    assert cases["plate_thesis"].camera.l3 == pytest.approx(95.685e-3, abs=1e-5)
    assert cases["none"].camera.magnification == pytest.approx(-1.0)


def test_focus_crosses_the_plate_at_z_star(cases):
    """The image of Z* converges on the plate's front face; beyond it, in front of the plate."""
    cam = cases["plate_thesis"].camera
    zs = focus_crossing_depth(cam)
    assert zs == pytest.approx(4.7226e-3, abs=1e-7)
    assert image_distance_of(cam, zs) == pytest.approx(cam.l3, rel=1e-12)
    assert image_distance_of(cam, 0.0) == pytest.approx(cam.image_distance, rel=1e-12)
    assert focus_region(cam, [-1e-3, 2e-3, 6e-3]).tolist() == [
        "behind the lenslets", "inside the plate", "in front of the plate"]


def test_expected_depth_models(cases):
    """Eq. 4.7 for the window; Z' = n S_o Z/(S_o - (n-1) Z) for the thesis back side, whose
    slope at the focal plane is n and whose exact inverse returns Z."""
    z = np.linspace(-10e-3, 10e-3, 9)
    ext = expected_effective_depth(cases["external"].camera, z)
    np.testing.assert_allclose(ext, z / 1.33, rtol=1e-12)
    thes = cases["plate_thesis"].camera
    zp = expected_effective_depth(thes, z)
    np.testing.assert_allclose(exact_thesis_inverse(thes, zp), z, atol=1e-15)
    h = 1e-7
    slope0 = (expected_effective_depth(thes, h) - expected_effective_depth(thes, -h)) / (2 * h)
    assert slope0 == pytest.approx(N_PLATE, rel=1e-6)
    np.testing.assert_allclose(expected_effective_depth(cases["plate_physical"].camera, z), z)


def test_corrections_each_back_side_gets(cases):
    """auto: 1/n for the thesis back side only; Eq. 4.7 (n1/n2) for the window."""
    assert DepthCorrection.for_camera(cases["plate_thesis"].camera).scale == pytest.approx(
        1 / N_PLATE)
    assert DepthCorrection.for_camera(cases["plate_physical"].camera).scale == 1.0
    assert DepthCorrection.for_camera(cases["external"].camera).scale == pytest.approx(1.33)


def test_thesis_back_side_micro_images_are_n_times_smaller(cases):
    """A particle on the focal plane lights one micro-image, a uniform disc of radius
    R f̄/S_i,eff ("physical") or R f̄/(n S_i,eff) ("thesis", in-glass angle): the rms radii
    differ by n (within 3 %: pixel sampling and the tracer's bilinear splat add ~1/3 px² to the
    squared rms radius, 1-2 % on the ratio). This is why the study gives the "thesis" case a
    light-field aperture of n N (:func:`micro_image_f_number`)."""
    radii = {}
    for name in ("plate_physical", "plate_thesis"):
        cam = cases[name].camera
        img = particle_image(cam, [(0.0, 0.0, 0.0)], rays_per_particle=20000)
        r, c = np.indices(img.shape)
        w = img / img.sum()
        rc, cc = (w * r).sum(), (w * c).sum()
        radii[name] = np.sqrt((w * ((r - rc) ** 2 + (c - cc) ** 2)).sum())
    assert radii["plate_physical"] / radii["plate_thesis"] == pytest.approx(N_PLATE, rel=0.03)
    assert micro_image_f_number(cases["plate_thesis"].camera) == pytest.approx(2.2 * N_PLATE)
    assert micro_image_f_number(cases["plate_physical"].camera) == pytest.approx(2.2)


# ---- reconstruction ------------------------------------------------------------------------


def test_external_interface_slopes(cases):
    """Water, l1 = 40 mm (thesis Table 5.1: 0.7563 uncorrected, 1.0059 corrected): the effective
    depth is compressed by n2/n1 exactly (paraxial, Eq. 4.7), so the uncorrected slope is
    1/1.33 ± 0.02 and the corrected one 1.00 ± 0.014 (the bound of the module docstring for
    single-depth errors ≲ 0.12 mm)."""
    s, _ = slopes(cases["external"])
    assert s["uncorrected"] == pytest.approx(1 / 1.33, abs=0.02)
    assert s["corrected"] == pytest.approx(1.0, abs=0.014)


def test_plate_thesis_back_side_slopes(cases):
    """Thesis back side (thesis Table 5.1: 1.4265 uncorrected, 0.9770 corrected): u is n times
    too small, the depth n times too large. Uncorrected slope n ± 0.03: the exact mapping
    Z' = n S_o Z/(S_o - (n-1) Z) adds +0.003 to the slope at these depths (its cubic term)
    and the particles' depth errors up to ±0.03 (module docstring); 0.03 is 2 % of n and
    still 15 times smaller than n - 1. After the 1/n of Eq. 5.1: 1.00 ± 0.02 (0.03/n, plus
    the curvature)."""
    s, _ = slopes(cases["plate_thesis"])
    assert s["uncorrected"] == pytest.approx(N_PLATE, abs=0.03)
    assert s["corrected (1/n)"] == pytest.approx(1.0, abs=0.02)


def test_plate_thesis_back_side_follows_the_projective_model(cases):
    """The reconstruction follows the projective model (sharp, at Z'), not only its slope:
    every effective depth within 0.3 mm (half a depth cell) of Z' = n S_o Z/(S_o - (n-1) Z).
    On this grid (voxel corners on the axis) the volume's centroids at Z = ±6 mm lay one depth
    cell towards focus (-7.98 / +8.46 mm against -8.53 / +9.01 mm) while the grid moved by half
    a voxel erred by 0.09 mm: the positions from the light field do not depend on the grid."""
    _, m = slopes(cases["plate_thesis"])
    np.testing.assert_allclose(m["effective_m"], m["expected_effective_m"], atol=0.3e-3)


def test_plate_physical_back_side_needs_no_correction(cases):
    """Physical back side: S_i,eff covers the plate and the light field is exact; slope
    1.00 ± 0.01 without correction, so the 1/n of Eq. 5.1 would be wrong here (1/n ± 0.01).
    Three depths (-10, 0, +10 mm): the slope is (e(10) - e(-10))/20 mm off by ≲ 0.01."""
    s, _ = slopes(cases["plate_physical"], np.array([-10.0, 0.0, 10.0]) * 1e-3)
    assert s["uncorrected"] == pytest.approx(1.0, abs=0.01)
    assert s["corrected (1/n)"] == pytest.approx(1 / N_PLATE, abs=0.01)
