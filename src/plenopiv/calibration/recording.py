"""A recording checked against its calibration: its micro-images where the calibration says.

Between the calibration and the recording the lenslet array may have moved on the sensor (a
knock, a temperature change, a remounted camera). Every ray of the reconstruction is then
wrong by the same fraction of a pixel, and nothing else says so. :func:`check_recording`
measures the micro-image lattice of the recording itself (the mean of a pair or of a batch
shows the micro-images: particle light falls only inside them) against the calibration's:
the shift and rotation that best lay the calibration's micro-image discs over the recorded
light. Beyond a tolerance it refuses with the figure, or, when allowed, moves the
calibration onto the recording and warns. Pixels are ``(row, col)``; the rotation is
counter-clockwise in ``(x = col, y = row)`` about the sensor's centre, as the lattice's. See
docs/methods.md#recording-against-calibration.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy.spatial import cKDTree

from plenopiv._threads import thread_count
from plenopiv.calibration._recording_kernels import soft_discs
from plenopiv.camera.resolution import micro_image_diameter_px
from plenopiv.errors import CalibrationError, PlenopivWarning

#: The default tolerance: the largest displacement of a micro-image, px, accepted as is
TOLERANCE_PX = 0.25
# tiles of about this many lenslets a side measure one shift each
_TILE_LENSLETS = 6
# a tile counts when its correlation peak stands this far above the correlation at half a
# pitch from it (relative), and it holds this fraction of the median tile's light
_MIN_CONTRAST = 0.2
_MIN_LIGHT = 0.1
# the fewest tiles that measure a shift and rotation, and the most their shifts may scatter
# about the fitted ones, a fraction of the pitch (an image with no micro-images scatters
# across the whole cell)
_MIN_TILES = 4

#: A recording is refused (or corrected) only when its micro-images lie beyond the tolerance
#: by this many standard errors of the measurement: a sparse pair's mean shows its
#: micro-images faintly, and its estimate scatters (at 2 standard errors an exact calibration
#: of a 30-particle pair was refused).
SIGNIFICANCE = 3.0
_MAX_TILE_SPREAD = 0.1
# a soft disc's edge, px (the correlation surface is then smooth enough for a parabola)
_EDGE_PX = 1.0
# the most tiles transformed at once
_TILE_BATCH = 256
# the second pass (discs moved by the first pass's estimate) is left out when that estimate
# moves no micro-image by more than this, px: the parabola's bias on so small a shift is a
# small fraction of it, far below TOLERANCE_PX
_SETTLED_PX = 0.02


@dataclass(frozen=True)
class LatticeCheck:
    """The recording's micro-image lattice against the calibration's.

    Attributes
    ----------
    measured : bool
        Whether the recording showed enough micro-images to measure (else the figures are
        NaN and nothing was decided).
    shift_px : ndarray, shape (2,)
        Shift ``(d_row, d_col)`` of the recording's micro-images from the calibration's, px.
    rotation_rad : float
        Their rotation about the sensor's centre, rad.
    max_displacement_px : float
        The largest displacement of a micro-image by that shift and rotation, px.
    sigma_px : float
        Standard error of ``max_displacement_px``, px (from the scatter of the tiles).
    n_tiles : int
        Tiles of the image that measured a shift.
    tolerance_px : float
        The tolerance it was checked against, px.
    corrected : bool
        Whether the calibration was moved onto the recording.
    note : str
        Why nothing was measured, or empty.
    calibration : Calibration or None
        The calibration to reconstruct the recording with: the one checked, or, corrected,
        that one moved onto the recording.
    """

    measured: bool
    shift_px: np.ndarray
    rotation_rad: float
    max_displacement_px: float
    sigma_px: float
    n_tiles: int
    tolerance_px: float
    corrected: bool = False
    note: str = ""
    calibration: object = dataclasses.field(default=None, repr=False, compare=False)

    @property
    def beyond_tolerance(self) -> bool:
        """Measured, and beyond the tolerance by more than :data:`SIGNIFICANCE` standard errors."""
        return bool(self.measured and self.max_displacement_px > self.tolerance_px
                    and self.max_displacement_px - self.tolerance_px
                    > SIGNIFICANCE * self.sigma_px)

    def summary(self) -> dict:
        """The check as a JSON-ready dict."""
        return {"measured": self.measured, "shift_px": [float(v) for v in self.shift_px],
                "rotation_rad": float(self.rotation_rad),
                "max_displacement_px": float(self.max_displacement_px),
                "sigma_px": float(self.sigma_px), "n_tiles": int(self.n_tiles),
                "tolerance_px": float(self.tolerance_px), "corrected": self.corrected,
                "note": self.note}


def check_recording(calibration, images, *, tolerance_px: float = TOLERANCE_PX,
                    correct: bool = False, f_number: float | None = None):
    """Check that a recording's micro-images lie where its calibration puts them.

    Parameters
    ----------
    calibration : Calibration
        The calibration the recording is to be reconstructed with.
    images : ndarray, shape (R, C) or (K, R, C), or a sequence of (R, C) arrays
        The recording: one image, a pair or a batch (their mean is measured).
    tolerance_px : float
        The largest displacement of a micro-image accepted, px (default 0.25).
    correct : bool
        Beyond the tolerance: False (default) raises; True moves the calibration's lenslet
        centres and focal spots by the measured shift and rotation and warns.
    f_number : float, optional
        The recording's aperture (default the camera's): sizes the micro-image discs.

    Returns
    -------
    LatticeCheck
        The measured shift (``shift_px``, ``(d_row, d_col)``) and rotation
        (``rotation_rad``), the largest displacement of a micro-image and its standard error;
        its ``calibration`` is the one to reconstruct with (``calibration`` itself unless
        corrected).

    Raises
    ------
    CalibrationError
        The micro-images are displaced beyond the tolerance and ``correct`` is False (the
        message gives the shift, the rotation and the largest displacement); or the images do
        not have the calibration's sensor shape.

    Notes
    -----
    Soft discs at the calibration's micro-images are cross-correlated with the mean image in
    tiles of about 6 x 6 lenslets; the tiles' shifts give a shift and a rotation about the
    sensor's centre (docs/methods.md#recording-against-calibration). The micro-images repeat
    with the pitch, so a shift is found modulo the pitch.
    """
    tol = float(tolerance_px)
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(f"tolerance_px = {tolerance_px!r}: expected a finite number > 0")
    shape = tuple(calibration.camera.sensor.shape)
    mean = _mean_image(images, shape)
    spots = np.asarray(calibration.focal_spot_px, dtype=np.float64)
    pitch = _pitch(spots)
    n_f = calibration.camera.main_lens.f_number if f_number is None else float(f_number)
    diameter = micro_image_diameter_px(calibration.camera, calibration.image_distance, n_f)
    radius = 0.5 * min(diameter, pitch)
    centre = (np.array(shape, dtype=np.float64) - 1.0) / 2.0
    shift, theta, sigma, n_tiles, note = np.zeros(2), 0.0, math.nan, 0, ""
    for _ in range(2):
        moved = _transform(spots, shift, theta, centre)
        tiles = _tile_shifts(mean, moved, radius, pitch)
        if len(tiles[0]) < _MIN_TILES:
            note = (f"only {len(tiles[0])} tiles of the recording show micro-images (at least "
                    f"{_MIN_TILES}): too little light to measure its lattice")
            break
        d_shift, d_theta, sigma, n_tiles, spread = _fit_transform(*tiles, centre, spots)
        if spread > _MAX_TILE_SPREAD * pitch:
            note = (f"the tiles of the recording disagree on its micro-images' shift by "
                    f"{spread:.2f} px rms (more than {_MAX_TILE_SPREAD:g} of the pitch): no "
                    "micro-image lattice to measure")
            break
        shift, theta = shift + d_shift, theta + d_theta
        if np.hypot(*(_transform(spots, shift, theta, centre) - spots).T).max() < _SETTLED_PX:
            break
    measured = not note
    if measured:
        disp = np.hypot(*(_transform(spots, shift, theta, centre) - spots).T)
        max_disp = float(disp.max())
    else:
        shift, theta, max_disp, sigma = np.full(2, np.nan), math.nan, math.nan, math.nan
    check = LatticeCheck(measured, shift, float(theta), max_disp, float(sigma), n_tiles, tol,
                         note=note, calibration=calibration)
    if not check.beyond_tolerance:
        return check
    figure = (f"the recording's micro-images lie up to {max_disp:.2f} ± {sigma:.2f} px from "
              f"the calibration's (shift {shift[0]:+.2f}, {shift[1]:+.2f} px (row, col), "
              f"rotation {theta * 1e3:+.3f} mrad about the sensor's centre, {n_tiles} tiles)")
    if not correct:
        raise CalibrationError(
            f"{figure}: more than lattice_tolerance_px = {tol:g} px; the lenslet array moved "
            "since the calibration: recalibrate, or let the calibration follow the recording "
            "([reconstruction] lattice_check = \"correct\", or check_recording(..., "
            "correct=True))")
    warnings.warn(f"{figure}: more than lattice_tolerance_px = {tol:g} px; the calibration's "
                  "lenslet centres and focal spots are moved onto the recording "
                  "([reconstruction] lattice_check = \"correct\")", PlenopivWarning,
                  stacklevel=2)
    moved = dataclasses.replace(
        calibration,
        centre_px=_transform(np.asarray(calibration.centre_px, float), shift, theta, centre),
        focal_spot_px=_transform(spots, shift, theta, centre),
        extra={**calibration.extra, "lattice_check": check.summary() | {"corrected": True}})
    return dataclasses.replace(check, corrected=True, calibration=moved)


def _mean_image(images, shape):
    """The mean of one image, a stack or a sequence of images of ``shape``, float64."""
    if isinstance(images, np.ndarray) and images.ndim == 2:
        stack = [images]
    elif isinstance(images, np.ndarray) and images.ndim == 3:
        stack = list(images)
    else:
        stack = list(images)
    if not stack:
        raise CalibrationError("check_recording: no image given")
    total = np.zeros(shape)
    for k, img in enumerate(stack):
        a = np.asarray(img, dtype=np.float64)
        if a.shape != shape:
            raise CalibrationError(f"check_recording: image {k} is {a.shape[0]} × {a.shape[1]} "
                                   f"pixels but the calibration's sensor is {shape[0]} × "
                                   f"{shape[1]}")
        total += a
    return total / len(stack)


def _pitch(spots):
    """The micro-images' pitch: the median nearest-neighbour distance, px."""
    if len(spots) < 2:
        raise CalibrationError("check_recording: the calibration has fewer than 2 lenslets")
    d, _ = cKDTree(spots).query(spots, k=2)
    return float(np.median(d[:, 1]))


