"""plenopiv.piv.uncertainty: the chain's measured response and how it completes the correlation
statistics (the whole-chain coverage is in test_vortex_validation.py and
docs/validation/uncertainty.md)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from plenopiv.piv import PIVSettings, VectorField
from plenopiv.piv.response import Response, response_shifts
from plenopiv.piv.uncertainty import (
    DEFAULT_RATIO,
    MAX_CONVERGENCE_RATIO,
    MIN_GAIN,
    REJECTED_RANGE_FACTOR,
    combine,
    convergence_ratio,
    curvature_noise_factor,
    filter_offset,
    iteration_uncertainty,
    location_uncertainty,
    rejected_neighbour_uncertainty,
    unresolved_gradient_bias,
)
from plenopiv.products.caches import cached_response, response_key
from plenopiv.workflow.response import placement_offset


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


def test_the_gain_error_is_the_rms_over_the_test_pairs_not_the_error_at_their_mean_gain():
    """Two test pairs measure w at gains 0.5 and 2 (mean 1.25): a displacement measured at
    those gains errs by 1 and 1/2 of the measured value, rms sqrt(5/8), where the mean gain
    would give 1/5; gains straddling 1 closely (0.8, 1.25, mean 1.025) still give their rms,
    not 0.024. One pair, or pairs of equal gain, give |1 - g| / g; a component no pair moves
    along, or a gain of 1, none; a gain below min_gain is held there."""
    z = np.array([-1e-3, 0.0, 1e-3])
    shifts = np.array([[1e-4, 0.0, 5e-5], [0.0, 0.0, 1e-4]])
    gain = np.full((2, 3, 3), np.nan)
    gain[0, 0] = 1.0                                  # only the first pair moves along x
    gain[:, 2] = np.array([0.5, 2.0])[:, None]
    resp = Response(z, shifts, gain, np.zeros((2, 3, 3)), np.zeros((2, 3, 3)), 100)
    err = resp.gain_error(z)
    np.testing.assert_allclose(err[2], np.sqrt(5 / 8))
    np.testing.assert_allclose(err[:2], 0.0)          # u at gain 1, v never moved
    gain[:, 2] = np.array([0.8, 1.25])[:, None]
    np.testing.assert_allclose(replace(resp, gain=gain).gain_error(z)[2],
                               np.sqrt((0.25**2 + 0.2**2) / 2))
    gain[:, 2] = 0.5
    np.testing.assert_allclose(replace(resp, gain=gain).gain_error(z)[2], 1.0)
    gain[:, 2] = 0.01                                 # held at min_gain 0.1: (1 - 0.1) / 0.1
    np.testing.assert_allclose(replace(resp, gain=gain).gain_error(z, 0.1)[2], 9.0)
    # through combine: the term is that error times the measured displacement
    gain[:, 2] = np.array([0.5, 2.0])[:, None]
    out = combine(_field(w=1e-4, sigma=0.0), replace(resp, gain=gain))
    np.testing.assert_allclose(out.uncertainty_parts["response_gain"][2], np.sqrt(5 / 8) * 1e-4)


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


def _iterated_field(u, spacing_m, last, previous, correlation=0.0):
    """``_grid_field`` with the signed corrections of its last two passes (u only, metres)."""
    zero = np.zeros(u.shape)
    parts = {"correlation": np.stack([np.full(u.shape, correlation), zero, zero]),
             "last_correction": np.stack([np.abs(last), zero, zero]),
             "last_corrector": np.stack([last, zero, zero])}
    if previous is not None:
        parts["previous_corrector"] = np.stack([previous, zero, zero])
    f = _grid_field(u, spacing_m)
    return replace(f, settings=PIVSettings(windows=((8, 8, 8),), overlap=0.5, passes=3),
                   uncertainty_parts=parts)


def _linear(h=(1e-3, 1e-3, 1e-3)):
    z, y, x = np.meshgrid(np.arange(4) * h[2], np.arange(5) * h[1], np.arange(6) * h[0],
                          indexing="ij")
    return 1e-4 + 0.01 * x - 0.02 * y + 0.03 * z, x, h


@pytest.mark.parametrize("ratio", [0.25, 0.5, 0.8])
def test_the_remaining_error_is_the_geometric_tail_of_the_corrections(ratio):
    """Passes that each leave a fraction rho of the error change the estimate by
    c_n = rho c_(n-1); what the last left is the tail rho c_n + rho^2 c_n + ... =
    rho / (1 - rho) c_n. Each correction also holds the correlation's random error cs in
    quadrature (|c|^2 = systematic^2 + cs^2): the ratio and the tail are those of the
    systematic parts. A linear field has no filter offset."""
    u, x, h = _linear()
    systematic = 2e-6 * (1 + x / x.max())             # a correction varying over the field
    cs = 1e-6
    last = np.hypot(systematic, cs)
    previous = np.hypot(systematic / ratio, cs)
    f = _iterated_field(u, h, last, previous, correlation=cs)
    sigma = iteration_uncertainty(f)
    tail = ratio / (1 - ratio) * systematic
    np.testing.assert_allclose(sigma[0], np.hypot(cs, tail), rtol=1e-9)
    np.testing.assert_allclose(sigma[1:], 0.0)
    np.testing.assert_allclose(combine(f, _response(gain_w=1.0, random_w=0.0)).u_uncertainty,
                               np.hypot(cs, tail), rtol=1e-9)


def test_corrections_at_the_noise_of_the_correlation_leave_nothing_to_the_iteration():
    """Converged passes still change each vector by the random error of their correlation,
    which does not shrink from pass to pass: the last two corrections are as large and
    their raw ratio is 1, a tail of 9 times them at the cap. Their noise removed, nothing
    is left: the uncertainty is the correlation statistics."""
    u, x, h = _linear()
    cs = 1e-6
    sign = np.where(np.indices(u.shape).sum(axis=0) % 2 == 0, 1.0, -1.0)
    last, previous = 0.8 * cs * sign, -0.9 * cs * sign
    f = _iterated_field(u, h, last, previous, correlation=cs)
    np.testing.assert_allclose(iteration_uncertainty(f)[0], cs, rtol=1e-12)
    rho = convergence_ratio(np.stack([last] * 3), np.stack([previous] * 3),
                            np.ones(u.shape, bool), np.full((3,) + u.shape, cs))
    np.testing.assert_allclose(rho, 0.0)
    # counted without their noise, the same corrections would give ratio 0.8 / 0.9
    np.testing.assert_allclose(
        convergence_ratio(np.stack([last] * 3), np.stack([previous] * 3),
                          np.ones(u.shape, bool)), 0.8 / 0.9)


def test_the_convergence_ratio_is_bounded_and_defaults_to_one_half():
    u, x, h = _linear()
    last = np.full(u.shape, 2e-6)
    # no convergence (the correction grew): held at MAX_CONVERGENCE_RATIO
    f = _iterated_field(u, h, last, last / 3.0)
    np.testing.assert_allclose(
        iteration_uncertainty(f)[0],
        MAX_CONVERGENCE_RATIO / (1 - MAX_CONVERGENCE_RATIO) * 2e-6, rtol=1e-9)
    # the previous pass had other windows: rho = 1/2, the remaining error = the last correction
    assert DEFAULT_RATIO == 0.5
    np.testing.assert_allclose(iteration_uncertainty(_iterated_field(u, h, last, None))[0],
                               2e-6, rtol=1e-9)
    ratio = convergence_ratio(np.stack([last] * 3), np.stack([last * 4] * 3),
                              np.ones(u.shape, bool))
    np.testing.assert_allclose(ratio, 0.25)
    # a field without signed corrections keeps its own uncertainty
    assert iteration_uncertainty(_grid_field(u, h)) is None


def test_the_smoothed_predictor_s_offset_is_not_an_iteration_error():
    """At the fixed point of passes with the [1, 2, 1]/4 predictor the corrector is still
    d - S(d) = -a h^2 / 2 for u = a x^2 (inside the grid), the same every pass: the estimate
    no longer changes, so nothing is left to the iteration, and the curvature is counted
    once, by the window-average bias (W^2/24) d2u/dx2 = a W^2 / 12."""
    h = np.array([1e-3, 1e-3, 1e-3])
    z, y, x = np.meshgrid(np.arange(4) * h[2], np.arange(5) * h[1], np.arange(6) * h[0],
                          indexing="ij")
    a = 50.0
    u = a * x**2
    offset = filter_offset(np.stack([u, 0 * u, 0 * u]))
    np.testing.assert_allclose(offset[0][:, :, 1:-1], -a * h[0] ** 2 / 2, rtol=1e-9)
    np.testing.assert_allclose(offset[1:], 0.0)
    f = _iterated_field(u, h, offset[0], offset[0])
    np.testing.assert_allclose(iteration_uncertainty(f)[0], 0.0, atol=1e-15)
    bias = a * (2 * h[0]) ** 2 / 12                  # W = 2h at 50 % overlap
    g = combine(f, _response(gain_w=1.0, random_w=0.0))
    np.testing.assert_allclose(g.u_uncertainty, bias, rtol=1e-9)
    # without a smoothed predictor the same corrections mean passes that do not converge
    raw = replace(f, settings=replace(f.settings, smooth_predictor=False))
    held = MAX_CONVERGENCE_RATIO / (1 - MAX_CONVERGENCE_RATIO)
    np.testing.assert_allclose(iteration_uncertainty(raw)[0], held * np.abs(offset[0]),
                               rtol=1e-9)


def test_one_test_displacement_is_the_middle_of_the_three(small_camera):
    """Three displacements along all axes at once, then one along x only and one along
    depth only; one displacement is the middle of the three."""
    five = response_shifts(small_camera)
    assert five.shape == (5, 3)
    np.testing.assert_allclose(response_shifts(small_camera, displacements=1), five[1:2])
    assert np.all(five[:3] > 0)
    assert five[3, 0] > 0 and np.all(five[3, 1:] == 0)
    assert np.all(five[4, :2] == 0) and five[4, 2] > 0
    with pytest.raises(ValueError, match="displacements"):
        response_shifts(small_camera, displacements=2)


def test_the_window_s_bias_bounds_what_deformation_passes_leave():
    """The fixed point of deformation passes, iterated on a 1-D grid of spacing h with
    windows W = 2h (50 % overlap): each pass takes the predictor P = the previous vectors
    smoothed by [1, 2, 1]/4 and linearly interpolated, and adds the window average of the
    flow less P (exact integrals). For u = a x^2 the vectors converge to u - a h^2/6 =
    u - (h^2/12) u'': half the one-window bias (W^2/24) u'' = a h^2 / 3 that
    unresolved_gradient_bias gives, which therefore bounds it."""
    from plenopiv.piv.outliers import _smooth_predictor

    h, a = 1e-3, 40.0
    x = np.arange(30) * h
    d = np.zeros_like(x)
    for _ in range(200):
        p = _smooth_predictor(d[None, None, None, :])[0, 0, 0]
        # window average over [x - h, x + h] of the flow and of the piecewise-linear P
        flow_average = a * (x**2 + h**2 / 3)
        pad = np.concatenate([[2 * p[0] - p[1]], p, [2 * p[-1] - p[-2]]])
        predictor_average = (pad[:-2] + 2 * pad[1:-1] + pad[2:]) / 4
        d = p + flow_average - predictor_average
    # the linear extrapolation at the ends disturbs the vectors near them; the disturbance
    # decays away from them (3 % three vectors in, 0.2 % five, 0.008 % eight)
    inside = slice(8, -8)
    fixed_point_bias = d[inside] - a * x[inside] ** 2
    np.testing.assert_allclose(fixed_point_bias, -a * h**2 / 6, rtol=1e-4)
    u = np.broadcast_to(a * x**2, (4, 5, x.size))
    bound = unresolved_gradient_bias(np.stack([u, 0 * u, 0 * u]), (h, h, h), (2 * h,) * 3)
    np.testing.assert_allclose(bound[0], a * h**2 / 3, rtol=1e-9)
    assert np.all(np.abs(fixed_point_bias) <= 0.5 * bound[0][0, 0, inside] * (1 + 1e-4))


def test_the_number_of_test_displacements_is_a_piv_key():
    from plenopiv.piv.settings import PIVSettings

    cfg = PIVSettings(response_displacements=1)
    assert cfg.response_displacements == 1
    assert PIVSettings().response_displacements == 3
    with pytest.raises(ValueError, match="response_displacements"):
        PIVSettings(response_displacements=2)


def test_the_curvature_of_random_errors_is_removed_from_the_bias_term(rng):
    """Vectors with independent random errors sigma and no curvature: the second differences
    give the bias term the variance k sigma^2, k = 2 sum a_i^2 + 4 (sum a_i)^2 with
    a_i = W_i^2 / (24 h_i^2) (7/6 at 50 % overlap), as large as the noise itself. combine
    removes that variance per vector, sqrt(max(0, b^2 - k sigma^2)): for b ~ N(0, k sigma^2)
    what stays has the mean square k sigma^2 E[max(0, X - 1)] = 0.4839 k sigma^2 (X a
    chi-square of one degree of freedom), not k sigma^2."""
    h = np.array([1e-3, 1e-3, 1e-3])
    k = curvature_noise_factor(h, 2 * h)
    assert k == pytest.approx(7 / 6)
    sigma = 1e-6
    shape = (24, 30, 36)
    noise = rng.normal(0.0, sigma, size=shape)
    u = 1e-4 + 0.01 * np.arange(shape[2]) * h[0] + noise       # linear: no curvature
    raw = unresolved_gradient_bias(np.stack([u, 0 * u, 0 * u]), h, 2 * h)[0]
    inner = (slice(1, -1),) * 3                                 # borders repeat a neighbour
    n = raw[inner].size
    # mean square of n samples of k sigma^2 chi2_1: relative standard error sqrt(2 / n)
    assert np.mean(raw[inner] ** 2) == pytest.approx(k * sigma**2, rel=5 * np.sqrt(2 / n))
    f = _grid_field(u, h)
    f = replace(f, uncertainty_parts={"correlation": np.stack([np.full(shape, sigma),
                                                               np.zeros(shape),
                                                               np.zeros(shape)])})
    kept = combine(f, _response(gain_w=1.0, random_w=0.0)).uncertainty_parts[
        "unresolved_gradient"][0]
    assert np.all(kept <= raw)
    assert np.mean(kept[inner] ** 2) == pytest.approx(0.4839 * k * sigma**2,
                                                      rel=5 * np.sqrt(2 / n) * 2)


def test_a_rejected_vector_leaves_its_range_to_its_neighbourhood():
    """A rejected vector whose measurement lay D from its neighbours' median gives itself and
    its 3 x 3 x 3 neighbourhood D / sqrt(12) (a rectangular distribution over the range);
    vectors two spacings away and components without disagreement get nothing; where two
    ranges overlap the larger counts."""
    shape = (5, 5, 7)
    f = _grid_field(np.zeros(shape), (1e-3, 1e-3, 1e-3))
    jump = np.zeros((3,) + shape)
    jump[0, 2, 2, 2] = 6e-4          # u of the vector (z, y, x) = (2, 2, 2)
    jump[0, 2, 2, 4] = 3e-4          # a smaller one two vectors along x
    f = replace(f, uncertainty_parts={"rejected_disagreement": jump})
    q = rejected_neighbour_uncertainty(f)
    assert REJECTED_RANGE_FACTOR == pytest.approx(1 / np.sqrt(12))
    np.testing.assert_allclose(q[0, 1:4, 1:4, 1:4], 6e-4 / np.sqrt(12))    # incl. (2, 2, 3)
    np.testing.assert_allclose(q[0, 1:4, 1:4, 5], 3e-4 / np.sqrt(12))
    assert q[0, 0].max() == 0.0 and q[0, 4].max() == 0.0 and q[0, :, :, 0].max() == 0.0
    assert q[1:].max() == 0.0
    # combined in quadrature with the other terms (here all zero)
    g = combine(f, _response(gain_w=1.0, random_w=0.0))
    np.testing.assert_allclose(g.u_uncertainty, q[0], atol=1e-18)
    np.testing.assert_allclose(g.uncertainty_parts["rejected_neighbour"], q)
    # a field without rejected vectors, or without the record, gets nothing
    none = replace(f, uncertainty_parts={"rejected_disagreement": np.zeros((3,) + shape)})
    assert rejected_neighbour_uncertainty(none).max() == 0.0
    assert rejected_neighbour_uncertainty(replace(f, uncertainty_parts=None)).max() == 0.0


def test_a_spurious_peak_s_reach_is_not_counted_as_unresolved_flow():
    """The uniform test pairs' rejected vectors are spurious peaks; their median disagreement
    S is removed in quadrature from a real rejection's: D = 5 S/3 leaves 4 S/3 (a 3-4-5
    triangle), a disagreement within S leaves nothing, a component without S keeps all."""
    from plenopiv.piv.response import rejected_disagreements, spurious_disagreement

    shape = (5, 5, 7)
    f = _grid_field(np.zeros(shape), (1e-3, 1e-3, 1e-3))
    jump = np.zeros((3,) + shape)
    jump[:, 2, 2, 2] = [5e-4, 2e-4, 5e-4]
    jump[:, 2, 2, 5] = [2e-4, 1e-4, 2e-4]
    f = replace(f, uncertainty_parts={"rejected_disagreement": jump})
    rows = rejected_disagreements(f)
    assert rows.shape == (2, 3)
    np.testing.assert_allclose(sorted(rows[:, 0]), [2e-4, 5e-4])
    # three test pairs' spurious peaks: 3e-4 typically along u and w, nothing along v, and
    # one peak on a ghost far off, which the median (the typical reach) does not follow
    spurious = spurious_disagreement([np.array([[3e-4, 0.0, 3e-4], [2e-4, 0.0, 2e-4]]),
                                      np.array([[3e-4, 0.0, 3e-4], [4e-4, 0.0, 4e-4],
                                                [5e-3, 0.0, 5e-3]]), np.zeros((0, 3))])
    np.testing.assert_allclose(spurious, [3e-4, 0.0, 3e-4])
    np.testing.assert_array_equal(spurious_disagreement([np.zeros((0, 3))]), 0.0)
    q = rejected_neighbour_uncertainty(f, spurious)
    np.testing.assert_allclose(q[0, 1:4, 1:4, 1:4], 4e-4 / np.sqrt(12))
    np.testing.assert_allclose(q[2, 1:4, 1:4, 1:4], 4e-4 / np.sqrt(12))
    np.testing.assert_allclose(q[1, 1:4, 1:4, 1:4], 2e-4 / np.sqrt(12))   # no S: all of it
    assert q[0, :, :, 6].max() == 0.0 and q[2, :, :, 6].max() == 0.0  # within S: spurious
    np.testing.assert_allclose(q[1, 1:4, 1:4, 6], 1e-4 / np.sqrt(12))
    np.testing.assert_array_equal(rejected_neighbour_uncertainty(f, None),
                                  rejected_neighbour_uncertainty(f))
    g = combine(f, replace(_response(gain_w=1.0, random_w=0.0), spurious=spurious))
    np.testing.assert_allclose(g.uncertainty_parts["rejected_neighbour"], q)
    r = replace(_response(), spurious=spurious)
    back = Response.from_dict(json.loads(json.dumps(r.to_dict())))
    np.testing.assert_array_equal(back.spurious, spurious)


def test_the_curvature_at_a_border_vector_is_its_own():
    """A cubic u = c x^3 curves by 6 c x: the one-sided border stencil gives the second
    difference 6 c x h^2 at the border vector itself (exact for a cubic, as the central one
    inside), where the neighbour's, the border's former estimate, is off by 6 c h^3; with
    three points the border takes the middle's, with two there is none."""
    from plenopiv.piv.uncertainty import _second_difference

    h, c = 1e-3, 2e3
    for n in (4, 5, 8):
        x = (np.arange(n) - 0.3) * h
        d2 = _second_difference(np.broadcast_to(c * x**3, (2, 3, n)), 2)
        np.testing.assert_allclose(d2, np.broadcast_to(6 * c * x * h**2, (2, 3, n)),
                                   rtol=1e-9, atol=1e-21)
        assert abs(d2[0, 0, 0] - 6 * c * x[1] * h**2) == pytest.approx(6 * c * h**3)
    x = np.arange(3) * h
    np.testing.assert_allclose(_second_difference(c * x**3, 0), 6 * c * x[1] * h**2)
    np.testing.assert_array_equal(_second_difference(c * x[:2] ** 3, 0), 0.0)


