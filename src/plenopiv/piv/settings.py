"""Validated settings of a multi-pass volumetric cross-correlation (:class:`PIVSettings`).

The settings are the one place where the PIV defaults live: the ``[piv]`` table of an
experiment file is this class (:mod:`plenopiv.config.experiment` builds it from the table).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

SUBPIXEL_METHODS = ("gaussian", "parabolic")
"""Valid values of :attr:`PIVSettings.subpixel`."""

REPLACEMENT_METHODS = ("median", "mean", "none")
"""Valid values of :attr:`PIVSettings.replacement`."""
DEFORMATION_ORDERS = (1, 2, 3, 4, 5)
"""Valid values of :attr:`PIVSettings.deformation_order` (1: trilinear, >1: B-spline)."""

MIN_WINDOW_VOX = 4
"""Smallest interrogation window edge, voxels: the 3-point peak fit needs distinct neighbours."""

MAX_PASSES = 100
"""Most passes a correlation may run."""

MAX_WINDOW_VOX = 1024
"""Largest interrogation window edge, voxels (a 1024³ float32 window pair is 8 GB)."""

UNCERTAINTY_METHODS = ("response", "correlation")
"""Valid values of :attr:`PIVSettings.uncertainty`."""

RESPONSE_DISPLACEMENTS = (1, 3)
"""Valid values of :attr:`PIVSettings.response_displacements`."""

RESPONSE_PARTICLES_PER_LENSLET = 0.15
"""Default seeding of the response's test pairs, particles per lenslet: the density the
validations were run at (docs/validation/vortex.md, uncertainty.md)."""

MAX_RESPONSE_PARTICLES_PER_LENSLET = 10.0
"""Largest seeding of the response's test pairs, particles per lenslet."""

MIN_PARTICLES_PER_WINDOW = 2
"""Default of :attr:`PIVSettings.min_particles_per_window`, particles (docs/methods.md,
*Particles per window*)."""

INTENSITY_CAP = 1.0
"""Default of :attr:`PIVSettings.intensity_cap`: the median particle's peak
(docs/methods.md#intensity-capping)."""


def _is_number(value) -> bool:
    """A real number that is not a boolean (``True`` is no threshold)."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_))


def _as_window(value, name):
    """Return one window as a ``(wz, wy, wx)`` tuple of int, or raise ValueError."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        value = (int(value),) * 3
    try:
        window = tuple(value)
    except TypeError:
        raise ValueError(
            f"{name} = {value!r}: expected an int or a (wz, wy, wx) tuple of int voxels"
        ) from None
    if len(window) != 3 or not all(
        isinstance(w, (int, np.integer)) and not isinstance(w, bool) for w in window
    ):
        raise ValueError(
            f"{name} = {value!r}: expected an int or a (wz, wy, wx) tuple of int voxels"
        )
    window = tuple(int(w) for w in window)
    if min(window) < MIN_WINDOW_VOX:
        raise ValueError(
            f"{name} = {window}: every window edge must be at least {MIN_WINDOW_VOX} voxels"
        )
    if max(window) > MAX_WINDOW_VOX:
        raise ValueError(
            f"{name} = {window}: every window edge must be at most {MAX_WINDOW_VOX} voxels"
        )
    return window