def _transform(points, shift, theta, centre):
    """``points`` rotated by ``theta`` about ``centre`` and shifted, ``(row, col)`` px.

    Counter-clockwise in ``(x = col, y = row)``: ``d_col' = cos d_col - sin d_row``,
    ``d_row' = sin d_col + cos d_row``.
    """
    d = points - centre
    c, s = math.cos(theta), math.sin(theta)
    rot = np.column_stack([s * d[:, 1] + c * d[:, 0], c * d[:, 1] - s * d[:, 0]])
    return centre + rot + np.asarray(shift, dtype=np.float64)


def _tile_shifts(mean, spots, radius, pitch):
    """Per tile: the shift of the recorded light from the discs at ``spots``, px.

    Returns the tiles' shifts (T, 2), their centres (T, 2) and their lights (T,), for the
    tiles that count (module notes of :func:`check_recording`).
    """
    size = max(int(round(_TILE_LENSLETS * pitch)), 16)
    reach = max(int(0.45 * pitch), 1)
    half = max(int(round(0.5 * pitch)), 1)
    full = reach + half + 1
    tiles = _tiles_with_spots(mean.shape, spots, size, pitch)
    lights = _tile_lights(mean, tiles)
    floor = _MIN_LIGHT * float(np.median(lights)) if len(lights) else 0.0
    tiles = [t for t, light in zip(tiles, lights, strict=True) if light > floor and light > 0]
    lights = lights[(lights > floor) & (lights > 0)]
    corrs = _tile_correlations(mean, soft_discs(mean.shape, spots, radius, _EDGE_PX), tiles,
                               full)
    out_shift, out_centre, out_light = [], [], []
    for (r0, c0, r1, c1), light, corr in zip(tiles, lights, corrs, strict=True):
        inner = corr[full - reach:full + reach + 1, full - reach:full + reach + 1]
        k = np.unravel_index(int(np.argmax(inner)), inner.shape)
        kr, kc = k[0] + full - reach, k[1] + full - reach
        peak = corr[kr, kc]
        # half a pitch away on both axes the discs fall on the gaps between them
        anti = max(corr[kr + a, kc + b] for a in (-half, half) for b in (-half, half))
        if not (peak > 0 and peak - anti >= _MIN_CONTRAST * (abs(peak) + abs(anti))):
            continue
        if min(k) == 0 or max(k) == 2 * reach:
            continue
        sub = (_parabola(corr[kr - 1, kc], peak, corr[kr + 1, kc]),
               _parabola(corr[kr, kc - 1], peak, corr[kr, kc + 1]))
        out_shift.append((kr - full + sub[0], kc - full + sub[1]))
        out_centre.append((0.5 * (r0 + r1 - 1), 0.5 * (c0 + c1 - 1)))
        out_light.append(float(light))
    return (np.array(out_shift, dtype=np.float64).reshape(-1, 2),
            np.array(out_centre, dtype=np.float64).reshape(-1, 2), np.array(out_light))