def test_the_curvature_noise_of_every_vector_border_included(rng):
    """White noise of variance sigma^2 through the scaled bias stencil: the mean square at
    every vector of a 3 x 4 x 6 grid (corners, edges, faces, inside) is the factor of that
    vector times sigma^2, within five standard errors of 4000 draws; inside it is the
    grid-free factor, at a border vector of a 4-point axis more."""
    h = np.array([1e-3, 1.2e-3, 1.5e-3])
    window = 2 * h
    scale = np.array([[1.0, 1.5, 2.0], [1.2, 1.0, 1.0], [2.5, 3.0, 1.1]])
    shape = (3, 4, 6)
    k = curvature_noise_factor(h, window, scale, shape)
    assert k.shape == (3,) + shape
    np.testing.assert_allclose(k[:, 1, 1:-1, 1:-1],
                               np.broadcast_to(curvature_noise_factor(h, window, scale)[:, None,
                                                                                      None],
                                               (3, 2, 4)))
    assert np.all(k[:, 1, 0, 1:-1] > k[:, 1, 1, 1:-1])
    draws, sigma = 4000, 1.0
    noise = rng.normal(0.0, sigma, size=(draws, 3) + shape)
    mean_square = np.zeros((3,) + shape)
    for d in range(draws):
        mean_square += unresolved_gradient_bias(noise[d], h, window, scale) ** 2
    mean_square /= draws
    np.testing.assert_allclose(mean_square, k * sigma**2, rtol=5 * np.sqrt(2 / draws))


