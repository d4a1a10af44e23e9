"""Calibrate a camera from its images: focal-point (+ alignment) (+ ruler) -> Calibration.

:func:`calibrate` runs the steps of the calibration package in order: focal spots and their
lattice (:mod:`~plenopiv.calibration.spots`), lenslet centres and the pairing of each focal
spot with its lenslet (:mod:`~plenopiv.calibration.lenslets`), the focal-point fit of S_i,
offset and rotation, and optionally the magnification method on a ruler image
(:mod:`~plenopiv.calibration.image_distance`). Orchestration lives here; file I/O and
reporting live in the CLI.

See docs/methods.md#calibration.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from plenopiv.calibration.defects import (
    HOT_SHAPE_MIN_RMS_PX,
    DarkFrame,
    WhiteFlat,
    gap_level,
    hot_pixel_mask,
)
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
from plenopiv.calibration.lattice_quality import (
    MAX_MISSING_FRACTION,
    MAX_RMS_RESIDUAL_PITCH,
    MIN_ON_LATTICE_FRACTION,
    pitch_sigma,
)
from plenopiv.calibration.lenslets import (
    LensletCentres,
    focal_spot_scale,
    lenslet_centres,
    lenslets_on_sensor,
    measure_white_image,
    pair_focal_spots,
    spot_lattice,
)
from plenopiv.calibration.model import Calibration
from plenopiv.calibration.nominal import check_against_camera
from plenopiv.calibration.psf import point_spread_sigma
from plenopiv.calibration.spot_detection import window_radius_from_rms
from plenopiv.calibration.spot_types import Lattice, SpotFlag, SpotSet
from plenopiv.camera.model import CameraModel, apply_misplacement
from plenopiv.camera.resolution import MICRO_IMAGE_TOLERANCE
from plenopiv.conventions import pixel_to_sensor, sensor_to_pixel
from plenopiv.errors import CalibrationError, PlenopivWarning
from plenopiv.products.images import check_image, warn_identical

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
            "point_spread_sigma_px": cal.point_spread_sigma_px,
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


def calibrate(camera: CameraModel, focal_point_image, *, alignment_image=None,
              ruler_image=None, ruler_spacing: float | None = None, ruler_axis: str = "x",
              method: str = "focal-point", fit_misplacement: bool = True,
              max_missing_fraction: float = MAX_MISSING_FRACTION, spot_threshold: float = 0.1,
              max_rms_residual_pitch: float | None = MAX_RMS_RESIDUAL_PITCH,
              spot_method: str = "auto", white_image=None,
              focal_point_f_number: float | None = None,
              phase_harmonics: int = PHASE_HARMONICS, dark=None,
              min_on_lattice_fraction: float | None = MIN_ON_LATTICE_FRACTION
              ) -> CalibrationReport:
    """Calibrate ``camera`` from its images.

    Parameters
    ----------
    camera : CameraModel
        The camera description (its ``image_distance`` may be unset).
    focal_point_image : ndarray
        White sheet through the stopped-down lens (or a full-aperture white).
    alignment_image, ruler_image : ndarray, optional
        Collimated light, lens removed: the lenslet centres (else the nominal lattice). A
        ruler on the focal plane, ticks ``ruler_spacing`` m apart along ``ruler_axis``.
    method : {"focal-point", "magnification", "both"}
        Which S_i is kept; "both" keeps the focal-point one, the other reported beside it.
    max_missing_fraction : float
        More missing lattice positions or focal spots than this (default 5 %) is an error;
        fewer are filled from the fitted model and reported.
    spot_threshold : float
        Threshold of every spot's first, thresholded centroid (detect_spots).
    max_rms_residual_pitch, min_on_lattice_fraction : float, optional
        An image whose spots fit their lattice worse than this fraction of the pitch (rms;
        default no limit: real arrays scatter), or fewer of whose complete spots than this
        fraction (default 90 %) lie within 0.15 pitch of a node, holds no lenslet lattice
        and is refused (:func:`~plenopiv.calibration.lattice_quality.check_lattice`).
    spot_method : str
        Spot-centre estimator (:func:`~plenopiv.calibration.spot_detection.detect_spots`).
    focal_point_f_number : float, optional
        The stop of the focal-point image (f/16 in the thesis). Given, the focal-point fit
        predicts each spot's centroid over that stop instead of its chief ray: through a
        plate they differ (with the "thesis" back side by 0.03 mm of S_i at 145 mm, f/16).
        Also measures the sensor's point spread (``extra["point_spread_sigma_px"]``).
    phase_harmonics : int
        Harmonics of each lattice's sub-pixel phase bias (default 2; 0: none; fit_lattice).
    white_image : ndarray, optional
        A white at the working aperture: divides the focal-point and alignment images
        (:class:`~plenopiv.calibration.defects.WhiteFlat`); its micro-image diameter is
        stored (``extra["micro_image_diameter_px"]``), an f-number 1.25 times off noted.
    dark : ndarray, optional
        A dark frame of the sensor (no light, the images' exposure), counts: subtracted from
        every image, its hot pixels (:func:`~plenopiv.calibration.defects.hot_pixels_from_dark`)
        ignored by the spot detection. Without it the black level, its fixed pattern per
        column and row, and the hot pixels are estimated on each image (methods.md).
    """
    _inputs(method, ruler_spacing, focal_point_image, alignment_image, ruler_image, white_image)
    shape, pp = camera.sensor.shape, camera.sensor.pixel_pitch
    dark_frame = DarkFrame.of(dark, shape)
    limits = {"max_missing_fraction": max_missing_fraction,
              "max_rms_residual_pitch": max_rms_residual_pitch,
              "min_on_lattice_fraction": min_on_lattice_fraction,
              "bad_pixels": dark_frame.hot}
    options = {"threshold": spot_threshold, "method": spot_method,
               "phase_harmonics": phase_harmonics, **limits}
    flat = WhiteFlat.of(white_image, dark_frame, shape, camera.pitch_px)
    fp = flat.apply(dark_frame.subtract(check_image(focal_point_image, shape=shape,
                                                    name="focal-point image")))

    # 1. focal spots; 2. the lenslets (alignment or nominal) and their spots; 3. the fit
    spots, lat = spot_lattice(fp, camera, "the focal-point image", **options)
    lenslets = _lenslets(camera, alignment_image, spots, dark_frame, flat, options)
    scale = focal_spot_scale(lat.lenslet_pitch_px, lenslets.pitch_px,
                             _lenslets_from(camera, lenslets))
    lenslets = lenslets_on_sensor(lenslets, scale, shape)   # spots cut by the edge: predicted
    focal_px = lat.corrected_centres_px
    spot_of = pair_focal_spots(focal_px, _pairable(lat), lenslets, scale, shape,
                               max_missing_fraction, margin_px=spots.window_radius_px + 1)
    found = spot_of >= 0

    spot_model = SpotModel.from_camera(camera, focal_point_f_number=focal_point_f_number)
    fit = fit_focal_points(pixel_to_sensor(lenslets.centre_px[found], shape, pp),
                           pixel_to_sensor(focal_px[spot_of[found]], shape, pp), spot_model,
                           fit_misplacement=fit_misplacement)

    # 4. the micro-image size at the working aperture; 5. the magnification method
    white, notes = _white(camera, white_image, fit.image_distance, dark_frame, limits)
    mag = _magnification(camera, ruler_image, lat, ruler_spacing, ruler_axis, dark_frame)

    spots_px, missing_notes = _every_focal_spot(focal_px, spot_of, lenslets, fit, spot_model,
                                                camera)
    si, meth, si_notes = _chosen_image_distance(method, fit, mag, camera, lenslets)
    calibrated = camera.with_image_distance(si, origin=f"measured by the {meth} method")
    psf = point_spread_sigma(calibrated, spots, focal_point_f_number, threshold=spot_threshold)
    cal = Calibration(camera=calibrated, centre_px=lenslets.centre_px,
                      focal_spot_px=spots_px, grid_index=lenslets.grid_index, method=meth,
                      offset=tuple(fit.offset), rotation=fit.rotation,
                      rms_residual_px=fit.rms_residual / pp,
                      extra=_extra(spot_of, fit, mag, meth, spots, white, psf))
    return CalibrationReport(cal, lat, lenslets.lattice, fit, mag, int(np.sum(~found)),
                             lenslets.grid_index[~found], lenslets.source,
                             focal_px[spot_of[found]], notes + missing_notes + si_notes
                             + _defect_notes(camera, focal_point_image, spots, lenslets, scale,
                                             fit, dark_frame), spots, lenslets.spots, white)


def _lenslets(camera, alignment_image, spots: SpotSet, dark_frame: DarkFrame,
              flat: WhiteFlat, options: dict) -> LensletCentres:
    """The lenslets (:func:`lenslet_centres`), hot pixels repaired.

    Without a dark frame, the hot pixels the focal-point image showed by their shape
    (:func:`~plenopiv.calibration.defects.hot_pixel_mask`) are repaired in the alignment
    image, whose one-pixel spots cannot tell them. The spots' window is that of their rms
    radius where the 99 % radius of their stacked light reads wider
    (:func:`~plenopiv.calibration.spot_detection.window_radius_from_rms`): without the dark
    the black level left in the gaps and a hot pixel beside a spot, summed over the cell's
    rings, carry the 99 % radius to the cell's edge, and a window that wide takes the gaps'
    pattern and noise into every centre (0.26 px of noise in each instead of 0.01,
    docs/methods.md#sensor-defects).
    """
    if dark_frame.frame is not None or alignment_image is None:
        return lenslet_centres(camera, alignment_image, dark=dark_frame, flat=flat, **options)
    if spots.spot_rms_radius_px >= HOT_SHAPE_MIN_RMS_PX:
        # broad focal spots: what they reject as one pixel of light is a hot pixel
        options = {**options, "bad_pixels": hot_pixel_mask(spots.rejected_px,
                                                           camera.sensor.shape)}
    lenslets = lenslet_centres(camera, alignment_image, dark=dark_frame, flat=flat, **options)
    found = lenslets.spots
    radius = window_radius_from_rms(found.spot_rms_radius_px)
    if not found.moment_radius_px > radius + 1.0:
        return lenslets
    return lenslet_centres(camera, alignment_image, dark=dark_frame, flat=flat,
                           **{**options, "moment_radius_px": radius})


#: The S_i the alignment lattice's pitch carries (:func:`_defect_notes`) is warned about
#: beyond this many times the focal-point fit's own standard deviation and beyond
#: LATTICE_SIGMA_FLOOR of S_i (0.01 mm at 100 mm; the demo camera's ideal render carries
#: 0.004 mm, with the real camera's effects and their dark 0.008 mm)
LATTICE_SIGMA_FACTOR = 3.0
LATTICE_SIGMA_FLOOR = 1e-4
#: Without a dark frame a black level above this fraction of the focal spots' peak is noted
BLACK_LEVEL_NOTE = 0.01


def _defect_notes(camera, focal_point_image, spots: SpotSet, lenslets: LensletCentres,
                  scale: float, fit: FocalPointFit, dark_frame: DarkFrame) -> list[str]:
    """What the images' defects leave in S_i: notes, and a warning beyond what noise allows.

    The alignment lattice's pitch, relative standard error ``eps``
    (:func:`~plenopiv.calibration.lattice_quality.pitch_sigma`), carries
    ``S_i scale / (scale - 1) eps`` into S_i (``scale = 1 + f/S_i``: 200 times ``eps`` at
    f = 0.5 mm, S_i = 100 mm), which the focal-point fit's standard deviation leaves out.
    Beyond :data:`LATTICE_SIGMA_FACTOR` times that deviation it is warned about, naming the
    dark frame where there was none. Without one, a black level above
    :data:`BLACK_LEVEL_NOTE` of the spots' peak is noted with the hot pixels repaired.
    """
    notes = []
    si = fit.image_distance
    if dark_frame.frame is None:
        level, peak = gap_level(focal_point_image, camera.pitch_px)
        if level > BLACK_LEVEL_NOTE * peak:
            notes.append(
                f"no dark frame: a black level of {level:.4g} counts (the median of the "
                f"focal-point image's gaps, {100 * level / peak:.2g} % of its brightest "
                "spots) and its pattern per column and row were estimated and taken off, and "
                f"{len(spots.rejected_px)} hot pixels found by their shape repaired; each "
                "pixel's own offset and hot pixels inside a spot stay (--dark takes them off)")
    if lenslets.lattice is None:
        return notes
    sigma = si * scale / (scale - 1.0) * pitch_sigma(lenslets.lattice)
    if not sigma > max(LATTICE_SIGMA_FACTOR * fit.sigma_image_distance,
                       LATTICE_SIGMA_FLOOR * si):
        return notes
    cause = ("without a dark frame hot pixels or the black level's pattern may sit in the "
             "alignment spots: give the dark frame (--dark)" if dark_frame.frame is None else
             "the alignment image's spots are noisier or more disturbed than its dark frame "
             "explains: check its exposure and focus")
    text = (f"the alignment image's lenslet centres fit their lattice to "
            f"{lenslets.lattice.rms_residual_px:.3f} px rms: its pitch carries "
            f"±{sigma * 1e3:.3f} mm into S_i, {sigma / fit.sigma_image_distance:.0f} times the "
            f"focal-point fit's ±{fit.sigma_image_distance * 1e3:.4f} mm; {cause}")
    warnings.warn(text, PlenopivWarning, stacklevel=3)
    return notes + [text]


def _lenslets_from(camera: CameraModel, lenslets: LensletCentres) -> str:
    """Where the lenslet pitch came from, as the user gave it (for messages)."""
    if lenslets.lattice is not None:
        return "measured on the alignment image"
    return (f"[microlens_array] pitch_um = {camera.microlens_array.pitch * 1e6:g} over [sensor] "
            f"pixel_pitch_um = {camera.sensor.pixel_pitch * 1e6:g}")


#: What a calibration image that is another one's copy means (warn_identical)
IDENTICAL_IMAGES = ("each calibration image shows its own thing (focal spots, lenslet centres, "
                    "ruler ticks, micro-images at the working aperture): one of them is the "
                    "wrong file")


def _inputs(method, ruler_spacing, focal_point_image, alignment_image, ruler_image, white_image):
    """Raise when ``method`` is unknown or lacks its ruler image; warn of identical images."""
    warn_identical(("the focal-point image", "the alignment image", "the ruler image",
                    "the white image"),
                   (focal_point_image, alignment_image, ruler_image, white_image),
                   consequence=IDENTICAL_IMAGES)
    if method not in METHODS:
        raise ValueError(f"method = {method!r}: expected one of {METHODS}")
    if method in ("magnification", "both") and (ruler_image is None or ruler_spacing is None):
        raise CalibrationError(f"method = {method!r} needs a ruler image and its tick spacing")


def _pairable(lat: Lattice) -> np.ndarray:
    """The focal spots that may be paired with a lenslet: complete, unsaturated inliers."""
    bad = SpotFlag.EDGE | SpotFlag.SATURATED | SpotFlag.OUTLIER
    return lat.inlier & ((lat.flags & bad) == 0)


def _every_focal_spot(focal_px, spot_of, lenslets: LensletCentres, fit: FocalPointFit,
                      spot_model: SpotModel, camera: CameraModel):
    """Every lenslet's focal spot, px: measured, or (missing) predicted by the fitted model.

    Returns the ``(N, 2)`` spots ``(row, col)`` px and the notes on the missing ones.
    """
    shape, pp = camera.sensor.shape, camera.sensor.pixel_pitch
    spots_px = np.empty_like(lenslets.centre_px)
    found = spot_of >= 0
    spots_px[found] = focal_px[spot_of[found]]
    missing = np.flatnonzero(~found)
    if not len(missing):
        return spots_px, []
    d_missing = apply_misplacement(pixel_to_sensor(lenslets.centre_px[missing], shape, pp),
                                   fit.offset, fit.rotation)
    spots_px[missing] = sensor_to_pixel(spot_model.predict(d_missing, fit.image_distance),
                                        shape, pp)
    idx = lenslets.grid_index[missing]
    return spots_px, [f"{len(missing)} of {len(lenslets.centre_px)} focal spots missing (grid "
                      f"rows {idx[:, 0].min()}-{idx[:, 0].max()}, cols {idx[:, 1].min()}-"
                      f"{idx[:, 1].max()}); filled from the fitted focal-point model"]


def _chosen_image_distance(method, fit: FocalPointFit, mag: MagnificationResult | None,
                           camera: CameraModel, lenslets: LensletCentres):
    """The S_i the calibration keeps (m), its method name, and notes.

    A note when the two methods disagree; the S_i is checked against the camera file
    (:func:`~plenopiv.calibration.nominal.check_against_camera`, with the alignment image's
    pitch when there is one), refused or warned about with the figures.
    """
    if method == "magnification":
        si, sigma, notes = mag.image_distance, mag.sigma_image_distance, []
    else:
        si, sigma, notes = fit.image_distance, fit.sigma_image_distance, _disagreement(fit, mag)
    aligned = lenslets.lattice is not None
    notes += check_against_camera(
        camera, si, sigma, method,
        alignment_pitch_px=float(lenslets.lattice.pitch_px[1]) if aligned else None)
    return si, method, notes


def _disagreement(fit: FocalPointFit, mag: MagnificationResult | None) -> list[str]:
    """A note when the focal-point and the magnification S_i disagree beyond 3 sigma."""
    notes = []
    if mag is not None and abs(mag.image_distance - fit.image_distance) > \
            3 * mag.sigma_image_distance:
        notes.append(
            f"the focal-point S_i ({fit.image_distance * 1e3:.2f} mm) and the magnification "
            f"S_i ({mag.image_distance * 1e3:.2f} ± {mag.sigma_image_distance * 1e3:.2f} mm) "
            "disagree: an exit-pupil offset, a wrong f̄ ([microlens_array] sensor_distance_um) "
            "or a wrong ruler spacing (--ruler-spacing-mm) (see the lens corrections)")
    return notes


def _extra(spot_of, fit: FocalPointFit, mag, meth, spots: SpotSet, white, psf) -> dict:
    """The ``extra`` record of the calibration product (JSON-ready)."""
    sigma = fit.sigma_image_distance if meth != "magnification" else mag.sigma_image_distance
    return {"n_missing": int(np.sum(spot_of < 0)), "sigma_image_distance_m": sigma,
            "focal_spot_rms_radius_px": spots.spot_rms_radius_px, "spot_method": spots.method,
            "point_spread_sigma_px": psf,
            **({} if white is None else
               {"micro_image_diameter_px": white["micro_image_diameter_px"]})}


def _white(camera: CameraModel, white_image, image_distance, dark_frame: DarkFrame, limits):
    """The white-image record (or None without one) and a note when the f-number is off."""
    if white_image is None:
        return None, []
    white = measure_white_image(camera, white_image, image_distance, dark=dark_frame,
                                **limits)
    if 1 / MICRO_IMAGE_TOLERANCE <= white["model_over_measured"] <= MICRO_IMAGE_TOLERANCE:
        return white, []
    return white, [
        f"the white image shows micro-images {white['micro_image_diameter_px']:.1f} px "
        f"across, but [main_lens] f_number = {white['f_number']:g} models "
        f"{white['modelled_diameter_px']:.1f} px (as from f_number = "
        f"{white['implied_f_number']:.3g}): set f_number to the recording's aperture"]


def _magnification(camera, ruler_image, lat: Lattice, spacing, axis,
                   dark_frame: DarkFrame) -> MagnificationResult | None:
    """The magnification method on a ruler image (None without the image or its spacing)."""
    if ruler_image is None or spacing is None:
        return None
    if axis not in ("x", "y"):
        raise ValueError(f"ruler_axis = {axis!r}: expected 'x' or 'y'")
    shape = camera.sensor.shape
    img = dark_frame.subtract(check_image(ruler_image, shape=shape, name="ruler image"),
                              patch=True)
    pitch_px = lat.lenslet_pitch_px
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
