"""Which micro-image each sensor pixel belongs to: the lattice of a calibration, on the pixels.

Every pixel is given to its nearest micro-image centre (the calibration's focal spots, where
the chief ray from the pupil centre lands), up to three quarters of a micro-image pitch away:
the micro-images' Voronoi cells, which for a square or hexagonal array are the squares or
hexagons about each centre. Repairs and neighbour comparisons stay inside a cell, so that a
pixel is never judged by, or filled from, the light of another lenslet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.errors import CalibrationError
from plenopiv.preprocess import _kernels

__all__ = ["GAP_MARGIN_PX", "MicroImages", "micro_images", "micro_images_from_centres"]

#: A pixel is in the gap between micro-images when it lies this far beyond the modelled
#: micro-image radius (pixels): its aperture cell is then wholly outside the aperture.
GAP_MARGIN_PX = 1.0

#: Pixels farther than this many micro-image pitches from every centre are outside the array.
REACH_PITCHES = 0.75


@dataclass(frozen=True)
class MicroImages:
    """The micro-images on the sensor.

    Attributes
    ----------
    label : (rows, cols) int32
        Index of each pixel's micro-image (rows of ``centre_px``); -1 outside the array.
    distance_px : (rows, cols) float32
        Distance of each pixel's centre from its micro-image's centre, pixels (inf outside).
    centre_px : (N, 2) float64
        Micro-image centres (row, col), pixels.
    radius_px : float
        Modelled micro-image radius at the recording's aperture, pixels: the aperture's image
        through a lenslet, R f̄ / S_i (docs/design.md §4).
    pitch_px : float
        Micro-image pitch, pixels: the lenslet pitch times 1 + f̄/S_i.
    """

    label: np.ndarray
    distance_px: np.ndarray
    centre_px: np.ndarray
    radius_px: float
    pitch_px: float

    @property
    def shape(self) -> tuple[int, int]:
        """The sensor's (rows, cols)."""
        return tuple(self.label.shape)

    @property
    def n_micro_images(self) -> int:
        """Number of micro-images (lenslets)."""
        return len(self.centre_px)

    @property
    def inside(self) -> np.ndarray:
        """Pixels that belong to a micro-image's cell (bool)."""
        return self.label >= 0

    @property
    def gap(self) -> np.ndarray:
        """Pixels between the micro-images (bool): they see no light through the main lens.

        In a cell, beyond the modelled radius by :data:`GAP_MARGIN_PX`.
        """
        return (self.label >= 0) & (self.distance_px > self.radius_px + GAP_MARGIN_PX)

    def offsets(self) -> tuple[np.ndarray, np.ndarray]:
        """``(d_row, d_col)`` of every pixel from its micro-image's centre, pixels (0 outside)."""
        rows, cols = np.indices(self.shape)
        lab = np.maximum(self.label, 0)
        inside = self.label >= 0
        dr = np.where(inside, rows - self.centre_px[lab, 0], 0.0)
        dc = np.where(inside, cols - self.centre_px[lab, 1], 0.0)
        return dr, dc


def micro_images_from_centres(centre_px, shape, pitch_px: float, radius_px: float, *,
                              engine: str = "numba") -> MicroImages:
    """Label the pixels of a ``shape`` sensor with their nearest micro-image centre.

    Parameters
    ----------
    centre_px : (N, 2) array_like
        Micro-image centres (row, col), pixels.
    shape : (rows, cols)
        The sensor.
    pitch_px : float
        Micro-image pitch, pixels (> 1).
    radius_px : float
        Modelled micro-image radius, pixels (> 0).
    engine : {"numba", "numpy"}
        The kernel or its NumPy twin (:mod:`plenopiv.preprocess._kernels`).
    """
    centres = np.ascontiguousarray(centre_px, dtype=np.float64)
    if centres.ndim != 2 or centres.shape[1] != 2 or len(centres) == 0:
        raise CalibrationError(f"micro-image centres have shape {centres.shape}: expected "
                               "(N, 2) (row, col) with N >= 1")
    if not np.isfinite(centres).all():
        raise CalibrationError("micro-image centres hold NaN or infinity")
    if not (math.isfinite(pitch_px) and pitch_px > 1):
        raise CalibrationError(f"micro-image pitch {pitch_px!r} px: expected a finite number "
                               "> 1 pixel")
    if not (math.isfinite(radius_px) and radius_px > 0):
        raise CalibrationError(f"micro-image radius {radius_px!r} px: expected a finite number "
                               "> 0")
    if engine not in ("numba", "numpy"):
        raise ValueError(f"engine = {engine!r}: expected 'numba' or 'numpy'")
    rows, cols = (int(v) for v in shape)
    reach = REACH_PITCHES * pitch_px
    half = int(math.ceil(reach)) + 1
    base = np.floor(centres + 0.5).astype(np.int64)
    label = np.full((rows, cols), -1, np.int32)
    dist2 = np.full((rows, cols), np.inf)
    kernel = (_kernels.label_micro_images if engine == "numba"
              else _kernels.label_micro_images_numpy)
    kernel(centres, base, half, float(reach * reach), label, dist2)
    return MicroImages(label, np.sqrt(dist2).astype(np.float32), centres, float(radius_px),
                       float(pitch_px))