def test_the_shared_error_grows_with_the_vectors_motion_whatever_its_direction():
    """The excess random error (the error both exposures share) is 0 at rest; its variance
    grows linearly with the lateral and the depth motion in resolution cells, each as the
    test pair moving along it alone measured, in every component whichever way the vector
    moved (a component that does not move gets it too), additive, held beyond the test
    pairs' motions; one test pair: linear in the whole motion through it."""
    cell = np.array([1e-4, 1e-4, 4e-4])                        # lateral, lateral, depth
    shifts = np.array([[1e-4, 0.0, 0.0], [0.0, 0.0, 4e-4]])    # 1 cell along x, 1 in depth;
    # two pairs cannot tell x from y apart: the lateral motion counts whatever its direction
    z = np.array([-1e-3, 0.0, 1e-3])
    random = np.zeros((2, 3, 3))
    random[0] = 2e-5                                           # lateral motion's spread
    random[1] = 3e-5                                           # depth motion's
    statistics = np.full((2, 3, 3), 1e-5)
    gain = np.full((2, 3, 3), np.nan)
    gain[0, 0], gain[1, 2] = 0.9, 0.5                          # along the axes they move
    resp = Response(z, shifts, gain, random, statistics, 100, cell)
    a, b = 2e-5**2 - 1e-5**2, 3e-5**2 - 1e-5**2                # excess variance per cell
    motions = {                                                 # (u, v, w) -> variance
        "rest": ((0.0, 0.0, 0.0), 0.0),
        "half a cell along y": ((0.0, 0.5e-4, 0.0), 0.5 * a),
        "along x and y": ((0.6e-4, 0.8e-4, 0.0), a),
        "depth only": ((0.0, 0.0, 2e-4), 0.5 * b),
        "both": ((0.5e-4, 0.0, 2e-4), 0.5 * a + 0.5 * b),
        "beyond": ((1e-3, 0.0, 4e-3), a + b),
    }
    for name, (d, var) in motions.items():
        disp = np.broadcast_to(np.asarray(d)[:, None, None, None], (3, 3, 2, 2))
        np.testing.assert_allclose(resp.excess(z, disp), np.sqrt(var), rtol=1e-9,
                                   atol=1e-20, err_msg=name)
    # the same for any direction of the same motion: a lateral motion turned by any angle,
    # and every motion reversed
    rng = np.random.default_rng(3)
    for _ in range(5):
        d = rng.normal(size=3) * np.array([1e-4, 1e-4, 4e-4])
        turn = rng.uniform(0, 2 * np.pi)
        other = np.array([d[0] * np.cos(turn) - d[1] * np.sin(turn),
                          d[0] * np.sin(turn) + d[1] * np.cos(turn), -d[2]])
        one, two = (resp.excess(z, np.broadcast_to(v[:, None, None, None], (3, 3, 2, 2)))
                    for v in (d, other))
        np.testing.assert_allclose(one, two, rtol=1e-12)
    # the gain is the mean over the test pairs that move along each axis
    g, _ = resp.at(z)
    np.testing.assert_allclose(g[0], 0.9)
    np.testing.assert_allclose(g[1], 1.0)      # no pair moved along y: no gain to apply
    np.testing.assert_allclose(g[2], 0.5)
    # one test pair: linear in the whole motion through it, held beyond
    one = Response(z, np.array([[1e-4, 1e-4, 0.0]]), np.ones((1, 3, 3)), random[:1],
                   statistics[:1], 100, cell)
    for d, frac in (((0.0, 0.0, 4e-4 / np.sqrt(2)), 0.5), ((1e-3, 0.0, 0.0), 1.0)):
        disp = np.broadcast_to(np.asarray(d)[:, None, None, None], (3, 3, 2, 2))
        np.testing.assert_allclose(one.excess(z, disp), np.sqrt(frac * a), rtol=1e-9)
    # the cell travels with the cached response
    back = Response.from_dict(json.loads(json.dumps(resp.to_dict())))
    np.testing.assert_array_equal(back.cell, cell)
    # through combine: the vector's own motion sets its excess
    f = _field(w=0.0, sigma=0.0)
    f = replace(f, u=f.u * 0.0, v=f.v * 0.0)
    out = combine(f, resp)
    np.testing.assert_allclose(out.uncertainty_parts["response_random"], 0.0, atol=1e-20)


