"""Lenslet spot detection and regular-lattice fitting (calibration step 1).

The two stage functions of the step, gathered with their result types: :func:`detect_spots`
(one sub-pixel centre per lenslet of a focal-point, alignment or white image, a
:class:`SpotSet`; in :mod:`~plenopiv.calibration.spot_detection`, with :func:`estimate_pitch`)
and :func:`fit_lattice` (grid indices, grid type and a regular lattice fitted by linear least
squares, a :class:`Lattice`; in :mod:`~plenopiv.calibration.lattice_fit`; :func:`check_lattice`
in :mod:`~plenopiv.calibration.lattice_quality`). :class:`SpotFlag`, :class:`SpotSet` and
:class:`Lattice` live in :mod:`~plenopiv.calibration.spot_types`, :func:`micro_image_diameter`
in :mod:`~plenopiv.calibration.lenslets`. Every length is in pixels (px).

See docs/methods.md#focal-spots and docs/methods.md#lattice-fit (the lattice convention).
"""

from plenopiv.calibration.lattice_fit import fit_lattice
from plenopiv.calibration.lattice_quality import (
    MAX_MISSING_FRACTION,
    MAX_RMS_RESIDUAL_PITCH,
    MIN_ON_LATTICE_FRACTION,
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
    "MIN_ON_LATTICE_FRACTION",
    "SpotFlag",
    "SpotSet",
    "Lattice",
    "estimate_pitch",
    "detect_spots",
    "fit_lattice",
    "check_lattice",
    "micro_image_diameter",
]
