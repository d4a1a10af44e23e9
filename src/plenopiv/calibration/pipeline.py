"""Calibrate a camera from its images: focal-point (+ alignment) (+ ruler) -> Calibration.

Steps, each a stage function of the calibration package:

1. :func:`~plenopiv.calibration.spots.detect_spots` and
   :func:`~plenopiv.calibration.spots.fit_lattice` on the focal-point image: one focal spot
   (micro-image centre) per lenslet, with its lattice index; missing spots are listed.
2. Lenslet centres: the spots of the alignment image (collimated light), or, without one,
   the camera's nominal lattice (with its configured offset and rotation). Each focal spot is
   paired with its lenslet by position.
3. :func:`~plenopiv.calibration.image_distance.fit_focal_points`: S_i, MLA offset, rotation.
4. Optionally the magnification method on a ruler image.

Orchestration lives here; file I/O and reporting live in the CLI.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from plenopiv.calibration.image_distance import (
    FocalPointFit,
    MagnificationResult,
    SpotModel,
    find_ruler_ticks,
    fit_focal_points,
    index_ticks,
    lenslet_integral_image,
    magnification_from_ticks,
)
from plenopiv.calibration.model import Calibration
from plenopiv.calibration.spots import (
    MAX_MISSING_FRACTION,
    MAX_RMS_RESIDUAL_PITCH,
    Lattice,
    SpotFlag,
    SpotSet,
    check_lattice,
    detect_spots,
    fit_lattice,
    micro_image_diameter,
)
from plenopiv.camera import CameraModel, apply_misplacement
from plenopiv.conventions import pixel_to_sensor, sensor_to_pixel
from plenopiv.errors import CalibrationError
from plenopiv.lightfield import MICRO_IMAGE_TOLERANCE, micro_image_diameter_px
from plenopiv.products.images import check_image

METHODS = ("focal-point", "magnification", "both")
# harmonics of the sub-pixel phase bias fitted with each lattice (fit_lattice)
PHASE_HARMONICS = 2


@dataclass(frozen=True)
class CalibrationReport:
    """Everything measured on the way to a :class:`Calibration` (for reports and JSON)."""

    calibration: Calibration
    focal_lattice: Lattice
    alignment_lattice: Lattice | None
    focal_fit: FocalPointFit | None
    magnification: MagnificationResult | None
    n_missing: int
    missing_index: np.ndarray
    lenslet_source: str
    fit_spots_px: np.ndarray
    notes: list = field(default_factory=list)
    focal_spots: SpotSet | None = None
    alignment_spots: SpotSet | None = None
    white: dict | None = None

    def summary(self) -> dict:
        """The one-object JSON summary of ``plenopiv calibrate --json``."""
        cal = self.calibration
        out = {
            "image_distance_mm": cal.image_distance * 1e3,
            "method": cal.method,
            "offset_um": [v * 1e6 for v in cal.offset],
            "rotation_rad": cal.rotation,
            "rms_residual_px": cal.rms_residual_px,
            "n_lenslets": cal.n_lenslets,
            "n_missing": self.n_missing,
            "grid": self.focal_lattice.grid,
            "pitch_px": [float(v) for v in self.focal_lattice.pitch_px],
            "lenslet_centres_from": self.lenslet_source,
            "lattice": {"focal_point": _lattice_summary(self.focal_lattice, self.focal_spots)},
        }
        if self.alignment_lattice is not None:
            out["lattice"]["alignment"] = _lattice_summary(self.alignment_lattice,
                                                           self.alignment_spots)
        if self.focal_fit is not None:
            f = self.focal_fit
            out["focal_point"] = {"image_distance_mm": f.image_distance * 1e3,
                                  "sigma_mm": f.sigma_image_distance * 1e3,
                                  "back_side": f.model.back_side,
                                  "offset_um": (f.offset * 1e6).tolist(),
                                  "rotation_rad": f.rotation,
                                  "rms_residual_px": cal.rms_residual_px}
        if self.magnification is not None:
            m = self.magnification
            out["magnification"] = {"image_distance_mm": m.image_distance * 1e3,
                                    "sigma_mm": m.sigma_image_distance * 1e3,
                                    "sigma_depth_of_focus_mm": m.sigma_depth_of_focus * 1e3,
                                    "sigma_height_mm": m.sigma_height * 1e3,
                                    "magnification": m.magnification,
                                    "object_distance_mm": m.object_distance * 1e3,
                                    "n_ticks": int(np.isfinite(m.tick_positions).sum())}
        if self.white is not None:
            out["white_image"] = dict(self.white)
        if self.notes:
            out["notes"] = list(self.notes)
        return out


def _lattice_summary(lat: Lattice, spots: SpotSet | None) -> dict:
    """Lattice quality and the spot estimator of one calibration image (JSON-ready)."""
    out = dict(lat.quality)
    if spots is not None:
        out.update(spot_method=spots.method, spot_radius_px=spots.spot_radius_px,
                   spot_rms_radius_px=spots.spot_rms_radius_px)
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
            for k, v in out.items()}


def _pair(focal_px, lenslet_px, scale, centre_rc, max_dist):
    """Pair each focal spot with the lenslet whose centre, scaled by ``scale`` about the sensor
    centre, lies nearest; returns the lenslet index per spot (-1 if none within max_dist)."""
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


def calibrate(camera: CameraModel, focal_point_image, *, alignment_image=None,
              ruler_image=None, ruler_spacing: float | None = None, ruler_axis: str = "x",
              method: str = "focal-point", fit_misplacement: bool = True,
              max_missing_fraction: float = MAX_MISSING_FRACTION, spot_threshold: float = 0.1,
              max_rms_residual_pitch: float = MAX_RMS_RESIDUAL_PITCH,
              spot_method: str = "auto", white_image=None,
              focal_point_f_number: float | None = None,
              phase_harmonics: int = PHASE_HARMONICS) -> CalibrationReport:
    """Calibrate ``camera`` from its images.

    Parameters
    ----------
    camera : CameraModel
        The camera description; its ``image_distance`` may be unset.
    focal_point_image : ndarray
        White sheet through the stopped-down lens (or a full-aperture white image).
    alignment_image : ndarray, optional
        Collimated light, lens removed: gives the lenslet centres. Without it the camera's
        nominal lattice is used.
    ruler_image : ndarray, optional
        A ruler on the nominal focal plane, ticks ``ruler_spacing`` metres apart along
        ``ruler_axis`` ("x": ticks are lines across x, i.e. along the sensor columns).
    method : {"focal-point", "magnification", "both"}
        Which S_i the calibration keeps. "both" keeps the focal-point value and reports the
        magnification value beside it.
    max_missing_fraction : float
        More missing spots than this fraction (default 5 %) is an error: of the lattice
        positions inside the focal-point (or alignment) image, and of the lenslets without a
        focal spot. Fewer are filled from the fitted model and reported.
    spot_threshold : float
        Threshold of the first, thresholded centroid of every spot (detect_spots).
    max_rms_residual_pitch : float
        A focal-point or alignment image whose spots fit their lattice worse than this
        fraction of the pitch (rms, default 1.5 %) is refused: not a calibration image, or
        not of this camera (:func:`~plenopiv.calibration.spots.check_lattice`).
    spot_method : str
        Spot-centre estimator (:func:`~plenopiv.calibration.spots.detect_spots`); the default
        ``"auto"`` takes the window centroid for focal-point and alignment spots.
    focal_point_f_number : float, optional
        The stop of the focal-point image (f/16 in the thesis). Given, the focal-point fit
        predicts each spot's centroid over that stop instead of its chief ray: through a
        plate they differ (with the "thesis" back side by 0.03 mm of S_i at 145 mm, f/16).
    phase_harmonics : int
        Harmonics of the sub-pixel phase bias fitted with each lattice (default 2; 0: none),
        see :func:`~plenopiv.calibration.spots.fit_lattice`.
    white_image : ndarray, optional
        A white image at the working aperture (the camera's ``f_number``): its micro-image
        diameter is measured and stored (``extra["micro_image_diameter_px"]``), and a
        camera f-number that models it more than 1.25 times larger or smaller is noted in
        the report; :func:`~plenopiv.lightfield.light_field` warns on the same comparison.

    Notes
    -----
    Each lattice is fitted together with its spots' sub-pixel phase bias (pixel-locking,
    ``fit_lattice(phase_harmonics=2)``), which is removed from the spot centres when it
    stands out of the noise; the lattice quality of both images goes into the summary.
    """
    if method not in METHODS:
        raise ValueError(f"method = {method!r}: expected one of {METHODS}")
    if method in ("magnification", "both") and (ruler_image is None or ruler_spacing is None):
        raise CalibrationError(f"method = {method!r} needs a ruler image and its tick spacing")
    shape, pp = camera.sensor.shape, camera.sensor.pixel_pitch
    mla = camera.microlens_array
    fp = check_image(focal_point_image, shape=shape, name="focal-point image")
    notes: list[str] = []

    # 1. focal spots
    spots = detect_spots(fp, grid=mla.grid, threshold=spot_threshold, method=spot_method)
    lat = fit_lattice(spots, grid=mla.grid, image_shape=shape, phase_harmonics=phase_harmonics)
    check_lattice(lat, what="the focal-point image", max_missing_fraction=max_missing_fraction,
                  max_rms_residual_pitch=max_rms_residual_pitch)
    good = lat.inlier & ((lat.flags & (SpotFlag.EDGE | SpotFlag.SATURATED | SpotFlag.OUTLIER))
                         == 0)
    centre_rc = (np.array(shape) - 1) / 2.0

    # 2. lenslet centres: the set of lenslets that exist, and their lattice indices
    align_lat = a_spots = None
    if alignment_image is not None:
        al = check_image(alignment_image, shape=shape, name="alignment image")
        # collimated light focuses to (almost) one pixel: accept one-pixel spots here; a hot
        # pixel is then rejected by the lattice fit as off-lattice instead
        a_spots = detect_spots(al, grid=mla.grid, threshold=spot_threshold, min_area_px=0.9,
                               method=spot_method)
        align_lat = fit_lattice(a_spots, grid=mla.grid, image_shape=shape,
                                phase_harmonics=phase_harmonics)
        check_lattice(align_lat, what="the alignment image",
                      max_missing_fraction=max_missing_fraction,
                      max_rms_residual_pitch=max_rms_residual_pitch)
        a_ok = align_lat.inlier & ((align_lat.flags & SpotFlag.EDGE) == 0)
        lenslet_px = align_lat.corrected_centres_px[a_ok]
        lenslet_idx = align_lat.grid_index[a_ok]
        source = "alignment image"
        lenslet_pitch_px = float(np.mean(align_lat.pitch_px))
    else:
        lenslet_px = sensor_to_pixel(mla.centres(), shape, pp)
        lenslet_idx = mla.grid_index()
        source = "nominal lattice"
        lenslet_pitch_px = camera.pitch_px
    scale0 = float(np.mean(lat.pitch_px)) / lenslet_pitch_px
    if not 1.0 < scale0 < 1.1:
        raise CalibrationError(
            f"the focal spots are {float(np.mean(lat.pitch_px)):.4g} px apart and the lenslets "
            f"{lenslet_pitch_px:.4g} px: expected a ratio 1 + f̄/S_i slightly above 1 (got "
            f"{scale0:.5f}); wrong camera file or image?")
    # the lenslets whose focal spot should be fully on the sensor
    predicted = centre_rc + (lenslet_px - centre_rc) * scale0
    margin = spots.window_radius_px + 1
    expected = np.all((predicted >= margin) & (predicted <= np.array(shape) - 1 - margin), axis=1)
    lenslet_px, lenslet_idx = lenslet_px[expected], lenslet_idx[expected]
    focal_px = lat.corrected_centres_px
    pair = _pair(focal_px, lenslet_px, scale0, centre_rc, 0.35 * lenslet_pitch_px)
    use = good & (pair >= 0)
    if use.sum() < 16:
        raise CalibrationError(f"only {int(use.sum())} focal spots could be paired with a "
                               f"lenslet centre ({source}): expected at least 16")
    spot_of = np.full(len(lenslet_px), -1)
    spot_of[pair[use]] = np.flatnonzero(use)
    missing = np.flatnonzero(spot_of < 0)
    frac = len(missing) / len(lenslet_px)
    if frac > max_missing_fraction:
        idx = lenslet_idx[missing]
        raise CalibrationError(
            f"{len(missing)} of {len(lenslet_px)} lenslets ({frac:.0%}) have no focal spot: "
            f"expected at most {max_missing_fraction:.0%}; grid rows {idx[:, 0].min()}-"
            f"{idx[:, 0].max()}, cols {idx[:, 1].min()}-{idx[:, 1].max()} affected; check "
            "the focal-point image, the aperture and spot_threshold")

    d_m = pixel_to_sensor(lenslet_px[spot_of >= 0], shape, pp)
    p_m = pixel_to_sensor(focal_px[spot_of[spot_of >= 0]], shape, pp)

    # 3. focal-point fit
    spot_model = SpotModel.from_camera(camera, focal_point_f_number=focal_point_f_number)
    fit = fit_focal_points(d_m, p_m, spot_model, fit_misplacement=fit_misplacement)

    # 4. the micro-image size at the working aperture
    white = None
    if white_image is not None:
        white = _white(camera, white_image, fit.image_distance, max_missing_fraction,
                       max_rms_residual_pitch)
        if not 1 / MICRO_IMAGE_TOLERANCE <= white["model_over_measured"] <= MICRO_IMAGE_TOLERANCE:
            notes.append(
                f"the white image shows micro-images {white['micro_image_diameter_px']:.1f} px "
                f"across, but [main_lens] f_number = {white['f_number']:g} models "
                f"{white['modelled_diameter_px']:.1f} px (as from f_number = "
                f"{white['implied_f_number']:.3g}): set f_number to the recording's aperture")

    # 5. magnification method
    mag = None
    if ruler_image is not None and ruler_spacing is not None:
        mag = _magnification(camera, ruler_image, lat, ruler_spacing, ruler_axis)

    # every lenslet gets a focal spot: measured, or (missing) predicted by the fitted model
    spots_px = np.empty_like(lenslet_px)
    found = spot_of >= 0
    spots_px[found] = focal_px[spot_of[found]]
    if len(missing):
        d_missing = apply_misplacement(pixel_to_sensor(lenslet_px[missing], shape, pp),
                                       fit.offset, fit.rotation)
        spots_px[missing] = sensor_to_pixel(spot_model.predict(d_missing, fit.image_distance),
                                            shape, pp)
        idx = lenslet_idx[missing]
        notes.append(f"{len(missing)} of {len(lenslet_px)} focal spots missing (grid rows "
                     f"{idx[:, 0].min()}-{idx[:, 0].max()}, cols {idx[:, 1].min()}-"
                     f"{idx[:, 1].max()}); filled from the fitted focal-point model")
    missing_index = lenslet_idx[missing]

    if method == "magnification":
        si, meth = mag.image_distance, "magnification"
    else:
        si, meth = fit.image_distance, method
        if mag is not None and abs(mag.image_distance - fit.image_distance) > \
                3 * mag.sigma_image_distance:
            notes.append(
                f"the focal-point S_i ({fit.image_distance * 1e3:.2f} mm) and the magnification "
                f"S_i ({mag.image_distance * 1e3:.2f} ± {mag.sigma_image_distance * 1e3:.2f} mm) "
                "disagree: an exit-pupil offset or a wrong f̄ (see the lens corrections)")
    cal = Calibration(camera=camera.with_image_distance(si), centre_px=lenslet_px,
                      focal_spot_px=spots_px, grid_index=lenslet_idx, image_distance=si,
                      method=meth, offset=tuple(fit.offset), rotation=fit.rotation,
                      rms_residual_px=fit.rms_residual / pp,
                      extra={"n_missing": int(len(missing)),
                             "sigma_image_distance_m": (fit.sigma_image_distance
                                                        if meth != "magnification"
                                                        else mag.sigma_image_distance),
                             "focal_spot_rms_radius_px": spots.spot_rms_radius_px,
                             "spot_method": spots.method,
                             **({} if white is None else
                                {"micro_image_diameter_px": white["micro_image_diameter_px"]})})
    return CalibrationReport(cal, lat, align_lat, fit, mag, int(len(missing)), missing_index,
                             source, focal_px[spot_of[found]], notes, spots, a_spots, white)


def _white(camera: CameraModel, white_image, image_distance, max_missing_fraction,
           max_rms_residual_pitch) -> dict:
    """Measure the micro-image diameter of a white image and model it from the f-number."""
    shape = camera.sensor.shape
    wh = check_image(white_image, shape=shape, name="white image").astype(float)
    grid = camera.microlens_array.grid
    w_spots = detect_spots(wh, grid=grid)
    w_lat = fit_lattice(w_spots, grid=grid, image_shape=shape)
    check_lattice(w_lat, what="the white image", max_missing_fraction=max_missing_fraction,
                  max_rms_residual_pitch=max_rms_residual_pitch)
    complete = (w_lat.flags & SpotFlag.EDGE) == 0
    black = float(np.percentile(wh, 1.0))
    measured = micro_image_diameter(wh - black, w_lat.predict(w_lat.grid_index[complete]),
                                    float(np.mean(w_lat.pitch_px)))
    n_f = camera.main_lens.f_number
    model = micro_image_diameter_px(camera, image_distance, n_f)
    return {"micro_image_diameter_px": measured, "modelled_diameter_px": model,
            "f_number": n_f, "model_over_measured": model / measured,
            "implied_f_number": n_f * model / measured}


def _magnification(camera, ruler_image, lat: Lattice, spacing, axis) -> MagnificationResult:
    if axis not in ("x", "y"):
        raise ValueError(f"ruler_axis = {axis!r}: expected 'x' or 'y'")
    shape = camera.sensor.shape
    img = check_image(ruler_image, shape=shape, name="ruler image")
    pitch_px = float(np.mean(lat.pitch_px))
    integ = lenslet_integral_image(img, lat.centres_px, lat.grid_index, pitch_px)
    if axis == "y":
        integ = integ.T
    mid = integ.shape[0] // 2
    band = integ[max(mid - 3, 0):mid + 4]
    profile = np.nanmean(band, axis=0)
    ticks = find_ruler_ticks(profile)
    # lenslet-index units to metres on the lenslet plane (the lattice pitch in px, scaled
    # back from the focal-spot spacing to the lenslet spacing by the camera's pitch)
    positions = index_ticks(ticks) * camera.microlens_array.pitch
    return magnification_from_ticks(positions, spacing, camera.main_lens.focal_length,
                                    camera.main_lens.f_number, camera.microlens_array.pitch)
