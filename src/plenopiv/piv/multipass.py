"""The WIDIM driver: :func:`correlate_volumes`, multi-pass 3-D PIV of two particle volumes.

Each pass correlates every window pair circularly through staged real FFTs, fits the peak
per axis (3-point Gaussian, or a least-squares Gaussian on the overlap-corrected correlation
where the peak is broad), validates the field by the normalised median test and replaces the
outliers; the next pass correlates the volumes deformed symmetrically by that predictor
(Scarano 2002). After the last pass each vector gets its standard uncertainty from the
correlation statistics (Wieneke 2015) and the error the iteration left.

See docs/methods.md#multi-pass-correlation, #peak-fit, #window-deformation, #outlier-test
and #per-vector-uncertainty, with the references.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from plenopiv.conventions import voxel_to_world
from plenopiv.errors import PIVError
from plenopiv.piv.correlation import _correlate_pass, _peak_refinement
from plenopiv.piv.evidence import capped, particle_table, particle_voxels, window_counts
from plenopiv.piv.field import (
    FLAG_EMPTY,
    FLAG_FEW_PARTICLES,
    FLAG_MASKED,
    FLAG_OUTLIER,
    VectorField,
)
from plenopiv.piv.inputs import (
    _check_engine,
    _check_mask,
    _check_volumes,
    _check_windows,
    _grid_geometry,
    _numba_threads,
    _resolve_workers,
)
from plenopiv.piv.outliers import _median_test, _replace, _replace_mean, _smooth_predictor
from plenopiv.piv.settings import PIVSettings
from plenopiv.piv.statistics import _correlation_uncertainty, _rejected_uncertainty
from plenopiv.piv.windows import (
    _centre_mask,
    _deform,
    _interpolate_field,
    _spline_coefficients,
    _window_layout,
)


def correlate_volumes(
    volume_a,
    volume_b,
    grid,
    *,
    settings=None,
    workers=None,
    engine="numba",
    progress: Callable[[dict], None] | None = None,
    mask=None,
    particles=None,
):
    r"""Measure the displacement field between two particle volumes by multi-pass 3-D PIV.

    Parameters
    ----------
    volume_a, volume_b : array_like, shape (nz, ny, nx)
        Reconstructed intensities (arbitrary units) at the first and second exposure, indexed
        ``[z, y, x]`` on the same grid; finite values. Converted to float32; not changed.
    grid : VolumeGrid or similar
        The volumes' grid: ``origin``, the ``(x, y, z)`` centre of voxel ``[0, 0, 0]`` in
        metres, and the voxel edge ``(dx, dy, dz)`` (or one edge) in metres, named ``voxel``
        as in :class:`plenopiv.camera.grid.VolumeGrid` or ``voxel_size``. If it has ``shape``,
        that must equal the volumes' shape.
    settings : PIVSettings, keyword-only
        Windows, passes, deformation and validation settings; ``PIVSettings()`` if None.
    workers : int, keyword-only
        Threads for the FFTs (``scipy.fft`` ``workers``) and the numba kernels (>= 1);
        None uses every core.
    engine : {"numba", "numpy"}, keyword-only
        Kernel implementation: ``"numba"`` (fast) or its plain-NumPy twin (reference).
    progress : callable, keyword-only
        Called after each pass with a dict holding ``pass`` (1-based), ``passes``,
        ``window_vox``, ``n_vectors`` and ``n_outliers``.
    mask : array_like of bool, shape (nz, ny, nx), keyword-only
        Volume mask on the volumes' grid: True for voxels outside the flow (a model, a wall).
        Masked voxels are set to zero in both volumes before correlating, and a vector whose
        window centre lies in the mask (the mask, interpolated trilinearly at the centre, is
        at least 0.5) is NaN, not valid, and flagged ``FLAG_MASKED``. None: no mask.
    particles : (positions_a, positions_b), keyword-only
        The volumes' particle tables, each ``(N, 3)`` ``(x, y, z)`` metres on ``grid``. A
        vector whose windows hold fewer than ``settings.min_particles_per_window`` of them
        in either volume (each window placed where the pass took it) is not valid and
        flagged ``FLAG_FEW_PARTICLES``. None: the volumes' local maxima above 0.1 of their
        bright level are the particles (:func:`plenopiv.piv.evidence.particle_table`).

    Returns
    -------
    VectorField
        Displacements (metres) on the window-centre grid of the last pass, with each
        vector's quality (peak height, peak ratio, flag, replaced, particles per window) and
        standard uncertainty.

    Raises
    ------
    PIVError
        If the volumes differ in shape, are not 3-D, hold non-finite values, do not fit the
        windows, the grid is unusable, or no window holds enough particles.
    ValueError
        If an option is outside its valid set.

    Notes
    -----
    Each window pair is correlated through real FFTs and its peak refined per axis by a
    3-point Gaussian fit; after each pass the field is validated, outliers are replaced and
    both volumes are deformed by the result (WIDIM, Scarano 2002). The uncertainty comes
    from correlation statistics (Wieneke 2015) and the last pass's correction. The equations,
    the bias of one pass and the references are in :mod:`plenopiv.piv.multipass`.

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> rng = np.random.default_rng(0)
    >>> a = rng.random((32, 32, 32), dtype=np.float32)
    >>> b = np.roll(a, (1, -2, 3), axis=(0, 1, 2))  # [z, y, x]; periodic: no overlap loss
    >>> grid = SimpleNamespace(origin=(0.0, 0.0, 0.0), voxel_size=1e-4)
    >>> s = PIVSettings(windows=32, passes=1, overlap_correction=False)
    >>> field = correlate_volumes(a, b, grid, settings=s)
    >>> [round(float(c[0, 0, 0]) / 1e-4, 3) for c in (field.u, field.v, field.w)]
    [3.0, -2.0, 1.0]
    """
    settings = PIVSettings() if settings is None else settings
    if not isinstance(settings, PIVSettings):
        raise ValueError(f"settings = {settings!r}: expected a PIVSettings")
    kernels = _check_engine(engine)
    workers = _resolve_workers(workers)
    if progress is not None and not callable(progress):
        raise ValueError(f"progress = {progress!r}: expected a callable or None")
    vol_a, vol_b = _check_volumes(volume_a, volume_b)
    origin, voxel = _grid_geometry(grid, vol_a.shape)
    _check_windows(settings, vol_a.shape)
    mask = _check_mask(mask, vol_a.shape)
    if mask is not None:
        vol_a = np.where(mask, np.float32(0), vol_a)
        vol_b = np.where(mask, np.float32(0), vol_b)
    tables, voxels = _particle_tables(particles, (vol_a, vol_b), origin, voxel, mask)
    vol_a, vol_b = map(capped, (vol_a, vol_b), voxels, (settings.intensity_cap,) * 2)
    with _numba_threads(workers):
        return _multipass(vol_a, vol_b, origin, voxel, settings, workers, kernels, progress,
                          mask=mask, tables=tables)


def _particle_tables(particles, volumes, origin, voxel, mask):
    """The :func:`particle_table` of both volumes and their :func:`particle_voxels`.

    From ``particles`` or, where None, the volumes' local maxima.
    """
    shape = volumes[0].shape
    if particles is None:
        voxels = tuple(particle_voxels(shape, volume=v) for v in volumes)
    elif not (isinstance(particles, (tuple, list)) and len(particles) == 2):
        raise ValueError(f"particles = {type(particles).__name__}: expected (positions_a, "
                         "positions_b), two (N, 3) tables of (x, y, z) metres, or None")
    else:
        voxels = []
        for name, p in zip("AB", particles, strict=True):
            p = np.asarray(p, dtype=float)
            if p.size and (p.ndim != 2 or p.shape[1] != 3):
                raise PIVError(f"the particle table of volume {name} has shape {p.shape}: "
                               "expected (N, 3) positions (x, y, z) in metres")
            voxels.append(particle_voxels(shape, positions=p, origin=origin, voxel=voxel))
    tables = tuple(particle_table(shape, index=i, mask=mask) for i in voxels)
    return tables, tuple(voxels)


class _Pass(NamedTuple):
    """What one correlation pass measured, in voxels ``(z, y, x)``, flat over its windows.

    ``last`` is what its correlation saw: the two volumes (deformed or not), the window
    shifts of a discrete offset (or None) and the displacement it found between its windows;
    ``change`` is what the pass changed in the estimate (None for the first pass);
    ``offsets`` where each window lay in the undeformed volumes A and B relative to its place
    in the layout, ``(n, 3)`` voxels each (None: not moved).
    """

    estimate: np.ndarray
    peak: np.ndarray
    snr: np.ndarray
    last: tuple
    change: np.ndarray | None
    offsets: tuple = (None, None)


def _first_pass(vol_a, vol_b, layout, correlate):
    """Correlate the undeformed volumes on the windows of ``layout``."""
    estimate, peak, snr = correlate(vol_a, vol_b, layout, shift=None)
    return _Pass(estimate, peak, snr, (vol_a, vol_b, None, estimate), None)


def _deformed_pass(vol_a, vol_b, layout, predictor, previous, deform, correlate):
    """Deform both volumes by ``-/+ predictor / 2`` and add the corrector they give."""
    voxel_axes = tuple(np.arange(n, dtype=float) for n in vol_a.shape)
    # float32 throughout: much faster than float64 for a full-size field
    dense = _interpolate_field(predictor.astype(np.float32), previous.centres, voxel_axes)
    a_def = deform(vol_a, dense, -0.5, "a")
    b_def = deform(vol_b, dense, +0.5, "b")
    del dense
    corrector, peak, snr = correlate(a_def, b_def, layout, shift=None)
    at_centres = _interpolate_field(predictor, previous.centres, layout.centres).reshape(3, -1).T
    estimate = at_centres + corrector
    return _Pass(estimate, peak, snr, (a_def, b_def, None, corrector), corrector,
                 (-0.5 * at_centres, 0.5 * at_centres))


def _offset_pass(vol_a, vol_b, layout, predictor, previous, correlate):
    """Shift each window pair by the predictor rounded to whole voxels (discrete offset)."""
    at_centres = _interpolate_field(predictor, previous.centres, layout.centres)
    shift = np.rint(at_centres.reshape(3, -1).T).astype(np.int64)
    corrector, peak, snr = correlate(vol_a, vol_b, layout, shift=shift)
    estimate = shift + corrector
    change = estimate - at_centres.reshape(3, -1).T
    return _Pass(estimate, peak, snr, (vol_a, vol_b, shift, corrector), change,
                 (-(shift // 2), shift - shift // 2))


def _deformer(vol_a, vol_b, settings, kernels):
    """``deform(volume, field_vox, factor, which)`` for the passes, B-spline prefilter done once."""
    order = settings.deformation_order
    coeffs = {"a": None, "b": None}
    if settings.deformation and order > 1 and settings.passes > 1:
        coeffs = {"a": _spline_coefficients(vol_a, order), "b": _spline_coefficients(vol_b, order)}

    def deform(volume, field_vox, factor, which):
        return _deform(volume, field_vox, factor, order, kernels, coeffs[which])

    return deform


def _multipass(vol_a, vol_b, origin, voxel, settings, workers, kernels, progress, *, mask,
               tables):
    """Run the WIDIM loop of :func:`correlate_volumes` on checked inputs.

    ``tables``: the :func:`~plenopiv.piv.evidence.particle_table` of volumes A and B.
    """
    correlate = functools.partial(
        _correlate_pass,
        gaussian=settings.subpixel == "gaussian",
        workers=workers,
        kernels=kernels,
        refine=_peak_refinement(settings),
    )
    deform = _deformer(vol_a, vol_b, settings, kernels)
    predictor = None  # (3, nz, ny, nx) field in voxels on `previous.centres`
    previous = None
    result = None
    earlier_change = None  # the previous pass's change, when it had the last pass's windows
    for k in range(settings.passes):
        layout = _window_layout(vol_a.shape, settings.window_vox(k), settings.overlap)
        if result is not None:
            same = previous.window == layout.window and previous.shape == layout.shape
            earlier_change = result.change if same else None
        if predictor is None:
            result = _first_pass(vol_a, vol_b, layout, correlate)
        elif settings.deformation:
            result = _deformed_pass(vol_a, vol_b, layout, predictor, previous, deform, correlate)
        else:
            result = _offset_pass(vol_a, vol_b, layout, predictor, previous, correlate)
        in_mask = _centre_mask(mask, layout)
        empty = ~np.all(np.isfinite(result.estimate), axis=1) & ~in_mask
        result.estimate[in_mask] = np.nan
        count, few = _evidence(result, layout, tables, settings, in_mask | empty)
        field_vox = result.estimate.T.reshape((3,) + layout.shape)
        outlier, _ = _median_test(
            field_vox,
            settings.median_threshold,
            settings.median_epsilon_vox,
            settings.median_iterations,
            kernels,
        )
        validated = _replace(field_vox, outlier, kernels)
        predictor = _smooth_predictor(validated) if settings.smooth_predictor else validated
        previous = layout
        if progress is not None:
            progress({"pass": k + 1, "passes": settings.passes, "window_vox": layout.window,
                      "n_vectors": int(outlier.size), "n_outliers": int(outlier.sum())})
    in_mask = in_mask.reshape(layout.shape)
    final = _final_vectors(field_vox, validated, outlier, in_mask, empty.reshape(layout.shape),
                           few.reshape(layout.shape), settings, kernels)
    sigma_vox, parts = _uncertainty(result, layout, final, in_mask, voxel, settings, kernels,
                                    earlier_change)
    return _vector_field(layout, origin, voxel, result, final, sigma_vox, parts, settings,
                         count.reshape(layout.shape))


def _particles(n: int) -> str:
    return f"{n} particle" if n == 1 else f"{n} particles"


def _evidence(result, layout, tables, settings, rejected):
    """The particles of each window in both volumes, and the windows holding too few.

    Returns ``(count, few)``, flat over the windows: the fewer of the particles its window
    held in volume A and in volume B, and True where that is below
    ``settings.min_particles_per_window`` (and the window is not ``rejected`` already, empty
    or masked); their estimates become NaN, like an empty window's. Raises PIVError when no
    window is left.
    """
    count = np.minimum(*(window_counts(t, layout, o)
                         for t, o in zip(tables, result.offsets, strict=True)))
    few = (count < settings.min_particles_per_window) & ~rejected
    result.estimate[few] = np.nan
    if few.any() and (few | rejected).all():
        held = [_particles(int(t[-1, -1, -1])) for t in tables]
        raise PIVError(
            f"no window of {layout.window} voxels holds {settings.min_particles_per_window} "
            f"particles in both volumes (volume A holds {held[0]}, B {held[1]}; the most in "
            f"one window: {int(count.max())}): too few particles for a vector; seed more, use "
            "larger [piv] windows, or lower [piv] min_particles_per_window")
    return count, few


class _Final(NamedTuple):
    """The last pass's vectors after replacement, voxels ``(3, nz, ny, nx)``, and their flags.

    ``disagreement`` is, per component, how far a rejected vector's own measurement lay from
    the local median of its neighbours (voxels; 0 where a vector was not rejected, was masked
    or had no measurement).
    """

    displacement: np.ndarray
    rejected: np.ndarray
    replaced: np.ndarray
    flag: np.ndarray
    disagreement: np.ndarray


def _final_vectors(field_vox, validated, outlier, in_mask, empty, few, settings, kernels):
    """Flag the last pass's rejected vectors and replace them as ``settings.replacement`` says."""
    rejected = outlier | in_mask
    flag = (
        np.where(outlier & ~empty & ~in_mask & ~few, FLAG_OUTLIER, 0)
        | np.where(empty, FLAG_EMPTY, 0)
        | np.where(in_mask, FLAG_MASKED, 0)
        | np.where(few, FLAG_FEW_PARTICLES, 0)
    ).astype(np.uint8)
    if settings.replacement == "median":
        result = validated.copy()
    elif settings.replacement == "mean":
        result = _replace_mean(field_vox, outlier, kernels)
    else:
        result = np.where(rejected[None], np.nan, field_vox)
    result[:, in_mask] = np.nan
    replaced = rejected & ~in_mask & np.all(np.isfinite(result), axis=0)
    measured = outlier & ~in_mask & np.all(np.isfinite(field_vox), axis=0)
    disagreement = np.where(measured[None], np.abs(np.nan_to_num(field_vox - validated)), 0.0)
    return _Final(result, rejected, replaced, flag, disagreement)


