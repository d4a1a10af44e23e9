"""Optics: ray transfer matrices, thin-lens and effective distances, focal spots, uncertainty."""

from __future__ import annotations

import numpy as np
import pytest

from plenopiv.camera import optics as O


def test_abcd_plate_is_air_of_thickness_t_over_n():
    # main lens -> l3 of air -> plate (t, n): a ray from the axis at angle θ reaches
    # x = (l3 + t/n) θ, the effective distance of Eq. 4.4 (Appendix B, Eq. B.2)
    l3, t, n = 95.68e-3, 6.3e-3, 1.46
    m = O.system_matrix(O.propagation(l3), O.flat_interface(1.0, n), O.propagation(t))
    assert m[0, 1] == pytest.approx(O.effective_image_distance(l3, t, n))
    assert m[1, 1] == pytest.approx(1 / n)
    assert O.effective_image_distance(l3, t, n) == pytest.approx(0.1, abs=5e-6)


def test_abcd_thin_lens_imaging_conjugates():
    f, so = 0.135, 0.4
    si = O.conjugate_distance(f, so)
    m = O.system_matrix(O.propagation(so), O.thin_lens(f), O.propagation(si))
    assert m[0, 1] == pytest.approx(0.0, abs=1e-15)            # every ray from a point meets
    assert m[0, 0] == pytest.approx(O.magnification(si, so))   # at height M·h


def test_thin_lens_relations_3_1_to_3_4():
    f = 0.135
    for si in (0.145, 0.2, 0.27, 0.405):
        so = O.conjugate_distance(f, si)
        m = O.magnification(si, so)
        assert O.image_distance_from_magnification(f, m) == pytest.approx(si)
        assert O.object_distance_from_magnification(f, m) == pytest.approx(so)
    assert O.magnification(0.1, 0.1) == -1.0


def test_effective_object_distance_reproduces_thesis_5_1():
    l2 = O.physical_interface_distance(0.1, 0.04, 1.33)
    assert round(l2 * 1e3, 2) == 69.92
    assert O.effective_object_distance(l2, 0.04, 1.33) == pytest.approx(0.1)


def test_focal_spot_scale_models_and_inverse():
    fb = 500e-6
    for si in (0.145, 0.2, 0.405):
        # no plate: both back-side models are Eq. 3.11
        assert O.focal_spot_scale(si, fb) == pytest.approx(1 + fb / si)
        assert O.focal_spot_scale(si, fb, back_side="thesis") == pytest.approx(1 + fb / si)
        for bs in ("physical", "thesis"):
            k = O.focal_spot_scale(si, fb, back_side=bs, thickness=10.4e-3,
                                   refractive_index=1.517, pupil_offset=3e-3)
            back = O.image_distance_from_spot_scale(k, fb, back_side=bs, thickness=10.4e-3,
                                                    refractive_index=1.517, pupil_offset=3e-3)
            assert back == pytest.approx(si, rel=1e-12)
    # Eq. 4.8 with l3 from Eq. 4.4
    si, t, n = 0.2, 10.4e-3, 1.517
    l3 = si - t / n
    assert O.focal_spot_scale(si, fb, back_side="thesis", thickness=t, refractive_index=n) \
        == pytest.approx(1 + fb / (n * l3 + t))


def test_exact_chief_ray_tends_to_paraxial_near_axis():
    d = np.array([[1e-6, 0.0], [0.0, -2e-6]])
    for bs in ("physical", "thesis"):
        exact = O.focal_spot_exact(d, 0.2, 500e-6, back_side=bs, thickness=10.4e-3,
                                   refractive_index=1.517)
        scale = O.focal_spot_scale(0.2, 500e-6, back_side=bs, thickness=10.4e-3,
                                   refractive_index=1.517)
        assert np.allclose(exact, d * scale, rtol=1e-9)


def test_exact_chief_ray_solves_snell():
    rho, air, t, n = np.array([0.02]), 0.15, 0.0104, 1.517
    m = O.chief_ray_tangent(rho, air, t, n)
    theta = np.arctan(m)
    theta_g = np.arcsin(np.sin(theta) / n)
    assert air * np.tan(theta) + t * np.tan(theta_g) == pytest.approx(rho, rel=1e-13)


def test_magnification_method_uncertainty_matches_fig_3_5():
    # 135 mm at f/5.6: ΔS_i = M²(L1 + L2) ≈ 1.04 % of S_i at every S_i (thesis Fig. 3.5)
    for si in (0.15, 0.2, 0.3, 0.4):
        frac = O.magnification_method_uncertainty(0.135, 5.6, si, 125e-6) / si
        assert frac == pytest.approx(0.0104, abs=0.0002)


def test_height_error_worked_example_eq_3_10():
    # a 1 cm span, an image height off by one 125 µm lenslet, 135 mm lens -> 1.69 mm
    assert O.height_error_sensitivity(0.135, 0.01) * 125e-6 == pytest.approx(1.69e-3, abs=5e-6)


def test_depth_of_focus_requires_c_smaller_than_aperture():
    with pytest.raises(O.ConfigError, match="circle of confusion"):
        O.depth_of_focus(0.05, 1000.0, -0.01, 125e-6, 5.0)
