"""Lattice quality: refuse a lattice not of its grid type, or not from a calibration image.

:func:`check_lattice_shape` (used by :func:`~plenopiv.calibration.lattice_fit.fit_lattice`)
refuses a lattice whose shape is not that of its grid type; :func:`check_lattice` one whose
spots do not sit on it (no lenslet lattice: a scene, a ruler, a particle image) or whose
missing positions say the image is not a calibration image of this camera.

See docs/methods.md#lattice-fit.
"""

from __future__ import annotations

import math

import numpy as np

from plenopiv.calibration.spot_types import ON_LATTICE_RADIUS
from plenopiv.errors import CalibrationError

#: The fewest of the complete spots that must lie within ON_LATTICE_RADIUS pitch of a node
MIN_ON_LATTICE_FRACTION = 0.9
MAX_MISSING_FRACTION = 0.05
#: The most uneven lighting of the lenslets (Lattice.lenslet_contrast) of a calibration image
MAX_LENSLET_CONTRAST = 0.2
#: No limit on the rms lattice residual by default: real arrays scatter about their lattice
MAX_RMS_RESIDUAL_PITCH = None

_NEEDS = {"focal-point": "the lenslets' focal spots (a white sheet through the stopped-down "
                        "lens)",
          "alignment": "one spot on each lenslet's axis (collimated light, the main lens off)",
          "white": "every micro-image evenly lit (a white sheet at the working aperture)"}
"""What each calibration image must show, by the word that names it."""

#: The likely swap where an image's spots sit on no lattice
NO_LATTICE = "a particle image or a scene"


def swap_hint(what: str, likely: str) -> str:
    """The hint that follows what the image shows: ``likely`` given as ``what``, and its need."""
    need = next((v for k, v in _NEEDS.items() if k in what), None)
    return f"{likely} given as {what}?" + (f" It must show {need}" if need else "")


def check_lattice(lattice, *, what="the image", max_rms_residual_pitch=MAX_RMS_RESIDUAL_PITCH,
                  max_missing_fraction=MAX_MISSING_FRACTION,
                  min_on_lattice_fraction=MIN_ON_LATTICE_FRACTION,
                  max_lenslet_contrast=MAX_LENSLET_CONTRAST):
    """Refuse a lattice that says its image is not a calibration image of this camera.

    Parameters
    ----------
    lattice : Lattice
    what : str
        How the error names the image (e.g. ``"the focal-point image"``).
    max_rms_residual_pitch : float or None
        Largest rms lattice residual as a fraction of the pitch; None (default) sets no
        limit: a real array's lenslets scatter about their lattice (2 % of the pitch in a
        light-field microscope), which :attr:`~plenopiv.calibration.spot_types.Lattice.
        best_centres_px` keeps, and the periodicity test below tells a lattice from none.
    max_missing_fraction : float or None
        Largest fraction of the lattice positions inside the image that hold no spot
        (default 5 %). Partial lenslets at the image's edges are not counted. None skips
        the check.
    min_on_lattice_fraction : float or None
        The fewest of the complete spots that must lie within 0.15 of the pitch of their
        lattice node (default 90 %,
        :attr:`~plenopiv.calibration.spot_types.Lattice.on_lattice_fraction`). A lenslet
        array with a scatter of up to 5 % of its pitch per axis keeps 98.9 % of its spots
        there; the spots of a scene, a particle image or of noise fall there by area alone,
        about 7 %. None skips the check.
    max_lenslet_contrast : float or None
        The most uneven lighting of the lenslets
        (:attr:`~plenopiv.calibration.spot_types.Lattice.lenslet_contrast`, default 0.2): a
        calibration image lights its lenslets alike up to a smooth vignetting and their
        throughput (±10 % gives 0.11-0.13); a ruler or a scene, whose micro-images form a
        lattice too, modulates them (0.24-0.45). None skips the check.

    Returns
    -------
    dict
        ``lattice.quality``.

    Raises
    ------
    CalibrationError
        Naming what was found, its value and the threshold.
    """
    q = lattice.quality
    pitch = float(q["lenslet_pitch_px"])
    if min_on_lattice_fraction is not None and \
            q["on_lattice_fraction"] < min_on_lattice_fraction:
        raise not_a_lattice(what, q["on_lattice_fraction"], q["n_spots"] - q["n_edge"],
                            q["grid"], pitch, q["rms_residual_px"], min_on_lattice_fraction)
    if max_rms_residual_pitch is not None and q["rms_residual_pitch"] > max_rms_residual_pitch:
        raise CalibrationError(
            f"{what}: the spots fit a regular {q['grid']} lattice only to "
            f"{q['rms_residual_px']:.3f} px rms, {100 * q['rms_residual_pitch']:.2f} % of its "
            f"pitch {pitch:.2f} px (at most {100 * max_rms_residual_pitch:g} %, "
            f"max_rms_residual_pitch); {swap_hint(what, NO_LATTICE)}"
        )
    if max_missing_fraction is not None and q["missing_fraction"] > max_missing_fraction:
        shown = ", ".join(f"({i}, {j})" for i, j in lattice.missing_index[:6])
        more = " ..." if lattice.n_missing > 6 else ""
        raise CalibrationError(
            f"{what}: {q['n_missing']} lattice positions inside the image hold no spot, "
            f"{100 * q['missing_fraction']:.1f} % of them (at most "
            f"{100 * max_missing_fraction:g} %, max_missing_fraction); grid indices "
            f"{shown}{more}; {holes_hint(lattice, what)}"
        )
    if max_lenslet_contrast is not None and q["lenslet_contrast"] > max_lenslet_contrast:
        raise CalibrationError(
            f"{what}: a lattice of {q['n_spots']} micro-images, but unevenly lit: one in ten "
            f"differs from its neighbours by more than {100 * q['lenslet_contrast']:.0f} % "
            f"(lenslet_contrast; a calibration image at most {100 * max_lenslet_contrast:g} "
            f"%, max_lenslet_contrast): the micro-images of a scene, a ruler or dense "
            f"particles; {swap_hint(what, 'a ruler, a scene or a particle image')}"
        )
    return q