def test_a_vector_measured_elsewhere_errs_by_the_gradient_times_the_offset():
    """A window that holds the particles of c - δ reports the displacement there: for a linear
    field d = G x the error is |G δ| per component, whatever the layer; a uniform field has
    none; beside a NaN vector the derivative is undefined and the term is 0, not NaN."""
    h = np.array([1e-3, 2e-3, 3e-3])                               # spacing x, y, z
    z, y, x = np.meshgrid(np.arange(4) * h[2], np.arange(5) * h[1], np.arange(6) * h[0],
                          indexing="ij")
    grad = np.array([[0.01, -0.02, 0.03], [0.0, 0.0, 0.0], [-0.04, 0.0, 0.05]])  # d_k/dx_a
    disp = np.stack([g[0] * x + g[1] * y + g[2] * z for g in grad])
    offset = np.array([1e-5, -2e-5, 4e-5])[:, None] * np.ones((3, 4))
    out = location_uncertainty(disp, h, offset)
    expected = np.sqrt(((grad * offset[:, 0]) ** 2).sum(axis=1))
    for k in range(3):
        np.testing.assert_allclose(out[k], expected[k], rtol=1e-9, atol=1e-20)
    assert location_uncertainty(np.ones_like(disp), h, offset).max() == 0.0
    disp[0, 2, 2, 2] = np.nan
    out = location_uncertainty(disp, h, offset)
    assert np.isfinite(out).all()
    # its neighbour along x has no x derivative left, only those along y and z
    np.testing.assert_allclose(out[0, 2, 2, 1], np.hypot(grad[0, 1] * offset[1, 0],
                                                         grad[0, 2] * offset[2, 0]))
    # no offset, no term
    assert location_uncertainty(disp, h, np.zeros((3, 4))).max() == 0.0


