"""plenopiv.piv.uncertainty: the chain's measured response and how it completes the correlation
statistics (the whole-chain coverage is in test_vortex_validation.py and
docs/validation/uncertainty.md)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from plenopiv.piv import PIVSettings, VectorField
from plenopiv.piv.uncertainty import (
    MIN_GAIN,
    Response,
    cached_response,
    combine,
    response_key,
    unresolved_gradient_bias,
)


def _response(gain_w=0.5, random_w=2e-5, statistics_w=0.0):
    z = np.array([-1e-3, 0.0, 1e-3])
    shifts = np.array([[1e-4, 1e-4, 5e-5], [2e-4, 2e-4, 1e-4]])
    gain = np.ones((2, 3, 3))
    gain[:, 2, :] = gain_w
    random = np.zeros((2, 3, 3))
    random[:, 2, :] = random_w
    statistics = np.zeros((2, 3, 3))
    statistics[:, 2, :] = statistics_w
    return Response(z, shifts, gain, random, statistics, 100)


def _field(w=1e-4, sigma=1e-5):
    shape = (3, 2, 2)
    ones = np.ones(shape)
    return VectorField(x=np.arange(2) * 1e-3, y=np.arange(2) * 1e-3,
                       z=np.array([-1e-3, 0.0, 1e-3]), u=ones * 2e-4, v=ones * 0.0,
                       w=ones * w, valid=np.ones(shape, bool), snr=ones * 3,
                       correlation=ones * 0.8, u_uncertainty=ones * sigma,
                       v_uncertainty=ones * sigma, w_uncertainty=ones * sigma)


def test_combine_adds_the_response_in_quadrature():
    f = combine(_field(w=1e-4, sigma=1e-5), _response(gain_w=0.5, random_w=2e-5))
    # w measured with gain 0.5: its true value is twice it, the error as large as the value
    expected = np.sqrt(1e-5**2 + 2e-5**2 + 1e-4**2)
    np.testing.assert_allclose(f.w_uncertainty, expected)
    # gain 1 and no random error: u and v keep the correlation statistics
    np.testing.assert_allclose(f.u_uncertainty, 1e-5)
    np.testing.assert_allclose(f.v_uncertainty, 1e-5)
    assert set(f.uncertainty_parts) >= {"response_random", "response_gain"}
    assert combine(_field(), None).w_uncertainty[0, 0, 0] == 1e-5


def test_the_test_vectors_random_error_is_not_counted_twice():
    """The test vectors' spread r holds their own statistics s: with gain 1, a vector whose
    statistics equal the test vectors' gets sqrt(s^2 + (r^2 - s^2)) = r, the rms error the
    response tests measured, not sqrt(s^2 + r^2)."""
    s, r = 1.2e-5, 2e-5
    f = combine(_field(w=1e-4, sigma=s), _response(gain_w=1.0, random_w=r, statistics_w=s))
    np.testing.assert_allclose(f.w_uncertainty, r)
    assert np.all(f.w_uncertainty < np.hypot(s, r))
    # statistics larger than the spread: nothing is added to them
    f = combine(_field(w=1e-4, sigma=3e-5), _response(gain_w=1.0, random_w=r, statistics_w=s * 3))
    np.testing.assert_allclose(f.w_uncertainty, 3e-5)
    np.testing.assert_allclose(f.uncertainty_parts["response_random"][2], 0.0)


def _grid_field(u, spacing_m, window_vox=(8, 8, 8)):
    """A field of displacement ``u`` (nz, ny, nx) on a grid of ``spacing_m`` (x, y, z) from
    windows of ``window_vox`` at 50 % overlap (the voxel is spacing / (window / 2))."""
    nz, ny, nx = u.shape
    ones = np.ones(u.shape)
    return VectorField(x=np.arange(nx) * spacing_m[0], y=np.arange(ny) * spacing_m[1],
                       z=np.arange(nz) * spacing_m[2], u=u, v=ones * 0.0, w=ones * 0.0,
                       valid=np.ones(u.shape, bool), snr=ones * 3, correlation=ones * 0.8,
                       settings=PIVSettings(windows=(window_vox,), overlap=0.5, passes=1),
                       u_uncertainty=ones * 0.0, v_uncertainty=ones * 0.0,
                       w_uncertainty=ones * 0.0)


def test_gradient_term_vanishes_for_uniform_and_linear_fields():
    h = (1e-3, 2e-3, 3e-3)
    z, y, x = np.meshgrid(np.arange(4) * h[2], np.arange(5) * h[1], np.arange(6) * h[0],
                          indexing="ij")
    for u in (np.full(x.shape, 2e-4), 1e-4 + 0.01 * x - 0.02 * y + 0.03 * z):
        disp = np.stack([u, u, u])
        np.testing.assert_allclose(unresolved_gradient_bias(disp, h, (2e-3, 4e-3, 6e-3)), 0.0,
                                   atol=1e-18)


def test_gradient_term_is_the_window_average_bias_of_a_quadratic_field():
    """u = a x^2 + b y^2 + c z^2: a top-hat window of edge W averages it to
    u(centre) + sum_i W_i^2/24 * d2u/dx_i^2 = u + (a Wx^2 + b Wy^2 + c Wz^2) / 12."""
    h = np.array([1e-3, 1.5e-3, 2e-3])            # vector spacing (x, y, z), metres
    window = 2 * h                                # 50 % overlap
    a, b, c = 40.0, -10.0, 5.0                    # 1/m
    z, y, x = np.meshgrid(np.arange(5) * h[2], np.arange(6) * h[1], np.arange(7) * h[0],
                          indexing="ij")
    u = a * x**2 + b * y**2 + c * z**2
    expected = abs(a * window[0] ** 2 + b * window[1] ** 2 + c * window[2] ** 2) / 12
    # the top-hat window average of the quadratic about a centre at 0 (midpoint quadrature)
    t = (np.arange(2000) + 0.5) / 2000 - 0.5
    avg = sum(k * np.mean((t * wk) ** 2) for k, wk in zip((a, b, c), window, strict=True))
    np.testing.assert_allclose(abs(avg), expected, rtol=1e-6)
    bias = unresolved_gradient_bias(np.stack([u, 0 * u, 0 * u]), h, window)
    np.testing.assert_allclose(bias[0], expected, rtol=1e-9)
    np.testing.assert_allclose(bias[1:], 0.0)
    # through combine: the window from the settings, the spacing from the grid
    f = combine(_grid_field(u, h), _response(gain_w=1.0, random_w=0.0))
    np.testing.assert_allclose(f.uncertainty_parts["unresolved_gradient"][0], expected,
                               rtol=1e-9)
    np.testing.assert_allclose(f.u_uncertainty, expected, rtol=1e-9)


def test_a_vector_the_chain_barely_sees_is_bounded():
    f = combine(_field(w=1e-4, sigma=0.0), _response(gain_w=0.0, random_w=0.0))
    np.testing.assert_allclose(f.w_uncertainty, (1 - MIN_GAIN) / MIN_GAIN * 1e-4)


def test_response_interpolates_between_layers():
    r = _response()
    r = Response(r.z, r.shifts, r.gain.copy(), r.random, r.statistics, 100)
    r.gain[:, 2, :] = [0.2, 0.6, 1.0]
    gain, _ = r.at([-0.5e-3, 0.5e-3, 2e-3])
    np.testing.assert_allclose(gain[2], [0.4, 0.8, 1.0])


def test_response_cache_round_trip_and_key(tmp_path):
    path = tmp_path / "response.json"
    calls = []

    def compute():
        calls.append(1)
        return _response()

    key = response_key("weights", [1, 2], {"a": 1})
    first, cached = cached_response(path, key, compute)
    assert not cached and path.exists()
    again, cached = cached_response(path, key, compute)
    assert cached and len(calls) == 1
    np.testing.assert_array_equal(again.gain, first.gain)
    _, cached = cached_response(path, response_key("another grid"), compute)
    assert not cached and len(calls) == 2
    path.write_text("{broken")
    _, cached = cached_response(path, key, compute)
    assert not cached and json.loads(path.read_text())["key"] == key
    assert cached_response(None, key, lambda: None) == (None, False)


@pytest.mark.parametrize("bad", [{"version": 0}, {}])
def test_response_from_another_version_is_rejected(bad):
    with pytest.raises(ValueError, match="version"):
        Response.from_dict(bad)


def test_curvature_already_in_the_last_correction_is_not_added_again():
    """The last correction (in sigma_CS) of a smoothed-predictor pass estimates the same
    curvature: only the window-average bias in excess of it is added."""
    h = np.array([1e-3, 1e-3, 1e-3])
    z, y, x = np.meshgrid(np.arange(4) * h[2], np.arange(5) * h[1], np.arange(6) * h[0],
                          indexing="ij")
    u = 50.0 * x**2
    bias = 50.0 * (2 * h[0]) ** 2 / 12           # (W^2 / 24) * 2a with W = 2h
    base = _grid_field(u, h)
    for last, added in ((0.0, bias), (0.6 * bias, 0.8 * bias), (2 * bias, 0.0)):
        parts = {"last_correction": np.stack([np.full(u.shape, last), 0 * u, 0 * u]),
                 "correlation": np.zeros((3,) + u.shape)}
        f = combine(replace(base, u_uncertainty=np.full(u.shape, last),
                            uncertainty_parts=parts), _response(gain_w=1.0, random_w=0.0))
        np.testing.assert_allclose(f.uncertainty_parts["unresolved_gradient"][0], added,
                                   rtol=1e-9, atol=1e-15)
        # the total is the larger of the two estimates, never their quadrature sum
        np.testing.assert_allclose(f.u_uncertainty, max(last, bias), rtol=1e-9)
