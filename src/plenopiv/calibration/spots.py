"""Lenslet spot detection and regular-lattice fitting (calibration step 1).

Two stage functions, in the order the data moves (this module gathers them and their
result types; each lives in the module of its step):

:func:`detect_spots`
    One sub-pixel centre per lenslet from a focal-point image (small bright spots), an
    alignment image (very small spots) or a full-aperture white image (one bright disc per
    lenslet). Returns a :class:`SpotSet`. In :mod:`plenopiv.calibration.spot_detection`, with
    :func:`estimate_pitch`.
:func:`fit_lattice`
    Gives every spot a grid index ``(row, col)``, classifies the grid (square or hexagonal) and
    fits a regular lattice by linear least squares. Returns a :class:`Lattice`. In
    :mod:`plenopiv.calibration.lattice_fit`; :func:`check_lattice` (in
    :mod:`plenopiv.calibration.lattice_quality`) refuses a lattice that is not of a
    calibration image.

:class:`SpotFlag`, :class:`SpotSet` and :class:`Lattice` live in
:mod:`plenopiv.calibration.spot_types`; :func:`micro_image_diameter` (white images) in
:mod:`plenopiv.calibration.lenslets`.

Conventions
-----------
Pixels are ``(row, col)``, 0-based, with the centre of the top-left pixel at (0, 0) (see
:mod:`plenopiv.conventions`); every length here is in pixels (px). The lattice is

``centre(i, j) = origin_px + i * basis[0] + j * basis[1] + (i mod 2) * odd_row_shift_px``

with ``basis[0]`` the step from lattice row ``i`` to row ``i + 1`` and ``basis[1]`` the step
from column ``j`` to ``j + 1``, both as ``(d_row, d_col)`` px. On a square grid the odd-row
shift is zero. On a hexagonal grid the lenslet rows run along the image col axis and odd rows
are shifted by half a pitch towards +col, ``odd_row_shift_px = basis[1] / 2`` for a regular
array; the shift is fitted (two more unknowns), so a slightly irregular array is measured
rather than forced. Row index 0 is the first lattice row and column index 0 the first lattice
column that hold a spot; on a rotated grid the position of index (0, 0) itself may lie outside
the image, and on a hexagonal grid an even row may begin at column 1 (row 0 is always even).
The rotation is the angle of ``basis[1]`` (the lattice +col direction) from the image +col
axis, counter-clockwise positive in ``(x = col, y = row)`` coordinates:
``rotation_rad = atan2(basis[1][0], basis[1][1])``. Because ``y = row`` points down the
screen, a positive rotation looks clockwise on a displayed image.

Examples
--------
>>> import numpy as np
>>> rr, cc = np.mgrid[0:120, 0:120]
>>> image = np.zeros((120, 120))
>>> for r in range(10, 120, 20):
...     for c in range(10, 120, 20):
...         image += np.exp(-((rr - r - 0.3) ** 2 + (cc - c + 0.2) ** 2) / 2.0)
>>> spots = detect_spots(image, expected_pitch_px=20.0)
>>> lattice = fit_lattice(spots)
>>> lattice.grid, np.round(lattice.pitch_px, 2).tolist(), np.round(lattice.origin_px, 1).tolist()
('square', [20.0, 20.0], [10.3, 9.8])
"""

from plenopiv.calibration.lattice_fit import fit_lattice
from plenopiv.calibration.lattice_quality import (
    MAX_MISSING_FRACTION,
    MAX_RMS_RESIDUAL_PITCH,
    check_lattice,
)
from plenopiv.calibration.lenslets import micro_image_diameter
from plenopiv.calibration.spot_detection import detect_spots, estimate_pitch
from plenopiv.calibration.spot_types import BACKGROUNDS, GRIDS, METHODS, Lattice, SpotFlag, SpotSet

__all__ = [
    "GRIDS",
    "METHODS",
    "BACKGROUNDS",
    "MAX_MISSING_FRACTION",
    "MAX_RMS_RESIDUAL_PITCH",
    "SpotFlag",
    "SpotSet",
    "Lattice",
    "estimate_pitch",
    "detect_spots",
    "fit_lattice",
    "check_lattice",
    "micro_image_diameter",
]
