"""The depth component fitted to continuity (plenopiv.piv.continuity and its workflow step)."""

import dataclasses
import json
import warnings

import numpy as np
import pytest

from plenopiv.errors import PlenopivWarning
from plenopiv.piv import PIVSettings
from plenopiv.piv.continuity import (
    CONSISTENCY_CHI2,
    column_gain_sigma,
    depth_from_continuity,
    gradient_matrix,
    gradient_sigma,
    layer_sigma,
)
from plenopiv.products.vectors import VectorResult
from plenopiv.workflow.correlation import fitted_to_continuity

#: The vector grid of the tests: metres, uneven in depth like a depth-corrected field.
X = np.linspace(-3e-3, 3e-3, 9)
Y = np.linspace(-2e-3, 2e-3, 6)
Z = np.array([-3.0, -2.1, -1.4, -0.7, 0.0, 0.7, 1.4, 2.2, 3.0]) * 1e-3


#: Standard uncertainty of u and v, metres (5 % of the vortex's 30 µm).
LATERAL_NOISE = 1.5e-6


def grids():
    return np.meshgrid(Z, Y, X, indexing="ij")      # zz, yy, xx, each (nz, ny, nx)


def depth_sigma(scale=1e-6):
    """A plenoptic camera's depth uncertainty: five times larger at focus than far from it."""
    zz = grids()[0]
    return scale * (1.0 + 4.0 * np.exp(-(zz / 1e-3) ** 2))


def dense_twin(u, v, w, su, sv, sw, x, y, z):
    """The same least-squares problem, written out densely and solved by np.linalg.lstsq."""
    su, sv, sw = layer_sigma(su), layer_sigma(sv), layer_sigma(sw)
    delta = np.gradient(u, x, axis=2) + np.gradient(v, y, axis=1)
    gx, gy, gz = (gradient_matrix(c) for c in (x, y, z))
    sd = np.sqrt(np.einsum("ij,kjl->kil", gy ** 2, sv ** 2)
                 + np.einsum("ij,klj->kli", gx ** 2, su ** 2))
    nz, ny, nx = w.shape
    rows, rhs = [], []
    for j in range(ny):
        for i in range(nx):
            for k in range(nz):
                r = np.zeros(w.size)
                r[np.ravel_multi_index((k, j, i), w.shape)] = 1 / sw[k, j, i]
                rows.append(r)
                rhs.append(w[k, j, i] / sw[k, j, i])
                r = np.zeros(w.size)
                for kk in range(nz):
                    r[np.ravel_multi_index((kk, j, i), w.shape)] = gz[k, kk] / sd[k, j, i]
                rows.append(r)
                rhs.append(-delta[k, j, i] / sd[k, j, i])
    sol = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    return sol.reshape(w.shape)


def test_gradient_matrix_is_numpys_gradient_on_uneven_and_short_axes():
    rng = np.random.default_rng(1)
    for n in (2, 3, 7):
        c = np.cumsum(rng.uniform(0.5, 2.0, n))
        f = rng.normal(size=n)
        assert np.allclose(gradient_matrix(c) @ f, np.gradient(f, c), rtol=1e-12, atol=0)


def test_gradient_sigma_is_the_root_sum_of_squared_coefficients():
    """Monte Carlo: the spread of np.gradient of independent errors."""
    rng = np.random.default_rng(2)
    s = rng.uniform(0.5, 2.0, (5, 4))
    draws = np.gradient(rng.normal(size=(20000, 5, 4)) * s, Z[:5], axis=1)
    assert np.allclose(draws.std(axis=0), gradient_sigma(s, Z[:5], 0), rtol=0.03)


def test_the_sparse_fit_is_its_dense_twin():
    rng = np.random.default_rng(3)
    shape = (5, 3, 4)
    x, y, z = X[:4], Y[:3], Z[:5]
    u, v, w = (rng.normal(size=shape) * 1e-5 for _ in range(3))
    su, sv, sw = (rng.uniform(0.5, 2.0, shape) * 1e-6 for _ in range(3))
    fit = depth_from_continuity(u, v, w, su, sv, sw, x, y, z)
    assert np.allclose(fit.w, dense_twin(u, v, w, su, sv, sw, x, y, z), rtol=1e-9,
                       atol=1e-15)


