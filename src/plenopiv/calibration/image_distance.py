"""The image distance S_i: focal-point method, magnification (ruler) method, lens corrections.

:func:`fit_focal_points` fits S_i, the MLA offset and rotation to the focal spots (thesis
§3.2, §4.3, Eqs. 3.12-3.14) with the exact chief ray of :class:`SpotModel`;
:func:`magnification_from_ticks` gives S_i from a ruler's ticks (§3.1.2, Eqs. 3.3-3.4, with
the uncertainties of Eqs. 3.9-3.10); :func:`fit_linear_correction` and
:func:`fit_pupil_correction` fit the lens corrections of an extension-tube series (§5.5).
Lengths in metres, angles in radians, sensor positions (x, y) in metres from the sensor centre.

See docs/methods.md#image-distance-by-focal-point,
docs/methods.md#image-distance-by-magnification and docs/methods.md#lens-corrections.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from plenopiv.camera import optics
from plenopiv.camera.model import CameraModel, apply_misplacement
from plenopiv.errors import CalibrationError

MODELS = ("exact", "paraxial")


@dataclass(frozen=True)
class SpotModel:
    """What the focal-spot forward model needs besides S_i (metres)."""

    sensor_distance: float
    back_side: str = "physical"
    thickness: float = 0.0
    refractive_index: float = 1.0
    pupil_offset: float = 0.0
    stop_radius: float = 0.0

    @classmethod
    def from_camera(cls, camera: CameraModel, *, back_side: str | None = None,
                    ignore_substrate: bool = False,
                    focal_point_f_number: float | None = None) -> SpotModel:
        """The spot model of ``camera`` (optionally another back side, or without the plate).

        ``focal_point_f_number``: the stop of the focal-point image; the model then predicts
        each spot's centroid over that stop rather than its chief ray (they differ through a
        plate, see :func:`plenopiv.camera.optics.focal_spot_exact`).
        """
        mla = camera.microlens_array
        t = 0.0 if ignore_substrate else camera.plate_thickness
        n = 1.0 if ignore_substrate else camera.plate_index
        stop = 0.0 if focal_point_f_number is None else \
            camera.main_lens.focal_length / float(focal_point_f_number) / 2.0
        return cls(mla.sensor_distance, back_side or mla.back_side, t, n,
                   camera.main_lens.exit_pupil_offset, stop)

    def predict(self, centres, image_distance, *, model: str = "exact") -> np.ndarray:
        """Spot positions (N, 2), metres, for lenslet centres (N, 2) and S_i,eff.

        ``"exact"``: the exact chief ray, or with ``stop_radius`` the spot's centroid over
        the stop; ``"paraxial"``: Eq. 3.11 / 4.8.
        """
        kw = dict(back_side=self.back_side, thickness=self.thickness,
                  refractive_index=self.refractive_index, pupil_offset=self.pupil_offset)
        if model == "exact":
            return optics.focal_spot_exact(centres, image_distance, self.sensor_distance,
                                           stop_radius=self.stop_radius, **kw)
        if model == "paraxial":
            return np.asarray(centres) * optics.focal_spot_scale(image_distance,
                                                                 self.sensor_distance, **kw)
        raise ValueError(f"model = {model!r}: expected one of {MODELS}")

    def image_distance_from_scale(self, scale) -> np.ndarray:
        """Paraxial S_i,eff from a spot scale p/d (closed form)."""
        return optics.image_distance_from_spot_scale(
            scale, self.sensor_distance, back_side=self.back_side, thickness=self.thickness,
            refractive_index=self.refractive_index, pupil_offset=self.pupil_offset)


@dataclass(frozen=True)
class FocalPointFit:
    """Result of the focal-point method.

    Attributes
    ----------
    image_distance : float
        S_i,eff, metres.
    offset : (2,) ndarray
        MLA offset (s_o, t_o), metres (Eqs. 3.13-3.14).
    rotation : float
        γ, radians.
    sigma_image_distance, sigma_offset, sigma_rotation
        One-standard-deviation uncertainties from the Jacobian at the solution, scaled by the
        residual variance (metres, metres, radians).
    residual : (N, 2) ndarray
        Measured minus predicted spot positions, metres.
    rms_residual : float
        e_RMS of Eq. 3.12, metres.
    """

    image_distance: float
    offset: np.ndarray
    rotation: float
    sigma_image_distance: float
    sigma_offset: np.ndarray
    sigma_rotation: float
    residual: np.ndarray
    rms_residual: float
    model: SpotModel
    n_used: int
    first_guess: float
    extra: dict = field(default_factory=dict)


def _first_guess(d, p, spot: SpotModel, fit_misplacement: bool):
    """Linearised fit p ≈ k (d + o + γ J d): k, o, γ by linear least squares."""
    if fit_misplacement:
        n = len(d)
        a = np.zeros((2 * n, 4))
        a[0::2, 0], a[1::2, 0] = d[:, 0], d[:, 1]          # k
        a[0::2, 1], a[1::2, 2] = 1.0, 1.0                  # k o_s, k o_t
        a[0::2, 3], a[1::2, 3] = -d[:, 1], d[:, 0]         # k γ
        sol, *_ = np.linalg.lstsq(a, p.reshape(-1), rcond=None)
        k = sol[0]
        return k, sol[1:3] / k, sol[3] / k
    k = float((p * d).sum() / (d * d).sum())
    return k, np.zeros(2), 0.0


def fit_focal_points(lenslet_centres, focal_spots, spot_model: SpotModel, *,
                     fit_misplacement: bool = True, model: str = "exact",
                     weights=None) -> FocalPointFit:
    """Fit S_i (and the MLA offset and rotation) to measured focal spots (thesis Eq. 3.12).

    Parameters
    ----------
    lenslet_centres : array_like, shape (N, 2)
        Lenslet centres (x, y), metres from the sensor centre: the alignment-image spots, or
        the nominal lattice.
    focal_spots : array_like, shape (N, 2)
        Measured focal-spot centroids (x, y), metres, same order; NaN rows are ignored.
    spot_model : SpotModel
        f̄, back-side model, substrate and exit-pupil offset.
    fit_misplacement : bool
        Fit (s_o, t_o, γ) too (Eqs. 3.13-3.14); else only S_i.
    model : {"exact", "paraxial"}
        Forward model: the exact chief ray, or the paraxial Eq. 3.11 / 4.8.
    weights : array_like, shape (N,), optional
        Relative weights of the spots (e.g. inverse centroid variance).

    Returns
    -------
    FocalPointFit
    """
    if model not in MODELS:
        raise ValueError(f"model = {model!r}: expected one of {MODELS}")
    d = np.asarray(lenslet_centres, dtype=float)
    p = np.asarray(focal_spots, dtype=float)
    if d.shape != p.shape or d.ndim != 2 or d.shape[1] != 2:
        raise CalibrationError(f"lenslet centres {d.shape} and focal spots {p.shape}: expected "
                               "two (N, 2) arrays in the same order")
    ok = np.isfinite(d).all(axis=1) & np.isfinite(p).all(axis=1)
    need = 4 if fit_misplacement else 1
    if ok.sum() < max(need + 1, 3):
        raise CalibrationError(f"only {int(ok.sum())} lenslets have both a centre and a focal "
                               f"spot: expected at least {max(need + 1, 3)}")
    d, p = d[ok], p[ok]
    w = np.ones(len(d)) if weights is None else np.asarray(weights, dtype=float)[ok]
    sw = np.sqrt(w)[:, None]

    k0, o0, g0 = _first_guess(d, p, spot_model, fit_misplacement)
    if not k0 > 1:
        raise CalibrationError(f"the focal spots are not spread out from the lenslet centres "
                               f"(scale p/d = {k0:.6f}, expected > 1): wrong centres or image")
    si0 = float(spot_model.image_distance_from_scale(k0))
    if not si0 > 0:
        raise CalibrationError(f"closed-form first guess S_i = {si0:g} m is not positive")
    scale = np.array([si0, 1e-4, 1e-4, 1e-3])     # parameter scales: m, m, m, rad

    def unpack(x):
        x = x * scale[: len(x)]
        if fit_misplacement:
            return x[0], x[1:3], x[3]
        return x[0], np.zeros(2), 0.0

    def residual(x):
        si, o, g = unpack(x)
        pred = spot_model.predict(apply_misplacement(d, o, g), si, model=model)
        return ((p - pred) * sw).ravel()

    x0 = np.array([si0, *o0, g0]) if fit_misplacement else np.array([si0])
    x0 = x0 / scale[: len(x0)]
    sol = least_squares(residual, x0, method="lm", x_scale="jac", xtol=1e-15, ftol=1e-15,
                        gtol=1e-15, max_nfev=400)
    si, o, g = unpack(sol.x)
    if not (np.isfinite(si) and si > 0):
        raise CalibrationError(f"the focal-point fit diverged (S_i = {si!r})")
    r = residual(sol.x).reshape(-1, 2) / sw
    dof = max(r.size - len(sol.x), 1)
    s2 = float((residual(sol.x) ** 2).sum() / dof)
    jac = sol.jac
    try:
        cov = np.linalg.inv(jac.T @ jac) * s2
        sig = np.sqrt(np.clip(np.diag(cov), 0, None)) * scale[: len(sol.x)]
    except np.linalg.LinAlgError:
        sig = np.full(len(sol.x), np.nan)
    rms = float(np.sqrt((r ** 2).sum() / r.size))   # Eq. 3.12
    return FocalPointFit(
        image_distance=float(si), offset=np.asarray(o, float), rotation=float(g),
        sigma_image_distance=float(sig[0]),
        sigma_offset=(sig[1:3] if fit_misplacement else np.zeros(2)),
        sigma_rotation=float(sig[3]) if fit_misplacement else 0.0,
        residual=r, rms_residual=rms, model=spot_model, n_used=int(ok.sum()),
        first_guess=si0, extra={"nfev": int(sol.nfev), "status": int(sol.status)})


# --------------------------------------------------------------------------------------------
# Magnification (ruler) method
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MagnificationResult:
    """Result of the magnification method (metres, dimensionless M).

    Attributes
    ----------
    image_distance, object_distance : float
        S_i (Eq. 3.4) and S_o (Eq. 3.3).
    magnification : float
        M = -d_i/d_o (negative).
    sigma_depth_of_focus : float
        ΔS_i = M² (L1 + L2) (Eqs. 3.5-3.9).
    sigma_height : float
        ΔS_i from the uncertainty of the image-side span, f_m/d_o · Δd_i (Eq. 3.10).
    sigma_image_distance : float
        Both combined in quadrature.
    tick_positions : ndarray
        Image-side tick positions along the ruler axis, metres on the lenslet plane.
    """

    image_distance: float
    object_distance: float
    magnification: float
    sigma_depth_of_focus: float
    sigma_height: float
    sigma_image_distance: float
    tick_positions: np.ndarray
    tick_spacing_image: float
    tick_spacing_object: float


def magnification_from_ticks(tick_positions, tick_spacing, focal_length, f_number,
                             lenslet_pitch, *, position_sigma=None) -> MagnificationResult:
    """S_i from image-side positions of consecutive ruler ticks (thesis §3.1.2).

    Parameters
    ----------
    tick_positions : array_like
        Image-side positions (metres, on the lenslet plane) of ticks k = 0, 1, 2, ... in
        order; NaN for a tick that was not found (its index is kept).
    tick_spacing : float
        d_o between consecutive ticks on the ruler, metres.
    focal_length, f_number : float
        Main lens f_m (metres) and N of the ruler image.
    lenslet_pitch : float
        p_m, metres (the spatial resolution).
    position_sigma : float, optional
        Uncertainty of one tick position (metres); default from the line-fit residuals.
    """
    x = np.asarray(tick_positions, dtype=float)
    k = np.arange(len(x), dtype=float)
    ok = np.isfinite(x)
    if ok.sum() < 2:
        raise CalibrationError(f"{int(ok.sum())} ruler ticks found: expected at least 2")
    a = np.stack([k[ok], np.ones(ok.sum())], axis=1)
    (slope, intercept), *_ = np.linalg.lstsq(a, x[ok], rcond=None)
    d_i = abs(slope)                                    # image-side spacing per tick
    m = -d_i / tick_spacing
    si = float(optics.image_distance_from_magnification(focal_length, m))
    so = float(optics.object_distance_from_magnification(focal_length, m))
    sig_dof = optics.magnification_method_uncertainty(focal_length, f_number, si, lenslet_pitch)
    n = int(ok.sum())
    if position_sigma is None:
        resid = x[ok] - a @ np.array([slope, intercept])
        position_sigma = float(np.sqrt((resid ** 2).sum() / max(n - 2, 1))) if n > 2 else \
            lenslet_pitch / math.sqrt(12)
    # σ of the fitted slope times the number of spacings spanned = σ of the span d_i
    span_ticks = k[ok].max() - k[ok].min()
    sig_slope = position_sigma / math.sqrt(((k[ok] - k[ok].mean()) ** 2).sum())
    span_object = span_ticks * tick_spacing
    sig_height = optics.height_error_sensitivity(focal_length, span_object) * sig_slope \
        * span_ticks
    return MagnificationResult(
        image_distance=si, object_distance=so, magnification=m,
        sigma_depth_of_focus=float(sig_dof), sigma_height=float(sig_height),
        sigma_image_distance=float(math.hypot(sig_dof, sig_height)),
        tick_positions=x, tick_spacing_image=float(d_i), tick_spacing_object=float(tick_spacing))


def lenslet_integral_image(image, centres_px, grid_index, pitch_px) -> np.ndarray:
    """Sum of the pixels under each lenslet (the integral image), shape (rows, cols).

    Parameters
    ----------
    image : ndarray
        Raw plenoptic image.
    centres_px : (N, 2)
        Micro-image centres (row, col), pixels.
    grid_index : (N, 2) int
        Lattice index (row, col) of each lenslet.
    pitch_px : float
        Micro-image pitch, pixels; each lenslet sums the pixels within pitch/2 of its centre.
    """
    img = np.asarray(image, dtype=float)
    c = np.asarray(centres_px, dtype=float)
    idx = np.asarray(grid_index, dtype=int)
    half = int(math.ceil(pitch_px / 2))
    off = np.arange(-half, half + 1)
    rr = np.rint(c[:, 0]).astype(int)[:, None, None] + off[None, :, None]
    cc = np.rint(c[:, 1]).astype(int)[:, None, None] + off[None, None, :]
    inside = (rr >= 0) & (rr < img.shape[0]) & (cc >= 0) & (cc < img.shape[1])
    near = ((rr - c[:, 0, None, None]) ** 2 + (cc - c[:, 1, None, None]) ** 2
            <= (pitch_px / 2) ** 2) & inside
    vals = np.where(near, img[np.clip(rr, 0, img.shape[0] - 1), np.clip(cc, 0, img.shape[1] - 1)],
                    0.0)
    out = np.full((idx[:, 0].max() + 1, idx[:, 1].max() + 1), np.nan)
    out[idx[:, 0], idx[:, 1]] = vals.sum(axis=(1, 2))
    return out


def find_ruler_ticks(profile, *, min_depth=0.1):
    """Sub-sample positions of dark ticks along a 1-D lenslet profile.

    Parameters
    ----------
    profile : 1-D array
        Integral-image intensity along the ruler axis (one value per lenslet).
    min_depth : float
        A tick must darken a lenslet by at least this fraction of the median.

    Returns
    -------
    ndarray
        Tick positions in lenslet units (fractional index), each the darkness-weighted
        centroid of the lenslets the tick covers (sub-lenslet interpolation).
    """
    prof = np.asarray(profile, dtype=float)
    med = np.nanmedian(prof)
    if not med > 0:
        raise CalibrationError("the ruler image is dark along the ruler axis")
    dark = np.clip(1 - prof / med, 0, None)
    dark = np.nan_to_num(dark)
    ticks = []
    for k in range(1, len(prof) - 1):
        if dark[k] >= min_depth and dark[k] >= dark[k - 1] and dark[k] > dark[k + 1]:
            lo, hi = k - 1, k + 2
            w = dark[lo:hi]
            ticks.append(float((w * np.arange(lo, hi)).sum() / w.sum()))
    if len(ticks) < 2:
        raise CalibrationError(f"found {len(ticks)} ruler ticks: expected at least 2 dark "
                               f"ticks (min_depth {min_depth:.0%} of the median lenslet)")
    return np.array(ticks)


def index_ticks(ticks_lenslets) -> np.ndarray:
    """Number consecutive ticks k = 0, 1, ... allowing gaps; NaN where one was missed."""
    t = np.sort(np.asarray(ticks_lenslets, dtype=float))
    gaps = np.diff(t)
    step = np.median(gaps)
    k = np.concatenate([[0], np.cumsum(np.rint(gaps / step).astype(int))])
    out = np.full(k[-1] + 1, np.nan)
    out[k] = t
    return out


# --------------------------------------------------------------------------------------------
# Lens corrections (§5.5)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LinearCorrection:
    """S_i,corr = a S_i,o + b (thesis Eqs. 5.2-5.4); ``b`` in metres."""

    a: float
    b: float
    r_squared: float

    def apply(self, image_distance):
        """Corrected S_i (metres) from a focal-point value S_i,o (metres)."""
        return self.a * np.asarray(image_distance, dtype=float) + self.b


def fit_linear_correction(computed, known) -> LinearCorrection:
    """Fit the thesis's per-lens correction from an extension-tube series (metres)."""
    x, y = np.asarray(computed, float), np.asarray(known, float)
    if x.shape != y.shape or x.size < 2:
        raise CalibrationError("the lens correction needs at least two (computed, known) S_i "
                               "pairs of equal length")
    a, b = np.polyfit(x, y, 1)
    r2 = 1 - ((y - (a * x + b)) ** 2).sum() / ((y - y.mean()) ** 2).sum()
    return LinearCorrection(float(a), float(b), float(r2))