def test_the_placement_of_a_shifted_reconstruction_is_its_shift(rng):
    """Correlating the true particles' volume with a reconstruction that drew every
    particle δ away gives δ in every layer (sub-voxel, each axis its own), in metres."""
    from plenopiv.camera.grid import VolumeGrid
    from plenopiv.piv import correlate_volumes
    from plenopiv.synthetic.truth import gaussian_truth_volume

    voxel = np.array([50e-6, 50e-6, 100e-6])
    grid = VolumeGrid.from_bounds((0.0, 48 * voxel[0]), (0.0, 48 * voxel[1]),
                                  (0.0, 64 * voxel[2]), voxel=tuple(voxel))
    lo, hi = np.array(grid.bounds)[:, 0], np.array(grid.bounds)[:, 1]
    margin = 8 * voxel                             # particles beyond the edges, as in a flow
    pos = rng.uniform(lo - margin, hi + margin, size=(1800, 3))
    delta = np.array([0.3, -0.2, 0.7]) * voxel
    blob = (2.0, 0.8, 0.8)
    recon = gaussian_truth_volume(grid, pos + delta, sigma_vox=(3.0, 1.0, 1.0))  # elongated
    settings = PIVSettings(windows=((16, 16, 16),), passes=2)

    def correlate(a, b):
        return correlate_volumes(a, b, grid, settings=settings)

    place = placement_offset(recon, pos, grid, correlate, blob)
    assert place.shape == (3, correlate(recon, recon).z.size)
    # a layer's mean over its ~36 vectors, of 50 %-overlapping windows (correlated errors);
    # along z the two shapes differ (sigma 2 against 3 voxels): within 0.15 voxel per layer,
    # 0.05 over all layers
    for k in range(3):
        np.testing.assert_allclose(place[k], delta[k], atol=0.15 * voxel[k], err_msg="xyz"[k])
        assert abs(place[k].mean() - delta[k]) < 0.05 * voxel[k]


def test_the_location_term_reaches_the_product_through_the_response():
    """combine adds the location term with the response's placement (the mean over its test
    pairs and the uncertainty of that mean), and the placement travels with the cached
    response."""
    h = (1e-3, 2e-3, 3e-3)
    z, y, x = np.meshgrid(np.arange(3) * h[2], np.arange(5) * h[1], np.arange(6) * h[0],
                          indexing="ij")
    f = _grid_field(0.02 * z, h)                                    # du/dz = 0.02
    f = replace(f, z=np.array([-1e-3, 0.0, 1e-3]) * 3)
    resp = _response(gain_w=1.0, random_w=0.0)
    placement = np.zeros((3, 3, 3))
    placement[:, 2] = np.array([3e-5, 5e-5, 7e-5])[:, None]        # z offsets of three pairs
    resp = replace(resp, placement=placement)
    dz = np.sqrt(5e-5**2 + 2e-5**2 / 3)     # their mean, and its standard error (s = 2e-5)
    np.testing.assert_allclose(resp.location(f.z)[2], dz)
    out = combine(f, resp)
    np.testing.assert_allclose(out.uncertainty_parts["location"][0], 0.02 * dz, rtol=1e-9)
    np.testing.assert_allclose(out.u_uncertainty, 0.02 * dz, rtol=1e-9)
    back = Response.from_dict(json.loads(json.dumps(resp.to_dict())))
    np.testing.assert_array_equal(back.placement, placement)
    assert _response().location(f.z).max() == 0.0                  # not measured: no term


def test_the_shared_error_of_each_component_follows_the_motion_along_each_axis():
    """With test pairs along x alone, along depth alone and diagonal ones, the excess of each
    lateral component is fitted per axis of motion: it gets from a motion along x what the
    pair along x gave it, from a motion along y what the diagonal pairs gave beyond that
    (here u's error grows with motion along x only, v's along y only); the depth component's
    with the lateral motion's magnitude and the depth motion."""
    cell = np.array([1e-4, 1e-4, 4e-4])
    shifts = np.array([[0.5, 0.5, 0.1], [1.25, 1.25, 0.25], [1.75, 1.75, 0.5],
                       [1.25, 0.0, 0.0], [0.0, 0.0, 0.5]]) * cell
    t = shifts / cell                                             # motion in cells
    rate = np.array([[4.0, 0.0, 0.0], [0.0, 4.0, 0.0]]) * 1e-10   # u, v per axis x, y, z
    rate_w = np.array([2.0, 9.0]) * 1e-10                         # w: lateral, depth

    def w_motion(m):
        return np.stack([np.hypot(m[..., 0], m[..., 1]), m[..., 2]], axis=-1)

    statistics = np.full((5, 3, 3), 1e-5)
    excess2 = np.concatenate([t @ rate.T, (w_motion(t) @ rate_w)[:, None]], axis=1)
    random = np.sqrt(statistics**2 + excess2[:, :, None])
    gain = np.ones((5, 3, 3))
    resp = Response(np.array([-1e-3, 0.0, 1e-3]), shifts, gain, random, statistics, 100, cell)
    for d in ((1e-4, 0.0, 0.0), (0.0, 1.5e-4, 0.0), (0.5e-4, 1e-4, 1e-4), (0.0, 0.0, 0.0)):
        disp = np.broadcast_to(np.asarray(d)[:, None, None, None], (3, 3, 2, 2))
        m = np.abs(d) / cell
        expected = np.sqrt(np.append(rate @ m, w_motion(m) @ rate_w))
        got = resp.excess(resp.z, disp)
        for k in range(3):
            np.testing.assert_allclose(got[k], expected[k], rtol=1e-6, atol=1e-12,
                                       err_msg=f"{d} component {k}")


def test_the_depth_error_of_a_lateral_motion_does_not_depend_on_its_direction():
    """The test pairs move laterally along x alone or diagonally, never along y alone: a
    depth error that does not grow from the diagonal pairs' motion to the pair's along x
    (as measured) must still reach a vector moving along y, and one moving along x, along
    y or obliquely by the same amount gets the same w excess, at every layer."""
    from plenopiv.piv.response import LATERAL_SHIFTS, SEPARATING_SHIFTS

    cell = np.array([1e-4, 1e-4, 4e-4])
    shifts = np.array([(a, a, 0.0) for a in LATERAL_SHIFTS] + list(SEPARATING_SHIFTS)) * cell
    z = np.array([-1e-3, 0.0, 1e-3])
    statistics = np.full((len(shifts), 3, 3), 1e-5)
    random = np.full((len(shifts), 3, 3), 3e-5)        # the same error whatever the motion
    random[-1] = statistics[-1]                        # none from depth motion alone
    resp = Response(z, shifts, np.ones_like(random), random, statistics, 100, cell)
    got = []
    for angle in (0.0, np.pi / 2, 0.4, np.pi):
        d = 1.25e-4 * np.array([np.cos(angle), np.sin(angle), 0.0])
        got.append(resp.excess(z, np.broadcast_to(d[:, None, None, None], (3, 3, 2, 2)))[2])
    assert got[0].min() > 1e-5                         # the excess is there along x
    for g in got[1:]:
        np.testing.assert_allclose(g, got[0], rtol=1e-9)