def _tiles_with_spots(shape, spots, size, pitch):
    """The tiles ``(r0, c0, r1, c1)`` that hold at least 4 spots within a pitch of them.

    Tiles of ``size`` px a side, row by row (the last row and column may be smaller).
    """
    order = np.argsort(spots[:, 0], kind="stable")
    rows, cols = spots[order, 0], spots[order, 1]
    tiles = []
    for r0 in range(0, shape[0] - size // 2, size):
        r1 = min(r0 + size, shape[0])
        lo, hi = np.searchsorted(rows, [r0 - pitch, r1 + pitch], side="left")
        band = np.sort(cols[lo:hi])
        for c0 in range(0, shape[1] - size // 2, size):
            c1 = min(c0 + size, shape[1])
            a, b = np.searchsorted(band, [c0 - pitch, c1 + pitch], side="left")
            if b - a >= 4:
                tiles.append((r0, c0, r1, c1))
    return tiles


def _by_shape(tiles):
    """The tiles' indices grouped by their shape ``(rows, cols)``.

    In chunks of at most :data:`_TILE_BATCH` tiles: bounded memory for a 16 MP sensor.
    """
    groups: dict = {}
    for k, (r0, c0, r1, c1) in enumerate(tiles):
        groups.setdefault((r1 - r0, c1 - c0), []).append(k)
    for shape, ks in groups.items():
        for i in range(0, len(ks), _TILE_BATCH):
            yield shape, ks[i:i + _TILE_BATCH]


def _stack(image, tiles, ks):
    """The tiles ``ks`` of ``image`` (all of one shape) as a stack (K, rows, cols)."""
    return np.stack([image[tiles[k][0]:tiles[k][2], tiles[k][1]:tiles[k][3]] for k in ks])


def _tile_lights(mean, tiles):
    """Each tile's light above its median, ``sum(max(m - median(m), 0))`` (T,)."""
    lights = np.zeros(len(tiles))
    for _, ks in _by_shape(tiles):
        m = _stack(mean, tiles, ks)
        med = np.median(m.reshape(len(ks), -1), axis=1)[:, None, None]
        lights[ks] = np.sum(np.clip(m - med, 0.0, None), axis=(1, 2))
    return lights


def _tile_correlations(mean, model, tiles, reach):
    """Each tile of ``mean`` correlated with the same tile of ``model``, both less their mean.

    :func:`_correlation` for shifts up to ``reach`` px, (T, 2 reach + 1, 2 reach + 1); the
    tiles of one shape are transformed together.
    """
    out = np.empty((len(tiles), 2 * reach + 1, 2 * reach + 1))
    for (h, w), ks in _by_shape(tiles):
        m = _stack(mean, tiles, ks)
        d = _stack(model, tiles, ks)
        m = m - m.mean(axis=(1, 2), keepdims=True)
        d = d - d.mean(axis=(1, 2), keepdims=True)
        # at least the tile and the shifts (no wrap-around), of sizes the FFT does fast
        shape = tuple(scipy.fft.next_fast_len(n + 2 * reach, real=True) for n in (h, w))
        workers = thread_count()
        spectrum = (scipy.fft.rfft2(m, shape, axes=(1, 2), workers=workers)
                    * np.conj(scipy.fft.rfft2(d, shape, axes=(1, 2), workers=workers)))
        corr = scipy.fft.irfft2(spectrum, shape, axes=(1, 2), workers=workers)
        idx = np.r_[np.arange(-reach, reach + 1)] % np.array(shape)[:, None]
        out[ks] = corr[:, idx[0][:, None], idx[1][None, :]]
    return out


def _correlation(m, w, reach):
    """``sum_x m(x) w(x - s)`` for shifts ``s`` of up to ``reach`` px, shape (2r+1, 2r+1).

    One tile at a time: the NumPy twin of :func:`_tile_correlations`.
    """
    shape = (m.shape[0] + 2 * reach, m.shape[1] + 2 * reach)
    fm = np.fft.rfft2(m, shape)
    fw = np.fft.rfft2(w, shape)
    full = np.fft.irfft2(fm * np.conj(fw), shape)
    idx = np.r_[np.arange(-reach, reach + 1)] % np.array(shape)[:, None]
    return full[np.ix_(idx[0], idx[1])]


def _parabola(left, mid, right):
    """Sub-pixel offset of a peak from three samples (0 when they do not make one)."""
    den = left - 2.0 * mid + right
    return float(np.clip(0.5 * (left - right) / den, -0.5, 0.5)) if den < 0 else 0.0


def _fit_transform(shifts, centres, lights, centre, spots):
    """Shift and rotation about ``centre`` fitted to the tiles' shifts; their spread.

    Least squares of ``d_row = t_r + theta (col - c_col)``, ``d_col = t_c - theta (row -
    c_row)`` over the tiles, twice, leaving out tiles beyond 3 robust standard deviations.
    Returns the shift (2,), the rotation, the standard error of the largest displacement of
    a micro-image (``spots``), the tiles used and the rms of their residuals, px.
    """
    d = centres - centre
    n = len(shifts)
    a = np.zeros((2 * n, 3))
    a[:n, 0], a[:n, 2] = 1.0, d[:, 1]
    a[n:, 1], a[n:, 2] = 1.0, -d[:, 0]
    y = np.concatenate([shifts[:, 0], shifts[:, 1]])
    use = np.ones(2 * n, dtype=bool)
    for _ in range(3):
        coef, *_ = np.linalg.lstsq(a[use], y[use], rcond=None)
        res = y - a @ coef
        scale = 1.4826 * float(np.median(np.abs(res[use]))) + 1e-3
        keep = np.abs(res) <= 3.0 * scale
        keep = keep[:n] & keep[n:]
        use = np.concatenate([keep, keep])
        if use.sum() < 2 * _MIN_TILES:
            use[:] = True
            break
    coef, *_ = np.linalg.lstsq(a[use], y[use], rcond=None)
    res = y[use] - a[use] @ coef
    dof = max(int(use.sum()) - 3, 1)
    s2 = float(res @ res) / dof
    cov = np.linalg.pinv(a[use].T @ a[use]) * s2
    # the largest displacement is at the farthest micro-image: its variance
    far = spots[np.argmax(np.hypot(*(spots - centre).T))] - centre
    g = np.array([[1.0, 0.0, far[1]], [0.0, 1.0, -far[0]]])
    sigma = float(math.sqrt(max(np.max(np.diag(g @ cov @ g.T)), 0.0)))
    return coef[:2], float(coef[2]), sigma, int(use.sum() // 2), float(math.sqrt(2.0 * s2))
