"""The light field (pixel -> ray through the lens and the lenslets), checked against the ray
tracer."""

from __future__ import annotations

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.conventions import pixel_to_sensor
from plenopiv.lightfield import _kernels as LK
from plenopiv.lightfield import light_field
from plenopiv.synthetic import _kernels as TK
from plenopiv.synthetic.tracer import geometry_vector


@pytest.fixture(scope="module")
def lf(small_camera):
    return light_field(Calibration.from_camera(small_camera))


def test_lit_fraction_kernel_matches_numpy(rng):
    ux, uy = rng.uniform(-1, 1, (2, 5000))
    for got, want in zip(LK.lit_fraction(ux, uy, 0.1, 0.8, 8),
                         LK.lit_fraction_numpy(ux, uy, 0.1, 0.8, 8), strict=True):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)


def test_pixel_rays_retrace_to_their_pixels(small_camera, lf):
    """The ray of each pixel (through u on the lens and s on the lenslets), traced forward by
    the simulator, lands on that pixel's centre."""
    g = geometry_vector(small_camera)
    rng = np.random.default_rng(3)
    # fully lit pixels (a pixel cut by the aperture edge aims at its lit part instead)
    pick = rng.choice(np.flatnonzero(lf.lit == 1.0), 3000, replace=False)
    u, s = lf.u[pick], lf.s[pick]
    m = (s - u) / small_camera.mla_z
    k, sx, sy = TK.trace_image_rays(u[:, 0].copy(), u[:, 1].copy(), np.zeros(len(pick)),
                                    m[:, 0].copy(), m[:, 1].copy(), g)
    assert np.all(k == lf.lenslet[pick])
    rows, cols = np.divmod(lf.pixel[pick], small_camera.sensor.cols)
    centre = pixel_to_sensor(np.stack([rows, cols], 1), small_camera.sensor.shape,
                             small_camera.sensor.pixel_pitch)
    assert np.abs(np.stack([sx, sy], 1) - centre).max() < 1e-6 * small_camera.sensor.pixel_pitch


def test_light_field_geometry(lf, small_camera):
    assert lf.lit.min() >= 0.5 and lf.lit.max() == 1.0
    assert np.hypot(*lf.u.T).max() <= lf.aperture_radius + lf.cell
    assert np.allclose(lf.position_at_depth(0.0), lf.focal_plane_position)
    assert np.allclose(lf.position_at_depth(-lf.object_distance), lf.u)
    assert lf.footprint == pytest.approx(125e-6 / abs(small_camera.magnification))
    assert len(np.unique(lf.pixel)) == lf.n_rays