def test_the_placement_does_not_depend_on_where_the_voxel_grid_starts(rng):
    """The same particles and the same reconstruction error on a grid shifted by a random
    fraction of a voxel along each axis give the same placement: nothing physical moved
    (per-layer means within 0.15 voxel, their mean within 0.05)."""
    from plenopiv.camera.grid import VolumeGrid
    from plenopiv.piv import correlate_volumes
    from plenopiv.synthetic.truth import gaussian_truth_volume

    voxel = np.array([50e-6, 50e-6, 100e-6])
    n = np.array([48, 48, 64])
    pos = rng.uniform(-8 * voxel, (n + 8) * voxel, size=(1800, 3))
    delta = np.array([-0.25, 0.4, -0.6]) * voxel
    settings = PIVSettings(windows=((16, 16, 16),), passes=2)
    places = []
    for frac in (np.zeros(3), rng.uniform(0.0, 1.0, 3)):
        lo = frac * voxel
        grid = VolumeGrid.from_bounds(*zip(lo, lo + n * voxel, strict=True), voxel=tuple(voxel))
        recon = gaussian_truth_volume(grid, pos + delta, sigma_vox=(3.0, 1.0, 1.0))

        def correlate(a, b, grid=grid):
            return correlate_volumes(a, b, grid, settings=settings)

        place = placement_offset(recon, pos, grid, correlate, (2.0, 0.8, 0.8))
        places.append(place / voxel[:, None])
    one, two = places
    np.testing.assert_allclose(one, two, atol=0.15)
    np.testing.assert_allclose(one.mean(axis=1), two.mean(axis=1), atol=0.05)
    np.testing.assert_allclose(two.mean(axis=1), delta / voxel, atol=0.05)


def test_the_lateral_edge_is_the_first_and_last_row_and_column():
    from plenopiv.piv.response import lateral_edge

    edge = lateral_edge((2, 4, 5))
    assert edge.shape == (2, 4, 5)
    np.testing.assert_array_equal(edge[0], edge[1])
    assert edge[0, 1:-1, 1:-1].sum() == 0 and edge[0].sum() == 4 * 5 - 2 * 3
    assert lateral_edge((3, 2, 6)).all()          # two rows: no interior


def test_edge_vectors_get_the_test_pairs_edge_error_and_interior_ones_theirs():
    """Test pairs whose edge vectors spread more than their interior ones give the real
    field's edge vectors the edge's excess and the interior vectors the interior's; the
    split survives the cache's round trip."""
    cell = np.array([1e-4, 1e-4, 4e-4])
    shifts = np.array([[1.25, 0.0, 0.0], [0.0, 0.0, 0.5]]) * cell
    z = np.array([-1e-3, 0.0, 1e-3])
    statistics = np.full((2, 3, 3), 1e-5)
    interior = np.full((2, 3, 3), np.sqrt(2) * 1e-5)      # excess 1e-5 per pair's motion
    edge = np.full((2, 3, 3), np.sqrt(5) * 1e-5)          # excess 2e-5
    gain = np.ones((2, 3, 3))
    resp = Response(z, shifts, gain, interior, statistics, 100, cell, None, edge, statistics)
    disp = np.broadcast_to((shifts[0] + shifts[1])[:, None, None, None], (3, 3, 4, 5))
    got = resp.excess(z, disp)
    # the motion of both pairs at once: twice one pair's excess variance
    from plenopiv.piv.response import lateral_edge

    mask = lateral_edge((3, 4, 5))
    np.testing.assert_allclose(got[:, mask], np.sqrt(2) * 2e-5, rtol=1e-6)
    np.testing.assert_allclose(got[:, ~mask], np.sqrt(2) * 1e-5, rtol=1e-6)
    back = Response.from_dict(json.loads(json.dumps(resp.to_dict())))
    np.testing.assert_allclose(back.excess(z, disp), got)
    # without the split every vector gets the interior's
    one = Response(z, shifts, gain, interior, statistics, 100, cell)
    np.testing.assert_allclose(one.excess(z, disp), np.sqrt(2) * 1e-5, rtol=1e-6)


