"""Lattice quality: refuse a lattice not of its grid type, or not from a calibration image.

:func:`check_lattice_shape` (used by :func:`~plenopiv.calibration.lattice_fit.fit_lattice`)
refuses a lattice whose shape is not that of its grid type; :func:`check_lattice` one whose
rms residual or missing positions say the image is not a calibration image of this camera.
"""

from __future__ import annotations

import math

import numpy as np

from plenopiv.errors import CalibrationError

MAX_RMS_RESIDUAL_PITCH = 0.015
MAX_MISSING_FRACTION = 0.05


def check_lattice(lattice, *, what="the image", max_rms_residual_pitch=MAX_RMS_RESIDUAL_PITCH,
                  max_missing_fraction=MAX_MISSING_FRACTION):
    """Refuse a lattice that says its image is not a calibration image of this camera.

    Parameters
    ----------
    lattice : Lattice
    what : str
        How the error names the image (e.g. ``"the focal-point image"``).
    max_rms_residual_pitch : float or None
        Largest rms lattice residual as a fraction of the pitch (default 1.5 %: 0.25 px at a
        17 px pitch; focal-point and white images reach 0.001-0.01 of the pitch, a scene or
        ruler image 0.02 and more). None skips the check.
    max_missing_fraction : float or None
        Largest fraction of the lattice positions inside the image that hold no spot
        (default 5 %). None skips the check.

    Returns
    -------
    dict
        ``lattice.quality``.

    Raises
    ------
    CalibrationError
        Naming the figure, its value and the threshold.
    """
    q = lattice.quality
    hint = ("is it a focal-point, alignment or white image of this camera, not a scene or a "
            "ruler?")
    if max_rms_residual_pitch is not None and q["rms_residual_pitch"] > max_rms_residual_pitch:
        raise CalibrationError(
            f"{what}: the spots fit a regular {q['grid']} lattice only to "
            f"{q['rms_residual_px']:.3f} px rms, {100 * q['rms_residual_pitch']:.2f} % of its "
            f"pitch {float(np.mean(q['pitch_px'])):.2f} px (at most "
            f"{100 * max_rms_residual_pitch:g} %, max_rms_residual_pitch); {hint}"
        )
    if max_missing_fraction is not None and q["missing_fraction"] > max_missing_fraction:
        shown = ", ".join(f"({i}, {j})" for i, j in lattice.missing_index[:6])
        more = " ..." if lattice.n_missing > 6 else ""
        raise CalibrationError(
            f"{what}: {q['n_missing']} lattice positions inside the image hold no spot, "
            f"{100 * q['missing_fraction']:.1f} % of them (at most "
            f"{100 * max_missing_fraction:g} %, max_missing_fraction); grid indices "
            f"{shown}{more}; {hint} (dark corners outside the lens's image circle: raise "
            "max_missing_fraction)"
        )
    return q


def check_lattice_shape(grid, basis, shift, tol):
    """Raise CalibrationError when the fitted lattice does not have its grid type's shape."""
    e_row, e_col = basis
    p_col = float(np.hypot(*e_col))
    p_row = float(np.hypot(*e_row))
    shear = abs(math.asin(np.clip((e_row @ e_col) / (p_row * p_col), -1.0, 1.0)))
    other = "hexagonal" if grid == "square" else "square"
    ratio_expected = 1.0 if grid == "square" else math.sqrt(3.0) / 2.0
    checks = [
        ("the angle between its row and column steps departs from 90 degrees by "
         f"{math.degrees(shear):.1f} degrees", shear, f"{math.degrees(tol):.1f} degrees"),
        (f"its row spacing is {p_row / p_col:.3f} of its pitch, expected {ratio_expected:.3f}",
         abs(p_row / (ratio_expected * p_col) - 1.0), f"{100 * tol:g} %"),
    ]
    if grid == "hexagonal":
        dev = float(np.hypot(*(shift - 0.5 * e_col))) / p_col
        checks.append(
            (f"its odd rows are shifted by ({shift[0]:.2f}, {shift[1]:.2f}) px, expected half "
             f"a pitch along its rows ({0.5 * e_col[0]:.2f}, {0.5 * e_col[1]:.2f}) px", dev,
             f"{100 * tol:g} % of the pitch")
        )
    for text, value, limit in checks:
        if value > tol:
            raise CalibrationError(
                f"the spots do not form a {grid} lattice: {text} (at most {limit}, "
                f"max_shape_error = {tol:g}); is the grid type wrong (a {other} array)?"
            )