def column_weighted_mean(values, sigma):
    return np.sum(values / sigma ** 2, axis=0) / np.sum(1 / sigma ** 2, axis=0)


@pytest.mark.parametrize("flow", ["rotation about y", "strain"])
def test_a_depth_gain_near_focus_is_restored_to_the_analytic_limit(flow):
    """Linear incompressible flows, where np.gradient is exact: u and v known (their
    uncertainty 1/20,000 of w's), w measured at a gain of 0.4 at focus rising to 1 far from it, with
    noise. In that limit continuity fixes each column up to one constant, which the fit
    takes as the column's mean of the measured w less the integral, weighted by 1/σ_w²."""
    zz, yy, xx = grids()
    if flow == "rotation about y":          # u = Ω z, w = -Ω x: div = 0, ∂w/∂z = 0
        u, v, w = 2e-2 * zz, 0 * yy, -2e-2 * xx
    else:                                   # u = a x, v = b y, w = -(a + b) z
        u, v, w = 1e-2 * xx, 0.5e-2 * yy, -1.5e-2 * zz
    gain = 1.0 - 0.6 * np.exp(-(zz / 1e-3) ** 2)
    sw = depth_sigma(2e-6)
    rng = np.random.default_rng(4)
    measured = gain * w + rng.normal(size=w.shape) * sw
    tiny = np.full(w.shape, 1e-10)
    fit = depth_from_continuity(u, v, measured, tiny, tiny, sw, X, Y, Z)
    integral = w - w[0]                     # the exact ∫ ∂w/∂z dz from the first layer
    expected = integral + column_weighted_mean(measured - integral, layer_sigma(sw))
    # the soft constraint's distance from the limit: (σ_δ h / σ_w)² ~ 1e-9 of w
    assert np.allclose(fit.w, expected, rtol=0, atol=1e-6 * np.abs(w).max())
    # and so the gain is near 1: the weighted mean leans on the far layers (gain 1)
    err_before = np.sqrt(np.mean((measured - w) ** 2))
    err_after = np.sqrt(np.mean((fit.w - w) ** 2))
    assert err_after < 0.5 * err_before


def test_a_consistent_field_is_not_changed():
    """Measured exactly (a discretely incompressible field without noise): w stays."""
    zz, yy, xx = grids()
    u, v, w = 1e-2 * xx + 3e-2 * zz, -0.4e-2 * yy, -0.6e-2 * zz - 1e-2 * xx
    s = depth_sigma()
    fit = depth_from_continuity(u, v, w, s / 5, s / 5, s, X, Y, Z)
    assert np.allclose(fit.w, w, rtol=0, atol=1e-12) and fit.chi2_per_vector < 1e-12


def oseen_about_y(rotate=False):
    """A Lamb-Oseen vortex about y (or, ``rotate``, about x), metres, on the test grid."""
    zz, yy, xx = grids()
    a = xx if not rotate else yy
    r2 = a ** 2 + zz ** 2
    core = 1.5e-3               # 30 µm at the core's edge, 2 vector spacings out
    speed = 7e-8 / np.maximum(r2, 1e-12) * (1 - np.exp(-r2 / core ** 2))
    lateral = -speed * zz
    w = speed * a
    if rotate:
        return 0 * xx, lateral, w
    return lateral, 0 * yy, w


def measured(u, v, w, rng, lateral_noise=LATERAL_NOISE):
    """u, v with lateral noise; w at the near-focus gain with depth noise (as in
    docs/validation/realcam.md: 5 % of the largest displacement laterally, 10 % in depth far
    from focus and 50 % at it)."""
    zz = grids()[0]
    gain = 1.0 - 0.6 * np.exp(-(zz / 1e-3) ** 2)
    sw = depth_sigma(3e-6)
    return (u + rng.normal(size=u.shape) * lateral_noise,
            v + rng.normal(size=v.shape) * lateral_noise,
            gain * w + rng.normal(size=w.shape) * sw, sw)


def as_vectors(u, v, w, su, sv, sw) -> VectorResult:
    shape = u.shape
    return VectorResult(x=X, y=Y, z=Z, u=u, v=v, w=w, valid=np.ones(shape, bool),
                        snr=np.full(shape, 3.0), u_uncertainty=su, v_uncertainty=sv,
                        w_uncertainty=sw)