def test_a_test_pair_s_edge_and_interior_spread_are_measured_apart(rng):
    """The spread of a test pair's vectors is taken about the layer's mean for the edge and
    the interior vectors apart: an edge that errs by 0.3 voxel rms and an exact interior
    give 0.3 and 0 (not 0.2 for both), and the gain is the layer's mean."""
    from plenopiv.piv.response import lateral_edge
    from plenopiv.workflow.response import _layer_statistics

    shape = (2, 5, 6)
    mask = lateral_edge(shape)
    u = np.full(shape, 1.0)
    for layer in range(shape[0]):                      # +-0.3 in equal numbers per layer
        u[layer][mask[layer]] += rng.permutation(np.resize([-0.3, 0.3], mask[layer].sum()))
    zero = np.zeros(shape)
    field = VectorField(x=np.arange(6.0), y=np.arange(5.0), z=np.arange(2.0), u=u, v=zero,
                        w=zero, valid=np.ones(shape, bool), snr=zero + 3, correlation=zero,
                        u_uncertainty=zero + 0.05, v_uncertainty=zero + 0.05,
                        w_uncertainty=zero + 0.05)
    gain, spread, stats, edge_spread, edge_stats = _layer_statistics(field, (1.0, 0.0, 0.0))
    np.testing.assert_allclose(gain[0], 1.0, rtol=1e-12)
    assert np.all(np.isnan(gain[1:]))
    np.testing.assert_allclose(spread[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(edge_spread[0], 0.3, rtol=1e-12)
    np.testing.assert_allclose(stats, 0.05)
    np.testing.assert_allclose(edge_stats, 0.05)


def _wave_field(values_u, x, y, z):
    shape = values_u.shape
    zero = np.zeros(shape)
    return VectorField(x=x, y=y, z=z, u=values_u, v=zero, w=zero,
                       valid=np.ones(shape, bool), snr=zero + 3, correlation=zero,
                       u_uncertainty=zero, v_uncertainty=zero, w_uncertainty=zero)


@pytest.mark.parametrize("phase", [0.0, 0.7, 2.1])
def test_the_modulation_gain_is_the_in_phase_part_of_the_measured_wave(rng, phase):
    """A wave measured at H = 0.62 of its amplitude, shifted by a quarter of its size in
    quadrature, on an offset and with noise: the fit gives H within its noise whatever the
    wave's phase and wherever the vector grid starts (a random fraction of a spacing), and
    NaN along an axis without a wavelength."""
    from plenopiv.piv.response import modulation_displacement, modulation_gain

    h = 1e-3
    origin = rng.uniform(0, h, size=3)
    x, y, z = (o + h * np.arange(n) for o, n in zip(origin, (9, 6, 5), strict=True))
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    wavelength = np.array([4 * h, 4 * h, 0.0])
    amplitude = np.array([2e-4, 1e-4, 1e-4])
    axes = (1, 0, 2)                          # u varies along y, v along x, w along z
    phases = np.array([phase, phase + 1, phase + 2])
    theta = 2 * np.pi * yy / wavelength[1] + phase
    noise = 2e-6
    u = (0.62 * amplitude[0] * np.sin(theta) + 0.25 * amplitude[0] * np.cos(theta) + 3e-5
         + rng.normal(0.0, noise, size=theta.shape))
    gain = modulation_gain(_wave_field(u, x, y, z), wavelength, amplitude, axes, phases)
    # noise of a least-squares amplitude over n samples: noise * sqrt(2 / n) / amplitude
    tol = 5 * noise * np.sqrt(2 / u.size) / amplitude[0]
    assert gain[0] == pytest.approx(0.62, abs=tol)
    assert gain[1] == pytest.approx(0.0, abs=1e-9)          # v is zero: no modulation
    assert np.isnan(gain[2])                                 # no wavelength along z
    # the displacement the test pair applies is the same wave
    pts = np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)
    d = modulation_displacement(pts, wavelength, amplitude, axes, phases)
    np.testing.assert_allclose(d[:, 0], amplitude[0] * np.sin(theta.ravel()), atol=1e-18)
    assert np.all(d[:, 2] == 0.0)


def test_the_modulation_factor_makes_the_curvature_term_the_error_of_the_measured_wave():
    """A wave of four vector spacings measured through top-hat windows of two spacings
    (H = sin(pi/2) / (pi/2) = 2/pi): the measured curvature gives the bias term 1/3 H A,
    short of the error (1 - H) A by 1.71; with the modulation factor it is the error at
    every vector (inside the border). A chain that loses no modulation keeps the plain term."""
    from plenopiv.piv.uncertainty import modulation_factor

    h = 1e-3
    x = h * np.arange(12)
    amplitude = 1e-4
    true = amplitude * np.sin(2 * np.pi * x / (4 * h) + 0.4)
    tophat = 2 / np.pi
    measured = tophat * true                 # a top-hat average of a sine: its transfer
    u = np.broadcast_to(measured, (3, 4, 12)).copy()
    disp = np.stack([u, 0 * u, 0 * u])
    spacing, window = np.array([h, h, h]), np.array([2 * h, 2 * h, 2 * h])
    modulation = np.full((3, 3), tophat)
    factor = modulation_factor(modulation, spacing, window)
    np.testing.assert_allclose(factor, (1 - tophat) / (2 / 6 * tophat))     # 1.712
    plain = unresolved_gradient_bias(disp, spacing, window)[0][:, :, 1:-1]
    scaled = unresolved_gradient_bias(disp, spacing, window, factor)[0][:, :, 1:-1]
    error = np.abs(measured - true)[1:-1]
    np.testing.assert_allclose(plain, np.broadcast_to(error / factor[0, 0], plain.shape),
                               atol=1e-18)
    np.testing.assert_allclose(scaled, np.broadcast_to(error, scaled.shape), atol=1e-18)
    # no loss of modulation, a modulation not measured: the plain term
    np.testing.assert_array_equal(modulation_factor(np.ones((3, 3)), spacing, window), 1.0)
    np.testing.assert_array_equal(modulation_factor(np.full((3, 3), np.nan), spacing, window),
                                  1.0)
    np.testing.assert_array_equal(modulation_factor(None, spacing, window), 1.0)


def test_the_scaled_curvature_of_random_errors_is_counted_per_component(rng):
    """With a factor per component and axis, the second differences of random errors give
    component k the variance k_k sigma^2 of the scaled stencil (Monte Carlo within its
    standard error)."""
    h = np.array([1e-3, 1e-3, 1e-3])
    scale = np.array([[1.0, 1.0, 1.0], [1.5, 1.0, 2.0], [3.0, 2.5, 1.2]])
    k = curvature_noise_factor(h, 2 * h, scale)
    assert k[0] == pytest.approx(curvature_noise_factor(h, 2 * h))
    sigma = 1e-6
    shape = (3, 20, 24, 28)
    noise = rng.normal(0.0, sigma, size=shape)
    raw = unresolved_gradient_bias(noise, h, 2 * h, scale)[(slice(None),) + (slice(1, -1),) * 3]
    n = raw[0].size
    for c in range(3):
        assert np.mean(raw[c] ** 2) == pytest.approx(k[c] * sigma**2, rel=5 * np.sqrt(2 / n))


def test_the_modulation_travels_with_the_cached_response():
    r = replace(_response(), modulation=np.array([[0.8, 0.7, np.nan]] * 3))
    back = Response.from_dict(json.loads(json.dumps(r.to_dict())))
    np.testing.assert_array_equal(back.modulation, r.modulation)
    assert Response.from_dict(json.loads(json.dumps(_response().to_dict()))).modulation is None


def test_three_modulation_pairs_give_every_component_along_every_axis():
    """A chain that measures component k varying along axis a at H[k, a] of its size
    (a stand-in for render -> reconstruct -> correlate): the three modulation pairs recover
    the whole matrix, each wave's largest gradient is 1/8 voxel per voxel, and an axis with
    fewer than three vectors has no wavelength (NaN)."""
    from plenopiv.piv.response import MODULATION_GRADIENT, _modulation

    true_h = np.array([[0.8, 0.7, 0.6], [0.75, 0.65, 0.55], [0.5, 0.45, 0.9]])
    h = np.array([1e-3, 1e-3, 2e-3])                       # vector spacing x, y, z
    voxel = np.array([1e-4, 1e-4, 2e-4])
    x, y, z = (s * np.arange(n) for s, n in zip(h, (8, 6, 5), strict=True))
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    centres = np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)
    seen = []

    def pair(displacement):
        # the displacement the pair applies, read back by perturbing one axis at a time
        base = displacement(centres)
        comps = np.zeros((3,) + xx.shape)
        for k in range(3):
            for a in range(3):
                probe = centres.copy()
                probe[:, a] += 1e-7
                if np.any(displacement(probe)[:, k] != base[:, k]):
                    comps[k] = true_h[k, a] * base[:, k].reshape(xx.shape)
                    slope = np.abs(np.gradient(base[:, k].reshape(xx.shape), h[a],
                                               axis=2 - a)).max()
                    seen.append(slope * voxel[a] / voxel[k])
        zero = np.zeros(xx.shape)
        return VectorField(x=x, y=y, z=z, u=comps[0], v=comps[1], w=comps[2],
                           valid=np.ones(xx.shape, bool), snr=zero + 3, correlation=zero,
                           u_uncertainty=zero, v_uncertainty=zero, w_uncertainty=zero)

    grid_field = pair(lambda p: np.zeros_like(p))
    got = _modulation(grid_field, voxel, pair)
    np.testing.assert_allclose(got, true_h, rtol=1e-9)
    # sampled four times per wavelength, the gradient's maximum is read at 1/sqrt(2) of it
    assert len(seen) == 9 and np.all(np.array(seen) <= MODULATION_GRADIENT * (1 + 1e-9))
    assert np.all(np.array(seen) >= MODULATION_GRADIENT * 0.6)
    # two layers of vectors: no wave along z, the lateral ones measured as before
    zero = np.zeros((2,) + xx.shape[1:])
    two_layers = VectorField(x=x, y=y, z=z[:2], u=zero, v=zero, w=zero,
                             valid=np.ones(zero.shape, bool), snr=zero, correlation=zero,
                             u_uncertainty=zero, v_uncertainty=zero, w_uncertainty=zero)
    got = _modulation(two_layers, voxel, pair)
    assert np.all(np.isnan(got[:, 2]))
    np.testing.assert_allclose(got[:, :2], true_h[:, :2], rtol=1e-9)
    assert np.all(np.isnan(_modulation(grid_field, voxel, lambda d: None)))


