"""Lenslet centres and the white image: where each lenslet is, and how large its micro-image.

Calibration step 2 (:func:`~plenopiv.calibration.calibrate.calibrate`):
:func:`lenslet_centres` (the spots of the alignment image, or the camera's nominal lattice),
:func:`pair_focal_spots` (each focal spot paired with its lenslet by position) and
:func:`measure_white_image` (the micro-image diameter of a white image,
:func:`micro_image_diameter`, against the one the camera's f-number models). Pixels are
``(row, col)`` with the centre of the top-left pixel at (0, 0) (:mod:`plenopiv.conventions`).

See docs/methods.md#lenslet-centres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from plenopiv.calibration.lattice_fit import fit_lattice
from plenopiv.calibration.lattice_quality import MIN_ON_LATTICE_FRACTION, check_lattice, swap_hint
from plenopiv.calibration.spot_detection import detect_spots
from plenopiv.calibration.spot_types import Lattice, SpotFlag, SpotSet
from plenopiv.camera.model import CameraModel
from plenopiv.camera.resolution import micro_image_diameter_px
from plenopiv.conventions import sensor_to_pixel
from plenopiv.errors import CalibrationError
from plenopiv.products.images import check_image

# the fewest focal spots paired with a lenslet centre that the focal-point fit accepts
MIN_PAIRED_SPOTS = 16


@dataclass(frozen=True)
class LensletCentres:
    """The lenslets of a camera: centres, lattice indices and where they came from.

    Attributes
    ----------
    centre_px : ndarray, shape (N, 2)
        Lenslet centres ``(row, col)``, px.
    grid_index : ndarray of int, shape (N, 2)
        Lattice index ``(row, col)`` of each lenslet.
    source : str
        ``"alignment image"`` or ``"nominal lattice"``.
    pitch_px : float
        Lenslet pitch, px.
    lattice : Lattice or None
        The alignment image's lattice, when there is one.
    spots : SpotSet or None
        The alignment image's spots, when there is one.
    """

    centre_px: np.ndarray
    grid_index: np.ndarray
    source: str
    pitch_px: float
    lattice: Lattice | None = None
    spots: SpotSet | None = None


def spot_lattice(image, camera: CameraModel, what: str, *, max_missing_fraction,
                 max_rms_residual_pitch=None, min_on_lattice_fraction=MIN_ON_LATTICE_FRACTION,
                 phase_harmonics=0, **detect_options):
    """Detect the spots of one calibration image, fit their lattice and check it.

    Parameters
    ----------
    image : ndarray, shape (R, C)
        A checked calibration image of ``camera``.
    camera : CameraModel
        Gives the grid type and the sensor shape, px.
    what : str
        How an error names the image (e.g. ``"the focal-point image"``).
    max_missing_fraction, max_rms_residual_pitch, min_on_lattice_fraction : float or None
        The limits of :func:`~plenopiv.calibration.lattice_quality.check_lattice`.
    phase_harmonics : int
        Passed to :func:`~plenopiv.calibration.lattice_fit.fit_lattice`.
    **detect_options
        Passed to :func:`~plenopiv.calibration.spot_detection.detect_spots`.

    Returns
    -------
    SpotSet, Lattice
    """
    grid = camera.microlens_array.grid
    spots = detect_spots(image, grid=grid, **detect_options)
    _check_spot_count(len(spots.centres_px), camera, what, max_missing_fraction)
    try:
        lattice = fit_lattice(spots, grid=grid, image_shape=camera.sensor.shape,
                              phase_harmonics=phase_harmonics, what=what)
    except CalibrationError as exc:
        if str(exc).startswith(what):
            raise
        raise CalibrationError(f"{what}: {exc}") from None
    check_lattice(lattice, what=what, max_missing_fraction=max_missing_fraction,
                  max_rms_residual_pitch=max_rms_residual_pitch,
                  min_on_lattice_fraction=min_on_lattice_fraction)
    return spots, lattice


FEW_SPOTS_FRACTION = 0.5
"""A calibration image lights every lenslet of its camera, one spot each, up to the missing
fraction it allows: one with fewer than this fraction of those shows scattered points."""


def _check_spot_count(n_spots: int, camera: CameraModel, what: str,
                      max_missing_fraction) -> None:
    """Refuse an image with far fewer spots than lenslets: a particle image or a scene."""
    n_lenslets = camera.microlens_array.count
    least = FEW_SPOTS_FRACTION * (1.0 - (max_missing_fraction or 0.0)) * n_lenslets
    if n_spots < least:
        raise CalibrationError(
            f"{what}: {n_spots} spots, where this camera's {n_lenslets} lenslets make one "
            f"each in a calibration image (at least {least:.0f} with max_missing_fraction = "
            f"{max_missing_fraction or 0:g}): it shows scattered points, not a lenslet "
            f"lattice; {swap_hint(what, 'a particle image or a scene')}")


def lenslet_centres(camera: CameraModel, alignment_image=None, *, dark=None, flat=None,
                    **lattice_options):
    """The lenslets of ``camera``: from its alignment image, or its nominal lattice.

    Parameters
    ----------
    camera : CameraModel
        The camera; its nominal lattice (with the configured offset and rotation) gives the
        centres when there is no alignment image.
    alignment_image : ndarray, optional
        Collimated light, main lens removed: one spot on each lenslet's axis.
    dark : DarkFrame, optional
        The dark frame (:class:`~plenopiv.calibration.defects.DarkFrame`) subtracted from
        the alignment image once checked.
    flat : WhiteFlat, optional
        The white's flat field (:class:`~plenopiv.calibration.defects.WhiteFlat`) applied
        after the dark.
    **lattice_options
        Passed to :func:`spot_lattice` (limits, ``phase_harmonics``, ``threshold``,
        ``method``).

    Returns
    -------
    LensletCentres
        From the alignment image: its complete lattice inliers, each at its best centre
        (:attr:`~plenopiv.calibration.spot_types.Lattice.best_centres_px`: the measured
        centre, less its sub-pixel phase bias, where the array scatters more than it is
        measured, its lattice node where not).
    """
    if alignment_image is None:
        shape, pp = camera.sensor.shape, camera.sensor.pixel_pitch
        mla = camera.microlens_array
        return LensletCentres(sensor_to_pixel(mla.centres(), shape, pp), mla.grid_index(),
                              "nominal lattice", camera.pitch_px)
    image = check_image(alignment_image, shape=camera.sensor.shape, name="alignment image")
    if dark is not None:
        image = dark.subtract(image)
    if flat is not None:
        image = flat.apply(image)
    # collimated light focuses to (almost) one pixel: accept one-pixel spots here, and never
    # take a spot's sharp core for a hot pixel; a hot pixel is then rejected by the lattice
    # fit as off-lattice instead
    spots, lat = spot_lattice(image, camera, "the alignment image", min_area_px=0.9,
                              hot_pixel_shapes=False, **lattice_options)
    ok = lat.inlier & ((lat.flags & SpotFlag.EDGE) == 0)
    return LensletCentres(lat.best_centres_px[ok], lat.grid_index[ok], "alignment image",
                          lat.lenslet_pitch_px, lat, spots)


def focal_spot_scale(focal_pitch_px: float, lenslet_pitch_px: float,
                     lenslets_from: str = "") -> float:
    """Ratio of the focal-spot pitch to the lenslet pitch, ``1 + f/S_i``; checked.

    ``lenslets_from``: where the lenslet pitch came from, for the message (e.g.
    ``"[microlens_array] pitch_um = 125 over [sensor] pixel_pitch_um = 7.4"``).

    Raises
    ------
    CalibrationError
        The ratio is not slightly above 1 (1 to 1.1): wrong camera file or image.
    """
    scale = focal_pitch_px / lenslet_pitch_px
    if not 1.0 < scale < 1.1:
        source = f" ({lenslets_from})" if lenslets_from else ""
        raise CalibrationError(
            f"the focal spots are {focal_pitch_px:.4g} px apart and the lenslets "
            f"{lenslet_pitch_px:.4g} px{source}: expected a ratio 1 + f̄/S_i slightly above 1 "
            f"(got {scale:.5f}); is that pitch wrong, or the image not a focal-point image of "
            "this camera?")
    return scale


def spots_inside(lenslets: LensletCentres, scale: float, shape, margin_px: float) -> np.ndarray:
    """Whether each lenslet's focal spot lies ``margin_px`` px inside the sensor's edge (bool).

    The focal spot is predicted by scaling the lenslet centre by ``scale`` about the sensor
    centre.
    """
    centre_rc = (np.array(shape) - 1) / 2.0
    predicted = centre_rc + (lenslets.centre_px - centre_rc) * scale
    return np.all((predicted >= margin_px) & (predicted <= np.array(shape) - 1 - margin_px),
                  axis=1)


def lenslets_on_sensor(lenslets: LensletCentres, scale: float, shape, margin_px: float = 0.0):
    """The lenslets whose focal spot lies on the sensor; a new :class:`LensletCentres`.

    The focal spot (:func:`spots_inside`) must lie ``margin_px`` px inside the sensor's edge.
    With the default 0, every lenslet whose micro-image centre is on the sensor is kept,
    however close to the edge: a rotated or hexagonal array brings the outer lenslets'
    spots within a spot window of the edge, where the spot cannot be measured but the
    micro-image's pixels still see the volume (their spots are then predicted by the fit).
    """
    inside = spots_inside(lenslets, scale, shape, margin_px)
    return LensletCentres(lenslets.centre_px[inside], lenslets.grid_index[inside],
                          lenslets.source, lenslets.pitch_px, lenslets.lattice, lenslets.spots)


def _pair(focal_px, lenslet_px, scale, centre_rc, max_dist):
    """Pair each focal spot with the nearest lenslet centre scaled about the sensor centre.

    ``centre_rc + (lenslet_px - centre_rc) * scale`` predicts each lenslet's focal spot;
    returns the lenslet index per spot (-1 if none within ``max_dist`` px).
    """
    predicted = centre_rc + (lenslet_px - centre_rc) * scale
    dist, idx = cKDTree(predicted).query(focal_px, distance_upper_bound=max_dist)
    idx = np.where(np.isfinite(dist), idx, -1)
    # one lenslet per spot
    seen = {}
    for i, j in enumerate(idx):
        if j < 0:
            continue
        if j in seen and dist[seen[j]] <= dist[i]:
            idx[i] = -1
            continue
        if j in seen:
            idx[seen[j]] = -1
        seen[j] = i
    return idx


def pair_focal_spots(focal_px, usable, lenslets: LensletCentres, scale: float, shape,
                     max_missing_fraction: float, margin_px: float = 0.0):
    """The focal spot of each lenslet: its index into ``focal_px``, -1 where none.

    Parameters
    ----------
    focal_px : ndarray, shape (M, 2)
        Focal-spot centres ``(row, col)``, px.
    usable : ndarray of bool, shape (M,)
        The spots that may be paired.
    lenslets : LensletCentres
        The lenslets whose focal spot is expected on the sensor.
    scale : float
        Focal-spot pitch over lenslet pitch (:func:`focal_spot_scale`).
    shape : tuple of int
        Sensor ``(rows, cols)``, px.
    max_missing_fraction : float
        Largest accepted fraction of lenslets without a focal spot.
    margin_px : float
        The fraction counts only the lenslets whose focal spot lies this far inside the
        sensor's edge (:func:`spots_inside`; a spot window: where it can be measured).

    Returns
    -------
    ndarray of int, shape (N,)

    Raises
    ------
    CalibrationError
        Fewer than 16 spots paired, or too many lenslets without a spot.
    """
    centre_rc = (np.array(shape) - 1) / 2.0
    pair = _pair(focal_px, lenslets.centre_px, scale, centre_rc, 0.35 * lenslets.pitch_px)
    use = usable & (pair >= 0)
    if use.sum() < MIN_PAIRED_SPOTS:
        raise CalibrationError(f"only {int(use.sum())} focal spots could be paired with a "
                               f"lenslet centre ({lenslets.source}): expected at least "
                               f"{MIN_PAIRED_SPOTS}")
    spot_of = np.full(len(lenslets.centre_px), -1)
    spot_of[pair[use]] = np.flatnonzero(use)
    counted = spots_inside(lenslets, scale, shape, margin_px)
    missing = np.flatnonzero((spot_of < 0) & counted)
    frac = len(missing) / max(int(counted.sum()), 1)
    if frac > max_missing_fraction:
        idx = lenslets.grid_index[missing]
        raise CalibrationError(
            f"{len(missing)} of {int(counted.sum())} lenslets ({frac:.0%}) have no focal "
            f"spot: expected at most {max_missing_fraction:.0%}; grid rows {idx[:, 0].min()}-"
            f"{idx[:, 0].max()}, cols {idx[:, 1].min()}-{idx[:, 1].max()} affected; check "
            "the focal-point image, the aperture and spot_threshold")
    return spot_of


def micro_image_diameter(image, centres_px, pitch_px):
    """Mean diameter (px) of the bright micro-images of a white (full-aperture) image.

    Each is ``2 sqrt(A / pi)``, ``A`` the number of pixels within half a pitch of its centre
    that are brighter than half its plateau (the median within 0.15 pitch of the centre,
    at least 1.5 px); only micro-images wholly inside the image count.

    Parameters
    ----------
    image : array_like, shape (R, C)
        Background-subtracted white image.
    centres_px : array_like, shape (N, 2)
        Micro-image centres ``(row, col)``, px.
    pitch_px : float
        Micro-image pitch, px.

    Raises
    ------
    CalibrationError
        No micro-image lies wholly inside the image.
    """
    w = np.asarray(image, float)
    h = int(math.ceil(pitch_px / 2)) + 1
    rr, cc = np.mgrid[-h : h + 1, -h : h + 1]
    core = max(0.15 * pitch_px, 1.5)
    out = []
    for r, c in np.asarray(centres_px, float):
        r0, c0 = int(round(r)), int(round(c))
        if r0 - h < 0 or c0 - h < 0 or r0 + h >= w.shape[0] or c0 + h >= w.shape[1]:
            continue
        patch = w[r0 - h : r0 + h + 1, c0 - h : c0 + h + 1]
        d = np.hypot(rr + r0 - r, cc + c0 - c)
        plateau = np.median(patch[d < core])
        area = np.count_nonzero((patch > 0.5 * plateau) & (d < pitch_px / 2))
        out.append(2.0 * math.sqrt(area / math.pi))
    if not out:
        raise CalibrationError("no complete micro-image to measure its diameter")
    return float(np.mean(out))


def measure_white_image(camera: CameraModel, white_image, image_distance: float, *,
                        dark=None, **limits) -> dict:
    """Measure the micro-image diameter of a white image and model it from the f-number.

    Parameters
    ----------
    camera : CameraModel
        The camera; its main-lens f-number models the diameter.
    white_image : ndarray, shape (R, C)
        A white image at the working aperture.
    image_distance : float
        The calibrated S_i, m.
    dark : DarkFrame, optional
        The dark frame (:class:`~plenopiv.calibration.defects.DarkFrame`) subtracted from
        the white image once checked; its hot pixels are patched.
    **limits
        The limits of the lattice check and ``bad_pixels`` (:func:`spot_lattice`).

    Returns
    -------
    dict
        ``micro_image_diameter_px`` (measured), ``modelled_diameter_px``, ``f_number``,
        ``model_over_measured`` and ``implied_f_number`` (the f-number that models the
        measured diameter).
    """
    shape = camera.sensor.shape
    wh = check_image(white_image, shape=shape, name="white image").astype(float)
    if dark is not None:
        wh = dark.subtract(wh, patch=True).astype(float)
    _spots, w_lat = spot_lattice(wh, camera, "the white image", **limits)
    complete = (w_lat.flags & SpotFlag.EDGE) == 0
    black = float(np.percentile(wh, 1.0))
    measured = micro_image_diameter(wh - black, w_lat.predict(w_lat.grid_index[complete]),
                                    w_lat.lenslet_pitch_px)
    n_f = camera.main_lens.f_number
    model = micro_image_diameter_px(camera, image_distance, n_f)
    return {"micro_image_diameter_px": measured, "modelled_diameter_px": model,
            "f_number": n_f, "model_over_measured": model / measured,
            "implied_f_number": n_f * model / measured}