def oseen_fit(transform=lambda *a: a, rotate=False, seed=5):
    u, v, w = oseen_about_y(rotate)
    mu, mv, mw, sw = measured(u, v, w, np.random.default_rng(seed))
    sl = np.full(u.shape, LATERAL_NOISE)
    return transform(mu, mv, mw, sl, sl, sw, X, Y, Z), (u, v, w)


def test_the_vortex_depth_gain_rises_and_u_v_stay_to_the_bit():
    """A vortex measured as a plenoptic camera does (w at 0.4 of itself at focus): the fit's
    w gain (least-squares slope of fitted on true) is within 0.1 of 1, against 0.6 to 0.7
    measured, and its rms error falls by half. The tolerance: np.gradient's truncation error
    on a core of 2.6 vector spacings, about 5 % of the gradient, integrated over the column."""
    (mu, mv, mw, su, sv, sw, *_), (u, v, w) = oseen_fit()
    vec = as_vectors(mu, mv, mw, su, sv, sw)
    out, record = fitted_to_continuity(vec)
    assert record["applied"] and record["chi2_per_vector"] <= CONSISTENCY_CHI2
    gain = lambda m: float(np.sum(m * w) / np.sum(w * w))      # noqa: E731
    assert gain(mw) < 0.8 and abs(gain(out.w) - 1.0) < 0.1
    assert np.sqrt(np.mean((out.w - w) ** 2)) < 0.5 * np.sqrt(np.mean((mw - w) ** 2))
    assert out.u is vec.u and out.v is vec.v
    assert out.u_uncertainty is vec.u_uncertainty and out.v_uncertainty is vec.v_uncertainty
    assert np.all(out.w_uncertainty < vec.w_uncertainty)


def test_the_fits_uncertainty_is_the_spread_of_the_fit_over_the_noise():
    """The same vortex measured 400 times with fresh noise (the gain deficit left out, so
    the model holds): the fitted w scatters about the truth by the fit's sigma_w (within the
    5 % a 400-draw standard deviation and np.gradient's truncation leave)."""
    u, v, w = oseen_about_y()
    zz = grids()[0]
    sw, sl = depth_sigma(3e-6), np.full(u.shape, LATERAL_NOISE)
    rng = np.random.default_rng(8)
    fits = []
    for _ in range(400):
        mu, mv = (c + rng.normal(size=c.shape) * LATERAL_NOISE for c in (u, v))
        fit = depth_from_continuity(mu, mv, w + rng.normal(size=w.shape) * sw, sl, sl, sw,
                                    X, Y, Z)
        fits.append(fit.w)
    spread = np.std(fits, axis=0)
    ratio = np.sqrt(np.mean(spread ** 2) / np.mean(fit.sigma_w ** 2))
    assert 0.95 < ratio < 1.05, ratio
    # near focus the fit is five times as sure as the measurement
    near = np.abs(zz) < 0.5e-3
    assert np.median(fit.sigma_w[near] / sw[near]) < 0.3


@pytest.mark.parametrize("change", ["shift of the origin", "millimetres", "mirror in depth",
                                    "x and y swapped"])