def _uncertainty(last_pass, layout, final, in_mask, voxel, settings, kernels,
                 earlier_change=None):
    """Standard uncertainty (3, nz, ny, nx) in voxels and its terms in metres ``(u, v, w)``.

    Besides the terms, ``parts`` holds how far each rejected vector's own measurement lay
    from its neighbours' median (``"rejected_disagreement"``, 0 elsewhere), the signed
    changes of the last pass (``"last_corrector"``) and, when it had the same windows, of
    the pass before (``"previous_corrector"``), metres ``(u, v, w)``, for
    :mod:`plenopiv.piv.uncertainty`.
    """
    sigma_cs = _correlation_uncertainty(*last_pass.last, layout, settings, kernels)
    last_change = np.zeros_like(sigma_cs)
    if last_pass.change is not None:
        # the last pass's change of the estimate: what the iteration still had to correct
        last_change = np.abs(np.nan_to_num(last_pass.change.T.reshape(sigma_cs.shape)))
    sigma_vox = np.sqrt(sigma_cs**2 + last_change**2)
    sigma_vox = _rejected_uncertainty(
        sigma_vox, final.displacement, final.rejected, in_mask, kernels
    )
    metres = np.array([voxel[2], voxel[1], voxel[0]])[:, None, None, None]  # (z, y, x) order
    parts = {name: (a * metres)[::-1] for name, a in
             (("correlation", sigma_cs), ("last_correction", last_change),
              ("rejected_disagreement", final.disagreement))}
    for name, change in (("last_corrector", last_pass.change),
                         ("previous_corrector", earlier_change)):
        if change is not None:
            parts[name] = (change.T.reshape(sigma_cs.shape) * metres)[::-1]
    return sigma_vox, parts