def holes_hint(lattice, what: str) -> str:
    """The hint for a lattice with holes, from where they lie.

    Along the lattice's border (within 2 lenslets of it for most of them): dark corners or
    edges, outside the lens's image circle. On far fewer rows or columns than scattered holes
    would take: a ruler, whose ticks hide lines of lenslets. Scattered: the lit lenslets of
    a particle image or a scene.
    """
    holes = np.asarray(lattice.missing_index).reshape(-1, 2)
    index = np.asarray(lattice.grid_index)[np.asarray(lattice.inlier, bool)]
    if not len(holes) or not len(index):
        return swap_hint(what, NO_LATTICE)
    lo, hi = index.min(axis=0), index.max(axis=0)
    border = np.minimum(holes - lo, hi - holes).min(axis=1) <= 2
    if border.mean() > 0.6:
        return ("its holes lie along its border: dark corners or edges outside the lens's "
                "image circle? (raise max_missing_fraction)")
    for axis, name in ((1, "columns"), (0, "rows")):
        # n holes scattered over m lines fill m (1 - exp(-n/m)) of them; a ruler's far fewer
        lines = len(np.unique(holes[:, axis]))
        span = hi[axis] - lo[axis] + 1
        if lines < 0.5 * span * (1.0 - math.exp(-len(holes) / span)):
            return (f"its holes fall on {lines} of its {span} {name}, as a ruler's ticks "
                    f"hide lines of lenslets; {swap_hint(what, 'a ruler image')}")
    return f"its holes are scattered over the lattice; {swap_hint(what, NO_LATTICE)}"


def not_a_lattice(what, fraction, n_complete, grid, pitch_px, rms_px,
                  minimum=MIN_ON_LATTICE_FRACTION) -> CalibrationError:
    """The error that says an image's spots do not sit on a lattice, with what was found."""
    return CalibrationError(
        f"{what}: not a lenslet lattice: only {100 * fraction:.0f} % of its {n_complete} "
        f"complete spots lie within {ON_LATTICE_RADIUS:g} of a pitch of a node of the "
        f"best-fitting {grid} lattice (pitch {pitch_px:.2f} px, rms residual {rms_px:.2f} px); "
        f"a lenslet array puts at least {100 * minimum:g} % there (min_on_lattice_fraction), "
        f"spots with no lattice about {100 * math.pi * ON_LATTICE_RADIUS ** 2:.0f} %; "
        f"{swap_hint(what, NO_LATTICE)}")


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


def pitch_sigma(lattice) -> float:
    """Relative standard error of a lattice's pitch from its inliers' residuals.

    Least squares of the positions ``origin + i b_1 + j b_2`` gives each basis vector the
    standard error ``sigma / sqrt(S_k)`` per component, ``sigma`` the residuals' rms per
    coordinate and ``S_k`` the sum of squares of the index ``k`` about its mean; over the
    pitch ``p`` that is ``sigma / (p sqrt(S_k))``, and the two axes together (inverse-variance
    mean) ``sigma / (p sqrt(S_1 + S_2))``. The residuals' rms, not their robust spread: a few
    centres pulled off their nodes (a hot pixel beside a spot) move the pitch as much as
    they weigh in it. NaN with fewer than 3 inliers.
    """
    inlier = np.asarray(lattice.inlier, dtype=bool)
    if np.count_nonzero(inlier) < 3:
        return float("nan")
    res = np.asarray(lattice.residual_px, dtype=np.float64)[inlier]
    idx = np.asarray(lattice.grid_index, dtype=np.float64)[inlier]
    sigma = math.sqrt(float(np.mean(res * res)))
    spread = float(np.sum((idx - idx.mean(axis=0)) ** 2))
    pitch = float(np.mean(lattice.pitch_px))
    if not (spread > 0 and pitch > 0):
        return float("nan")
    return sigma / (pitch * math.sqrt(spread))
