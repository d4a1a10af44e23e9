"""Accuracy of a measured displacement field against a known one: gain, bias and rms.

One function, :func:`gain_bias_rms`, used by every validation (vortex study, ``plenopiv demo``,
``plenopiv validate``, the full-camera benchmark), so that they all report the same figures.

A bias and an rms alone can hide a measurement that is systematically too small: on an
antisymmetric flow (a vortex) an under-measured component has zero mean error, and its rms
error is bounded by the rms of the flow itself. The **gain**, the least-squares slope of the
measured against the true displacement, shows it directly: 1 for a measurement at true size,
0.5 for one at half size.
"""

from __future__ import annotations

import numpy as np

__all__ = ["gain_bias_rms"]

#: A component whose true values vary by less than this fraction of their rms (or not at all)
#: has no defined gain (a uniform shift): NaN is returned.
_MIN_SPREAD = 1e-6


def gain_bias_rms(measured, true, mask=None) -> dict:
    """Gain, offset, bias and rms of measured against true displacements, per component.

    Parameters
    ----------
    measured, true : array_like, shape (C, ...)
        Displacement components first (e.g. ``(3, nz, ny, nx)`` for u, v, w, or ``(3, N)``),
        in one unit (voxels, say); the figures come back in that unit.
    mask : array_like of bool, shape (...), optional
        The samples to use (e.g. valid vectors inside the volume); all of them if None.
        Samples where either array is not finite are left out.

    Returns
    -------
    dict
        ``n`` (samples used); per component, lists of length C: ``gain``, the least-squares
        slope of measured on true (``cov(m, t) / var(t)``, NaN where the true values do not
        vary); ``gain_se``, its standard error for independent samples (residual rms about
        the line over the spread of t and sqrt(n - 2); vectors of overlapping windows are
        not independent, so read it as a lower bound); ``offset``, the intercept of that
        line; ``correlation``, Pearson's r (NaN likewise); ``bias``, mean(m - t); ``rms``,
        sqrt(mean((m - t)²)); ``true_rms``, sqrt(mean(t²)), the size of the flow for
        comparison. With no sample every figure is NaN.

    Examples
    --------
    >>> t = np.array([[-2.0, -1.0, 0.0, 1.0, 2.0]])
    >>> r = gain_bias_rms(0.5 * t + 0.1, t)
    >>> round(r["gain"][0], 6), round(r["bias"][0], 6)
    (0.5, 0.1)
    """
    m = np.asarray(measured, dtype=float)
    t = np.asarray(true, dtype=float)
    if m.shape != t.shape or m.ndim < 1:
        raise ValueError(f"measured has shape {m.shape} and true {t.shape}: expected two "
                         "arrays of one (C, ...) shape, components first")
    c = m.shape[0]
    m = m.reshape(c, -1)
    t = t.reshape(c, -1)
    ok = np.all(np.isfinite(m) & np.isfinite(t), axis=0)
    if mask is not None:
        mk = np.asarray(mask, dtype=bool)
        if mk.size != ok.size:
            raise ValueError(f"mask has shape {mk.shape}: expected {tuple(np.shape(measured))[1:]}")
        ok &= mk.ravel()
    m, t = m[:, ok], t[:, ok]
    n = int(ok.sum())
    nan = [float("nan")] * c
    if n == 0:
        return {"n": 0, "gain": nan, "gain_se": nan, "offset": nan, "correlation": nan,
                "bias": nan, "rms": nan, "true_rms": nan}
    err = m - t
    tm, mm = t.mean(axis=1), m.mean(axis=1)
    dt, dm = t - tm[:, None], m - mm[:, None]
    var_t = (dt ** 2).mean(axis=1)
    var_m = (dm ** 2).mean(axis=1)
    cov = (dt * dm).mean(axis=1)
    true_rms = np.sqrt((t ** 2).mean(axis=1))
    varies = (n > 1) & (np.sqrt(var_t) > _MIN_SPREAD * np.maximum(true_rms, np.finfo(float).tiny))
    with np.errstate(invalid="ignore", divide="ignore"):
        gain = np.where(varies, cov / np.where(varies, var_t, 1.0), np.nan)
        corr = np.where(varies & (var_m > 0), cov / np.sqrt(var_t * np.where(var_m > 0, var_m, 1)),
                        np.nan)
    offset = np.where(varies, mm - gain * tm, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        resid = dm - np.where(varies, gain, 0.0)[:, None] * dt
        gain_se = np.where(varies & (n > 2), np.sqrt((resid ** 2).sum(axis=1) / max(n - 2, 1)
                                                     / np.where(varies, var_t * n, 1.0)),
                           np.nan)
    return {"n": n, "gain": gain.tolist(), "gain_se": gain_se.tolist(),
            "offset": offset.tolist(),
            "correlation": corr.tolist(), "bias": err.mean(axis=1).tolist(),
            "rms": np.sqrt((err ** 2).mean(axis=1)).tolist(), "true_rms": true_rms.tolist()}