@dataclass(frozen=True)
class PupilCorrection:
    """Physical two-constant model: 1/(p/d - 1) = (D0 + Δ)/f̄_eff.

    Attributes
    ----------
    sensor_distance : float
        f̄_eff, the camera constant (lenslet plane to sensor), metres.
    pupil_distance : float
        D0, the air-equivalent distance from the exit pupil to the lenslets without tubes, m.
    pupil_offset : float or None
        e = S_i,0 - D0 when the image distance without tubes S_i,0 is known, metres.
    """

    sensor_distance: float
    pupil_distance: float
    pupil_offset: float | None
    sigma_sensor_distance: float
    sigma_pupil_distance: float

    def image_distance(self, spot_scale):
        """S_i,eff (metres) from a measured spot scale p/d (needs ``pupil_offset``)."""
        if self.pupil_offset is None:
            raise CalibrationError("the pupil model needs the image distance without tubes "
                                   "(S_i,0) to give absolute image distances")
        return self.sensor_distance / (np.asarray(spot_scale, float) - 1) + self.pupil_offset


def fit_pupil_correction(spot_scales, tube_lengths, *, base_image_distance=None
                         ) -> PupilCorrection:
    """Fit f̄_eff and the pupil distance D0 from spot scales of an extension-tube series.

    Parameters
    ----------
    spot_scales : array_like
        Measured p/d for each image (e.g. 1 + f̄/(S_i - e) from a paraxial fit).
    tube_lengths : array_like
        Extension Δ of each image, metres (0 for none).
    base_image_distance : float, optional
        S_i,0 without tubes (metres), e.g. from the magnification method; gives the pupil
        offset e = S_i,0 - D0.

    Notes
    -----
    Chief rays leave from the exit pupil, a distance D0 + Δ from the lenslets, so
    p/d - 1 = f̄/(D0 + Δ): the line y = 1/(p/d - 1) = Δ/f̄ + D0/f̄ has slope 1/f̄_eff and
    intercept D0/f̄_eff (docs/design.md §4).
    """
    k = np.asarray(spot_scales, float)
    dl = np.asarray(tube_lengths, float)
    if k.shape != dl.shape or k.size < 2 or np.ptp(dl) <= 0:
        raise CalibrationError("the pupil model needs at least two images with different "
                               "tube lengths")
    y = 1.0 / (k - 1.0)
    a = np.stack([dl, np.ones_like(dl)], axis=1)
    (slope, icpt), *_ = np.linalg.lstsq(a, y, rcond=None)
    resid = y - a @ np.array([slope, icpt])
    dof = max(len(y) - 2, 1)
    cov = np.linalg.inv(a.T @ a) * (resid @ resid) / dof
    fbar = 1.0 / slope
    d0 = icpt / slope
    sig_fbar = math.sqrt(cov[0, 0]) / slope ** 2
    sig_d0 = math.sqrt(cov[1, 1] / slope ** 2 + icpt ** 2 * cov[0, 0] / slope ** 4
                       - 2 * icpt * cov[0, 1] / slope ** 3) if dof > 0 else float("nan")
    e = None if base_image_distance is None else float(base_image_distance - d0)
    return PupilCorrection(float(fbar), float(d0), e, float(sig_fbar), float(sig_d0))