@pytest.mark.study
def test_the_coverage_report_states_its_sampling_error():
    """uncertainty.md gives the binomial standard error of its coverages: 95 % over 100
    vectors is known to 2.2 points, 90 % over 400 to 1.5; cases without vectors are left
    out."""
    from pipelines.studies.uncertainty import _sampling_error

    cases = [{"n_vectors": 100, "coverage": {"response": [0.95, 0.95, 0.95]}},
             {"n_vectors": 400, "coverage": {"response": [0.90, 0.96, 0.98]}},
             {"n_vectors": 0, "coverage": {"response": [np.nan] * 3}}]
    text = _sampling_error(cases)
    assert "0.7-2.2 points" in text and "n = 100-400" in text
    assert _sampling_error(cases[2:]) == ""


@pytest.mark.study
def test_the_chance_that_a_right_sigma_leaves_the_band_matches_sampling(rng):
    """A σ exactly right puts each error within ±2σ with probability erf(sqrt 2) = 95.45 %;
    the share over n independent vectors is outside 90-98 % with the binomial chance the
    report states: checked against 200,000 simulated cases per n (Monte Carlo error below
    0.1 points), with n = 161 (one of the study's cases) at about 6 %; bounds inclusive
    (n = 50: 45 and 49 of 50 are inside, 44 and 50 outside)."""
    from math import erf, sqrt

    from pipelines.studies.uncertainty import GAUSSIAN_2SIGMA, chance_outside_band

    assert GAUSSIAN_2SIGMA == pytest.approx(erf(sqrt(2.0)), rel=1e-12)
    for n in (50, 161, 473):
        within = rng.binomial(n, GAUSSIAN_2SIGMA, size=200_000)
        outside = np.mean((within < 0.90 * n - 1e-9) | (within > 0.98 * n + 1e-9))
        assert chance_outside_band(n) == pytest.approx(outside, abs=0.002)
    assert 0.05 < chance_outside_band(161) < 0.08
    p = GAUSSIAN_2SIGMA
    from scipy.stats import binom
    assert chance_outside_band(50) == pytest.approx(binom.cdf(44, 50, p) + binom.pmf(50, 50, p))
    assert chance_outside_band(0) == 1.0


def test_the_modulation_gain_does_not_depend_on_where_the_vector_grid_starts(rng):
    """The same measured wave (H = 0.7, world coordinates) sampled on vector grids whose
    origins differ by a random fraction of a spacing along each axis, with independent noise
    of 2 % of the amplitude: the gains agree within their noise and with 0.7 (a bias of the
    fit from the grid's phase would show here), for a wave along x and one along z."""
    from plenopiv.piv.response import modulation_gain

    h = np.array([1e-3, 1e-3, 2e-3])
    wavelength = 4 * h
    amplitude = np.array([1e-4, 1e-4, 2e-4])
    axes, phase = (0, 1, 2), np.array([0.3, 1.1, 2.0])
    gains = []
    for shift in (np.zeros(3), rng.uniform(0, 1, size=3)):
        x, y, z = ((s + np.arange(n)) * step
                   for s, n, step in zip(shift, (8, 6, 5), h, strict=True))
        zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
        pts = (xx, yy, zz)
        comps = [0.7 * amplitude[k] * np.sin(2 * np.pi * pts[a] / wavelength[a] + phase[k])
                 + rng.normal(0.0, 0.02 * amplitude[k], size=xx.shape)
                 for k, a in enumerate(axes)]
        zero = np.zeros(xx.shape)
        field = VectorField(x=x, y=y, z=z, u=comps[0], v=comps[1], w=comps[2],
                            valid=np.ones(xx.shape, bool), snr=zero + 3, correlation=zero,
                            u_uncertainty=zero, v_uncertainty=zero, w_uncertainty=zero)
        gains.append(modulation_gain(field, wavelength, amplitude, axes, phase))
    tol = 5 * 0.02 * np.sqrt(2 / (8 * 6 * 5))          # five standard errors of the fit
    np.testing.assert_allclose(gains[0], 0.7, atol=tol)
    np.testing.assert_allclose(gains[1], gains[0], atol=tol * np.sqrt(2))


@pytest.mark.study
def test_coverage_is_split_beside_a_rejected_vector_and_elsewhere():
    """The study's split: a rejected vector's 3 x 3 x 3 neighbourhood (27 vectors inside the
    grid, 8 at a corner, itself included) and the rest; per region the share within ±2σ and
    the median |error| / σ, which for errors of exactly ±k σ is k."""
    from pipelines.studies.uncertainty import beside_rejection, region_coverage

    valid = np.ones((5, 6, 7), bool)
    valid[2, 3, 3] = False
    assert beside_rejection(valid).sum() == 27
    valid[0, 0, 6] = False
    got = beside_rejection(valid)
    assert got.sum() == 27 + 8 and got[1, 1, 5] and not got[2, 2, 5]
    assert not beside_rejection(np.ones((3, 3, 3), bool)).any()

    beside = np.array([True] * 4 + [False] * 6)
    sigma = np.ones((3, 10))
    err = np.vstack([[0.5, -0.5, 3.0, 0.5] + [1.0] * 6,       # u: 3 of 4 beside, all elsewhere
                     [0.1] * 4 + [-2.5] * 3 + [1.5] * 3,        # v: 4 of 4, 3 of 6
                     [2.0] * 10])                               # w: on the edge, counted in
    r = region_coverage(err, sigma, beside)
    assert r["beside_rejection"]["n"] == 4 and r["elsewhere"]["n"] == 6
    np.testing.assert_allclose(r["beside_rejection"]["coverage"], [0.75, 1.0, 1.0])
    np.testing.assert_allclose(r["elsewhere"]["coverage"], [1.0, 0.5, 1.0])
    np.testing.assert_allclose(r["beside_rejection"]["median_ratio"], [0.5, 0.1, 2.0])
    np.testing.assert_allclose(r["elsewhere"]["median_ratio"], [1.0, 2.0, 2.0])
    empty = region_coverage(err, sigma, np.zeros(10, bool))["beside_rejection"]
    assert empty["n"] == 0 and np.all(np.isnan(empty["coverage"]))


@pytest.mark.study
def test_realisations_pool_by_vectors_and_compare_their_scatter_with_the_binomial_error():
    """Pooled share = all realisations' vectors together; the scatter of independent
    realisations of n independent vectors matches the binomial error sqrt(p (1 - p) / n)."""
    from pipelines.studies.uncertainty import realisation_summary

    r = realisation_summary([[0.9, 1.0, 0.95], [0.96, 0.8, 0.95]], [100, 300])
    np.testing.assert_allclose(r["pooled"], [(90 + 288) / 400, (100 + 240) / 400, 0.95])
    assert r["n_total"] == 400 and r["outside"] == 2          # 1.0 above, 0.8 below
    np.testing.assert_allclose(r["scatter"][2], 0.0)

    rng = np.random.default_rng(11)
    n, p = 160, 0.954
    shares = rng.binomial(n, p, size=(400, 3)) / n
    r = realisation_summary(shares, np.full(400, n))
    np.testing.assert_allclose(r["pooled"], p, atol=4 * np.sqrt(p * (1 - p) / (400 * n)))
    # the standard deviation of 400 samples is within ±3.5 % (1 sd) of the true one
    np.testing.assert_allclose(r["scatter_ratio"], 1.0, atol=0.12)