def test_the_fit_does_not_depend_on_what_is_not_physical(change):
    """The same flow on a shifted grid, in other units, mirrored in depth or with its
    lateral axes swapped gives the same w, transformed alike."""
    (args, _) = oseen_fit()
    ref = depth_from_continuity(*args).w
    u, v, w, su, sv, sw, x, y, z = args
    if change == "shift of the origin":
        got = depth_from_continuity(u, v, w, su, sv, sw, x + 0.37, y - 1.2, z + 0.8).w
    elif change == "millimetres":
        got = depth_from_continuity(*(a * 1e3 for a in args)).w / 1e3
    elif change == "mirror in depth":
        f = lambda a: a[::-1]           # noqa: E731
        got = -f(depth_from_continuity(f(u), f(v), -f(w), f(su), f(sv), f(sw), x, y,
                                       -z[::-1]).w)
    else:
        t = lambda a: np.swapaxes(a, 1, 2)      # noqa: E731
        got = t(depth_from_continuity(t(v), t(u), t(w), t(sv), t(su), t(sw), y, x, z).w)
    assert np.allclose(got, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


def test_a_flow_that_is_not_incompressible_is_kept_with_a_warning():
    """A uniform expansion (div = 3a) measured with the same noise: the misfit is far above
    the limit, w is kept and the warning names the figure and the key."""
    zz, yy, xx = grids()
    a = 1e-2
    mu, mv, mw, sw = measured(a * xx, a * yy, a * zz, np.random.default_rng(6))
    sl = np.full(mu.shape, LATERAL_NOISE)
    vec = as_vectors(mu, mv, mw, sl, sl, sw)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out, record = fitted_to_continuity(vec)
    assert out is vec and not record["applied"]
    assert record["chi2_per_vector"] > CONSISTENCY_CHI2
    said = [str(c.message) for c in caught if issubclass(c.category, PlenopivWarning)]
    assert len(said) == 1 and "[piv] continuity = false" in said[0]
    assert f"{record['chi2_per_vector']:.1f}" in said[0]


def test_nan_vectors_stay_nan_and_take_no_part():
    (mu, mv, mw, su, sv, sw, *_), _ = oseen_fit()
    mw = mw.copy()
    mw[4, 2, 3] = np.nan
    mu = mu.copy()
    mu[6, 1, 1] = np.nan
    fit = depth_from_continuity(mu, mv, mw, su, sv, sw, X, Y, Z)
    assert np.isnan(fit.w[4, 2, 3]) and np.isfinite(np.delete(fit.w.ravel(), np.ravel_multi_index(
        (4, 2, 3), mw.shape))).all()
    assert fit.vectors == mw.size - 1


def test_a_layer_without_uncertainties_keeps_its_vectors():
    """A layer whose uncertainties are all NaN (every window masked, say) takes no part, and
    its measured w is kept, not lost; the other layers are fitted."""
    (mu, mv, mw, su, sv, sw, *_), _ = oseen_fit()
    sw = sw.copy()
    sw[2] = np.nan
    vec = as_vectors(mu, mv, mw, su, sv, sw)
    out, record = fitted_to_continuity(vec)
    assert record["applied"] and record["vectors"] == mw.size - mw[2].size
    assert np.array_equal(out.w[2], mw[2]) and np.all(np.isnan(out.w_uncertainty[2]))
    assert np.isfinite(out.w).all() and not np.allclose(out.w[4], mw[4])


def test_where_the_fit_is_not_made_the_record_says_why():
    (mu, mv, mw, su, sv, sw, *_), _ = oseen_fit()
    vec = as_vectors(mu, mv, mw, su, sv, sw)
    out, rec = fitted_to_continuity(vec, PIVSettings(continuity=False))
    assert out is vec and rec == {"applied": False, "reason": "[piv] continuity = false"}
    one = dataclasses.replace(vec, z=Z[:1], u=mu[:1], v=mv[:1], w=mw[:1], valid=vec.valid[:1],
                              snr=vec.snr[:1], u_uncertainty=su[:1], v_uncertainty=sv[:1],
                              w_uncertainty=sw[:1])
    assert fitted_to_continuity(one)[1]["reason"] == "one layer of vectors in depth"
    thin = dataclasses.replace(vec, x=X[:1], u=mu[..., :1], v=mv[..., :1], w=mw[..., :1],
                               valid=vec.valid[..., :1], snr=vec.snr[..., :1],
                               u_uncertainty=su[..., :1], v_uncertainty=sv[..., :1],
                               w_uncertainty=sw[..., :1])
    assert fitted_to_continuity(thin)[1]["reason"].startswith("one vector along x or y")
    with pytest.raises(ValueError, match="at least two along each axis"):
        depth_from_continuity(thin.u, thin.v, thin.w, su[..., :1], sv[..., :1], sw[..., :1],
                              X[:1], Y, Z)
    bare = dataclasses.replace(vec, u_uncertainty=None, v_uncertainty=None, w_uncertainty=None)
    assert fitted_to_continuity(bare)[1]["reason"] == "the vectors carry no uncertainty"
    json.dumps(rec)


@pytest.mark.parametrize("value", ["yes", 1, None])
def test_continuity_takes_true_or_false_only(value):
    with pytest.raises(ValueError, match=r"continuity = .*expected True or False"):
        PIVSettings(continuity=value)


def test_the_response_gain_term_weighs_the_layers_by_their_gain_error_not_their_attenuation():
    """The response's term e_k·|w| is smallest where w is most attenuated (near focus): as a
    weight it made a column's level that of its worst layers. Taken at the column's rms w,
    layers of equal gain error weigh equally: a rotation about y (∂w/∂z = 0, each column
    one w) measured at 0.4 of itself at focus and 1 far from it is fitted to the column's
    plain mean, not pulled to the focus layer's 0.4."""
    zz, yy, xx = grids()
    u, v, w = 2e-2 * zz, 0 * yy, -2e-2 * xx
    gain = 1.0 - 0.6 * np.exp(-(zz / 1e-3) ** 2)
    measured_w = gain * w
    e = np.full(len(Z), 4.5)                      # one test pair's failure: every layer
    sigma = e[:, None, None] * np.abs(measured_w) + 1e-9
    tiny = np.full(w.shape, 1e-10)
    raw = depth_from_continuity(u, v, measured_w, tiny, tiny, sigma, X, Y, Z)
    fair = depth_from_continuity(u, v, measured_w, tiny, tiny,
                                 column_gain_sigma(sigma, measured_w, e), X, Y, Z)
    inside = np.abs(xx[0]) > 0                    # columns where w is not zero
    gain_of = [float(np.sum(f.w[:, inside] * w[:, inside]) / np.sum(w[:, inside] ** 2))
               for f in (raw, fair)]
    assert gain_of[1] == pytest.approx(np.mean(gain[:, 0, 0]), abs=1e-3)
    assert gain_of[0] < gain_of[1] - 0.05          # the raw weights lean on the focus


def test_column_gain_sigma_keeps_the_rest_of_the_uncertainty():
    rng = np.random.default_rng(2)
    w = rng.normal(size=(4, 3, 5))
    e = np.array([0.5, 1.0, 2.0, 0.0])
    rest = rng.uniform(0.1, 0.3, w.shape)
    sigma = np.sqrt(rest ** 2 + (e[:, None, None] * w) ** 2)
    col = np.sqrt(np.mean(w ** 2, axis=0))
    want = np.sqrt(rest ** 2 + (e[:, None, None] * col) ** 2)
    assert np.allclose(column_gain_sigma(sigma, w, e), want, rtol=1e-12)
    w[1, 0, 0] = np.nan                           # a NaN vector: NaN, its column still fair
    got = column_gain_sigma(np.where(np.isnan(w), np.nan, sigma), w, e)
    assert np.isnan(got[1, 0, 0]) and np.isfinite(got[0, 0, 0])


def test_the_pairs_fit_uses_the_response_gain_error_where_the_vectors_carry_it():
    (mu, mv, mw, su, sv, sw, *_), _ = oseen_fit()
    e = np.linspace(0.5, 2.0, len(Z))
    sigma = np.sqrt(sw ** 2 + (e[:, None, None] * mw) ** 2)
    vec = dataclasses.replace(as_vectors(mu, mv, mw, su, sv, sigma), w_gain_error=e)
    out, record = fitted_to_continuity(vec, PIVSettings())
    want = depth_from_continuity(mu, mv, mw, su, sv, column_gain_sigma(sigma, mw, e), X, Y, Z)
    assert record["applied"] and np.array_equal(out.w, want.w)
    plain, _ = fitted_to_continuity(dataclasses.replace(vec, w_gain_error=None), PIVSettings())
    assert not np.array_equal(plain.w, out.w)


@pytest.mark.parametrize("change", ["unit", "reversed flow", "layers reordered"])
def test_column_gain_sigma_does_not_depend_on_what_is_not_physical(change):
    """Metres or velocities (a scale), the flow run backwards (w → −w) or the layers listed
    in another order: the weights follow, nothing else moves."""
    rng = np.random.default_rng(5)
    w = rng.normal(size=(5, 3, 4))
    e = rng.uniform(0.2, 3.0, 5)
    sigma = np.sqrt(rng.uniform(0.1, 0.3, w.shape) ** 2 + (e[:, None, None] * w) ** 2)
    base = column_gain_sigma(sigma, w, e)
    if change == "unit":
        got, want = column_gain_sigma(sigma * 1e3, w * 1e3, e), base * 1e3
    elif change == "reversed flow":
        got, want = column_gain_sigma(sigma, -w, e), base
    else:
        order = rng.permutation(5)
        got, want = column_gain_sigma(sigma[order], w[order], e[order]), base[order]
    assert np.allclose(got, want, rtol=1e-12)