@dataclass(frozen=True)
class PIVSettings:
    """Validated settings of a multi-pass volumetric cross-correlation.

    Parameters
    ----------
    windows : int, (wz, wy, wx) or sequence of (wz, wy, wx)
        Interrogation window edge in voxels, per pass and per axis in the volume's index order
        ``(z, y, x)``. A single int or triple means one window size for every pass. Windows
        may differ per axis: plenoptic particles are elongated in Z, so a taller window in z
        (e.g. ``((32, 32, 32), (24, 16, 16))``) keeps enough particle pairs per window.
        Every edge is at least 4 voxels. Stored as a tuple of triples. Default
        ``((24, 16, 16), (16, 12, 12))``. An experiment file that leaves ``[piv] windows``
        unset gets windows chosen for its camera and box by the commands that run it
        (:func:`plenopiv.workflow.judgement.choose_unset`: 16 → 12 lenslet footprints
        laterally and 3.6 → 2.7 depth cells, cut to give 4 vectors along every axis of the
        box); windows it gives are never changed.
    overlap : float
        Fraction of a window shared with its neighbour, ``0 <= overlap < 1``. The window step
        is ``max(1, round(w * (1 - overlap)))`` voxels per axis.
    passes : int or None
        Number of passes, at least ``len(windows)``; the passes after the last listed window
        repeat it (WIDIM iterations at the final resolution). ``None`` means ``len(windows)``.
    deformation : bool
        True: deform both volumes by the predictor field (WIDIM, Scarano 2002). False: shift
        each window pair by the predictor rounded to whole voxels (discrete window offset).
    deformation_order : int
        Interpolation order used to deform the volumes, one of ``DEFORMATION_ORDERS``:
        1 is trilinear and 3 a cubic B-spline (numba kernels); 2, 4 and 5 are B-splines
        evaluated by ``scipy.ndimage.map_coordinates`` (slower). Trilinear deformation
        leaves a bias of about 0.03 voxel on images of 1-voxel standard deviation.
    median_threshold : float
        Threshold of the normalised median test (dimensionless, > 0); 2.0 is the value
        recommended by Westerweel & Scarano (2005).
    median_epsilon_vox : float
        Noise level added to the median residual, voxels (>= 0); 0.1 voxel after
        Westerweel & Scarano (2005).
    median_iterations : int
        Detection rounds of the median test (>= 1); each round ignores the vectors flagged
        before it, so that clustered outliers do not hide each other.
    smooth_predictor : bool
        Low-pass the predictor of every pass after the first with a [1, 2, 1]/4 filter per
        axis before deforming (the returned field is not smoothed). This keeps repeated
        deformation passes stable (Schrijer & Scarano 2008); a linear flow is not changed.
        The filter acts on every pass: filtering fewer predictors (only those before a
        smaller window, or none), or a weaker [1, 6, 1]/8 filter, leaves the lateral error of
        a vortex core (window-scale structure, not the filter) where it is and raises the
        random error elsewhere (docs/validation/uncertainty.md).
    subpixel : str
        Sub-voxel peak estimator, one of ``SUBPIXEL_METHODS``: ``"gaussian"`` (3-point
        Gaussian fit per axis, parabolic where a value is not positive) or ``"parabolic"``.
    replacement : str
        What becomes of the vectors rejected after the last pass (failed median test, empty
        window), one of ``REPLACEMENT_METHODS``: ``"median"`` (component-wise median of the
        usable 3x3x3 neighbours, the default), ``"mean"`` (their mean) or ``"none"`` (left
        NaN). Between passes rejected vectors are always filled by the local median, since
        window deformation needs a complete predictor.
    overlap_correction : bool
        Divide the correlation about its peak by the windows' overlap fraction
        ``prod(1 - |lag|/w)`` before the sub-voxel fit. Particle pairs cut by the window
        border weight the correlation by that triangle and pull the fitted peak towards zero
        by about ``2 sigma**2 / w`` voxels for particle images of standard deviation ``sigma``:
        0.5 voxel along z for the depth-elongated particles of a plenoptic reconstruction
        (sigma about 2 voxels) in 12-voxel windows, which then need many deformation passes
        to converge. Assumes window contents that are not periodic (real particle volumes).
    broad_peaks : bool
        With the Gaussian estimator, fit a least-squares Gaussian to the five samples about
        the peak along an axis where the peak is broad (fitted standard deviation of at
        least 1 voxel, window of at least 8 voxels): less noise than three samples of a
        peak several voxels wide, the depth axis of plenoptic volumes; and to seven samples
        where it is wide (standard deviation of at least 2 voxels, window of at least 12):
        five samples then lie within one standard deviation and see only the peak's top.
        Near the focal plane most particles keep their reconstructed depth for a small
        move while the rest jump by several voxels (a particle's light stays in one lenslet
        until its blur crosses the lenslet's edge), so the depth peak is a main lobe with a
        shoulder; seven samples take in more of the shoulder (docs/validation/vortex.md).
    uncertainty : str
        The per-vector uncertainty, one of ``UNCERTAINTY_METHODS``: ``"response"`` (the
        correlation statistics completed by the chain's measured response to known
        displacements, once per experiment: :mod:`plenopiv.piv.uncertainty`) or
        ``"correlation"`` (the correlation statistics only: faster, and short of the depth
        uncertainty near focus). Used by the pair's workflow, not by the correlation itself.
    response_displacements : int
        Test displacements of the ``"response"`` uncertainty, one of
        ``RESPONSE_DISPLACEMENTS``: 3 (fractions 0.5, 1.25 and 1.75 of a lenslet footprint
        laterally with 0.1, 0.25 and 0.5 depth resolution cells, the two axes apart, and the
        modulated pairs of the curvature term) or 1 (the middle one alone).
    response_particles_per_lenslet : float
        Seeding of the ``"response"`` uncertainty's test pairs, particles per lenslet of the
        field of view: this density times the lenslets the box covers, through the whole box.
        The response is measured once per experiment and shared by all its pairs, so it
        follows this setting, never a pair's own particle count: set it to the experiment's
        nominal seeding (default :data:`RESPONSE_PARTICLES_PER_LENSLET`).
    min_particles_per_window : int
        Fewest particles each window of a vector must hold in both volumes, particles
        (>= 0; 0 turns the test off). A particle counts in the window holding its position
        in the volume's particle table, the window placed where the pass took it; a vector
        whose windows hold fewer is not valid, flagged ``FLAG_FEW_PARTICLES`` (8) and
        replaced like an outlier. The default, :data:`MIN_PARTICLES_PER_WINDOW`, is where the
        error of the vectors leaves the noise on the synthetic cases
        (docs/methods.md#particles-per-window).
    intensity_cap : float
        Each volume is capped at this fraction of the median peak of its particles before
        it is correlated (>= 0; 0: not capped), so that every particle brighter than that
        weighs alike: the correlation then follows the particles rather than the brightest
        few, whose brightness is the laser's, the particle's size and the reconstruction's,
        not the flow's (intensity capping, Shavit, Lowe & Steinbuck 2007). The default,
        :data:`INTENSITY_CAP`: docs/methods.md#intensity-capping.
    continuity : bool
        Fit the finished field's depth component w to the continuity of an incompressible
        flow, ``∂w/∂z = -(∂u/∂x + ∂v/∂y)``, weighted by the uncertainties (u and v are not
        changed): near focus the correlation measures a fraction of w, and the lateral
        components hold what it misses (:mod:`plenopiv.piv.continuity`,
        docs/methods.md#depth-from-continuity). Set False for a flow that is not
        incompressible. Used by the pair's workflow and ``plenopiv piv``, not by the
        correlation itself.

    Raises
    ------
    ValueError
        If a value is outside its valid range; the message names the parameter.

    Notes
    -----
    This class is the ``[piv]`` table of an experiment file: every key, its default and its
    check are here (:mod:`plenopiv.config.experiment` builds it from the table).

    Examples
    --------
    >>> s = PIVSettings(windows=((32, 32, 32), (24, 16, 16)), passes=3)
    >>> s.window_vox(2)
    (24, 16, 16)
    """

    windows: tuple[tuple[int, int, int], ...] | tuple[int, int, int] | int = (
        (24, 16, 16),
        (16, 12, 12),
    )
    overlap: float = 0.5
    passes: int | None = 3
    deformation: bool = True
    deformation_order: int = 3
    median_threshold: float = 2.0
    median_epsilon_vox: float = 0.1
    median_iterations: int = 2
    smooth_predictor: bool = True
    subpixel: str = "gaussian"
    replacement: str = "median"
    overlap_correction: bool = True
    broad_peaks: bool = True
    uncertainty: str = "response"
    response_displacements: int = 3
    response_particles_per_lenslet: float = RESPONSE_PARTICLES_PER_LENSLET
    min_particles_per_window: int = MIN_PARTICLES_PER_WINDOW
    intensity_cap: float = INTENSITY_CAP
    continuity: bool = True

    def __post_init__(self):
        w = self.windows
        is_int = lambda e: isinstance(e, (int, np.integer)) and not isinstance(e, bool)  # noqa: E731
        if is_int(w) or (
            isinstance(w, Sequence) and not isinstance(w, str) and all(map(is_int, w))
        ):
            windows = (_as_window(w, "windows"),)
        elif isinstance(w, Sequence) and not isinstance(w, str) and len(w) > 0:
            windows = tuple(_as_window(e, f"windows[{i}]") for i, e in enumerate(w))
        else:
            raise ValueError(
                f"windows = {w!r}: expected an int, a (wz, wy, wx) triple or a non-empty "
                "sequence of triples (voxels, one per pass)"
            )
        object.__setattr__(self, "windows", windows)

        passes = len(windows) if self.passes is None else self.passes
        if (
            not isinstance(passes, (int, np.integer))
            or isinstance(passes, bool)
            or not len(windows) <= passes <= MAX_PASSES
        ):
            raise ValueError(
                f"passes = {self.passes!r}: expected an int >= len(windows) = {len(windows)} "
                f"and <= {MAX_PASSES} (or None for exactly one pass per window)"
            )
        object.__setattr__(self, "passes", int(passes))

        if not (_is_number(self.overlap) and 0.0 <= self.overlap < 1.0):
            raise ValueError(
                f"overlap = {self.overlap!r}: expected a fraction with 0 <= overlap < 1"
            )
        for name in ("deformation", "smooth_predictor", "overlap_correction", "broad_peaks",
                     "continuity"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} = {getattr(self, name)!r}: expected True or False")
        if self.deformation_order not in DEFORMATION_ORDERS or isinstance(
            self.deformation_order, bool
        ):
            raise ValueError(
                f"deformation_order = {self.deformation_order!r}: "
                f"expected one of {DEFORMATION_ORDERS}"
            )
        if not (_is_number(self.median_threshold) and self.median_threshold > 0):
            raise ValueError(
                f"median_threshold = {self.median_threshold!r}: expected a number > 0 "
                "(2.0 is the usual value)"
            )
        eps = self.median_epsilon_vox
        if not (_is_number(eps) and math.isfinite(eps) and eps >= 0):
            raise ValueError(
                f"median_epsilon_vox = {eps!r}: expected a finite number of voxels >= 0 (e.g. 0.1)"
            )
        it = self.median_iterations
        if not isinstance(it, (int, np.integer)) or isinstance(it, bool) or it < 1:
            raise ValueError(f"median_iterations = {it!r}: expected an int >= 1")
        if self.subpixel not in SUBPIXEL_METHODS:
            raise ValueError(f"subpixel = {self.subpixel!r}: expected one of {SUBPIXEL_METHODS}")
        if self.replacement not in REPLACEMENT_METHODS:
            raise ValueError(
                f"replacement = {self.replacement!r}: expected one of {REPLACEMENT_METHODS}"
            )
        if self.uncertainty not in UNCERTAINTY_METHODS:
            raise ValueError(
                f"uncertainty = {self.uncertainty!r}: expected one of {UNCERTAINTY_METHODS}"
            )
        n = self.response_displacements
        if isinstance(n, bool) or n not in RESPONSE_DISPLACEMENTS:
            raise ValueError(
                f"response_displacements = {n!r}: expected one of {RESPONSE_DISPLACEMENTS}"
            )
        ppl = self.response_particles_per_lenslet
        if not (_is_number(ppl) and 0 < ppl <= MAX_RESPONSE_PARTICLES_PER_LENSLET):
            raise ValueError(
                f"response_particles_per_lenslet = {ppl!r}: expected particles per lenslet "
                f"> 0 and <= {MAX_RESPONSE_PARTICLES_PER_LENSLET:g} (the experiment's nominal "
                "seeding)"
            )
        m = self.min_particles_per_window
        if not isinstance(m, (int, np.integer)) or isinstance(m, bool) or m < 0:
            raise ValueError(f"min_particles_per_window = {m!r}: expected a whole number of "
                             "particles >= 0 (0: no minimum)")
        object.__setattr__(self, "min_particles_per_window", int(m))
        cap = self.intensity_cap
        if not _is_number(cap) or not math.isfinite(cap) or cap < 0:
            raise ValueError(f"intensity_cap = {cap!r}: expected a fraction >= 0 of the median "
                             "particle's peak (0: the volumes are not capped)")
        object.__setattr__(self, "intensity_cap", float(cap))

    def window_vox(self, pass_index):
        """Window edge ``(wz, wy, wx)`` in voxels of pass ``pass_index`` (0-based)."""
        if not 0 <= pass_index < self.passes:
            raise ValueError(f"pass_index = {pass_index}: expected 0 <= pass_index < {self.passes}")
        return self.windows[min(pass_index, len(self.windows) - 1)]