def micro_images(calibration: Calibration, *, f_number: float | None = None) -> MicroImages:
    """The micro-images of a calibrated camera, at the recording's aperture.

    Centres: ``calibration.focal_spot_px``; pitch: the lenslet pitch in pixels times
    1 + f̄/S_i; radius: R f̄/(S_i p_p) with R = f_m/(2N) (divided by the substrate's index
    with the ``"thesis"`` back side, as :func:`plenopiv.lightfield.light_field` does).

    Parameters
    ----------
    calibration : Calibration
    f_number : float, optional
        Aperture of the recording (default: the camera's).
    """
    cam = calibration.camera
    mla = cam.microlens_array
    si = calibration.image_distance
    fbar = mla.sensor_distance
    n_f = cam.main_lens.f_number if f_number is None else float(f_number)
    radius = cam.main_lens.focal_length / n_f / 2
    if mla.back_side == "thesis" and mla.substrate is not None:
        radius /= mla.substrate.refractive_index
    radius_px = radius * fbar / si / cam.sensor.pixel_pitch
    pitch_px = cam.pitch_px * (1 + fbar / si)
    return micro_images_from_centres(calibration.focal_spot_px, cam.sensor.shape, pitch_px,
                                     radius_px)


def per_micro_image(values, label, n: int, q: float) -> np.ndarray:
    """The ``q``-th percentile (0-100, nearest rank below) of ``values`` in each micro-image.

    ``values`` and ``label`` are matching 1-D arrays (the pixels to use and their micro-image
    index, 0 … n-1); returns an (n,) array, NaN for micro-images without a value.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    lab = np.asarray(label).ravel()
    out = np.full(int(n), np.nan)
    keep = (lab >= 0) & (lab < n)
    v, lab = v[keep], lab[keep]
    if v.size == 0:
        return out
    order = np.lexsort((v, lab))
    v, lab = v[order], lab[order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    counts = np.diff(np.r_[starts, lab.size])
    pick = starts + np.floor((counts - 1) * (q / 100.0)).astype(np.int64)
    out[lab[starts]] = v[pick]
    return out


#: The black level is the median of the darkest quarter of the micro-image gaps.
DARKEST_GAPS = 0.25


def gap_level(image, micro: MicroImages) -> float:
    """The level of the gaps between micro-images, counts: the black level of a recording.

    The median of each micro-image's gap pixels (:attr:`MicroImages.gap`), then the median
    of the darkest quarter of them (:data:`DARKEST_GAPS`): a gap beside a bright micro-image
    may catch some of its light through the point spread, the darkest do not. Without gap
    pixels (micro-images that fill their cells), the 5th percentile of the image.
    """
    img = np.asarray(image, dtype=np.float64)
    gap = micro.gap
    if not gap.any():
        return float(np.percentile(img, 5.0))
    medians = per_micro_image(img[gap], micro.label[gap], micro.n_micro_images, 50.0)
    medians = np.sort(medians[np.isfinite(medians)])
    darkest = medians[: max(1, int(np.ceil(DARKEST_GAPS * medians.size)))]
    return float(np.median(darkest))