def _vector_field(layout, origin, voxel, last_pass, final, sigma_vox, parts, settings,
                  count):
    """Assemble the :class:`VectorField` in metres from the last pass's results in voxels."""
    shape = layout.shape
    cz, cy, cx = layout.centres
    zeros = np.zeros
    x = voxel_to_world(np.stack([zeros(cx.size), zeros(cx.size), cx], axis=-1), origin, voxel)[:, 0]
    y = voxel_to_world(np.stack([zeros(cy.size), cy, zeros(cy.size)], axis=-1), origin, voxel)[:, 1]
    z = voxel_to_world(np.stack([cz, zeros(cz.size), zeros(cz.size)], axis=-1), origin, voxel)[:, 2]
    dx, dy, dz = voxel
    result = final.displacement
    return VectorField(
        x=x,
        y=y,
        z=z,
        u=result[2] * dx,
        v=result[1] * dy,
        w=result[0] * dz,
        valid=~final.rejected,
        snr=last_pass.snr.reshape(shape),
        correlation=last_pass.peak.reshape(shape),
        n_replaced=int(final.replaced.sum()),
        settings=settings,
        replaced=final.replaced,
        flag=final.flag,
        u_uncertainty=sigma_vox[2] * dx,
        v_uncertainty=sigma_vox[1] * dy,
        w_uncertainty=sigma_vox[0] * dz,
        uncertainty_parts=parts,
        particles_per_window=count,
    )
