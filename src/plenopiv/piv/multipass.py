r"""The WIDIM driver: :func:`correlate_volumes`, multi-pass 3-D PIV of two particle volumes.

Method
------
*Correlation.* Each window pair ``a, b`` (means removed) is correlated circularly through
real FFTs, without zero padding, batched over all windows of a pass:

.. math:: R(s) = \frac{\sum_x a(x)\, b(x + s)}{\sqrt{\sum_x a^2 \sum_x b^2}}
          = \frac{\mathcal{F}^{-1}[\overline{\hat a}\, \hat b](s)}
                  {\lVert a\rVert\, \lVert b\rVert}

so the peak height is a correlation coefficient. The integer peak ``s_0`` is refined per
axis by the 3-point Gaussian fit (Willert & Gharib 1991)

.. math:: \delta = \frac{\ln R_{-1} - \ln R_{+1}}{2(\ln R_{-1} - 2 \ln R_0 + \ln R_{+1})}

falling back to the parabola (``R`` in place of ``ln R``) where a value is not positive,
and to the integer peak where the parabola is not concave. The peak ratio ``snr`` is the
primary peak over the highest other face-connected local maximum.

With ``settings.overlap_correction`` (default) the samples about the peak are first
divided by the overlap fraction of their lag, :math:`R(s) / \prod_i (1 - |s_i|/w_i)`
(Westerweel 1997), which removes the bias of particle pairs lost across the window
border; with ``settings.broad_peaks`` (default) the five samples ``s_0 - 2 .. s_0 + 2``
along each axis are fitted by a weighted least-squares Gaussian, whose vertex (within
1.5 voxel of ``s_0``) is taken where that Gaussian is at least 1 voxel wide (standard
deviation), and the seven samples ``s_0 - 3 .. s_0 + 3`` (vertex within 2.5 voxels) where
it is at least 2 voxels wide (the depth peaks of plenoptic volumes, which five samples see
only the top of; the overlap correction moves their vertex up to :math:`2\sigma^2/w`, over
a voxel, from the raw correlation's highest sample).

The window spectra are computed one axis at a time, so that the 1-D transforms shared by
overlapping windows are done once (x for every line segment of the volume, y for every
plane of a window column, z per window), in float32 on ``workers`` threads.

*Bias of one pass.* Particle images cut by the window border move less than the
particles, so without the overlap correction one correlation underestimates a
displacement by a fraction that grows with the particle size over the window size:
about 20 % for images of standard deviation 1 voxel in 16-voxel windows, about 50 %
along z for images of 2.5 voxels in 24-voxel windows, and 52 % along z for the
resolution-cell particles of the 50 mm plenoptic geometry (sigma 1.9 voxels) in 12-voxel
windows (measured on synthetic volumes; with the overlap correction the last measures
1 voxel as 1.01 in one pass). Window deformation removes the remaining bias: each pass
measures only what the predictor left, and the corrector tends to zero as the passes
converge, each pass reducing the remaining error by about that fraction. Particles much
longer than the window along an axis therefore need more passes. The discrete window
offset (``deformation=False``) keeps the bias on the sub-voxel remainder.

*Multi-pass window deformation* (WIDIM, Scarano 2002). After each pass the field is
validated (:func:`normalized_median_test`), outliers are replaced
(:func:`replace_outliers`), and the result, the predictor ``d_p``, is interpolated
trilinearly to every voxel. Both volumes are then deformed symmetrically (central
difference),

.. math:: A'(x) = A(x - d_p(x)/2), \qquad B'(x) = B(x + d_p(x)/2),

with interpolation of order ``settings.deformation_order``, and the correlation of the
deformed volumes gives the corrector ``d_c``; the new estimate is ``d_p + d_c`` at the
window centres of the (possibly smaller) windows of the next pass. The predictor is
extrapolated linearly beyond the outermost window centres and, with
``settings.smooth_predictor``, low-passed by a [1, 2, 1]/4 filter per axis, which keeps
repeated passes from amplifying errors whose wavelength is close to the window size
(Schrijer & Scarano 2008). With ``deformation=False`` each window pair is instead shifted
by ``-/+ d_p/2`` rounded to whole voxels (discrete window offset).

The last pass is validated too; ``valid`` marks the rejected vectors and
``settings.replacement`` says whether they are filled by the local median or mean or
left NaN. The returned field is not smoothed.

*Uncertainty* (correlation statistics, Wieneke 2015, per axis in 3-D). After the last
pass the two (deformed) windows ``a, b`` (means removed) nearly coincide. Along axis
``e`` the correlation values beside the integer peak ``s_0`` are sums of per-voxel
products, :math:`C^\pm = \sum_x c^\pm(x)` with :math:`c^+(x) = a(x)\, b(x + s_0 + e)`
and :math:`c^-(x) = a(x + e)\, b(x + s_0)` (circular within the window, as the
correlation), so that :math:`\Delta c = c^+ - c^-` vanishes voxel by voxel where the two
windows are equal. The asymmetry :math:`\Delta C = C^+ - C^-` moves the sub-voxel peak;
its standard deviation is estimated from the spread of :math:`\Delta c` about its mean,
with the covariance of neighbouring voxels (a particle image spans several voxels)
counted by summing :math:`\Delta c` over circular blocks of ``2h + 1`` voxels per axis
(Bartlett's estimator):

.. math:: \sigma_{\Delta C}^2 = \frac{1}{|B|} \sum_x
          \Big( \sum_{y \in B(x)} (\Delta c(y) - \overline{\Delta c}) \Big)^2

with ``h`` per axis the particle image's correlation width, ``ceil(sqrt(2) s_p)`` for
particle images of standard deviation ``s_p`` (from the volume's autocorrelation at a
lag of one voxel, :func:`particle_image_size`). The standard uncertainty is the shift of
the 3-point fit when the neighbours differ by :math:`\pm\sigma_{\Delta C}/2` about
their mean :math:`\bar C = (C^+ + C^-)/2`:

.. math:: \sigma = \left| \delta\big(C_0,\ \bar C + \sigma_{\Delta C}/2,\
          \bar C - \sigma_{\Delta C}/2\big) \right|

with :math:`\delta` the Gaussian (or parabolic) estimator above. The statistics see
only what makes the two deformed windows differ; the error the iteration left behind is
not in them. After two or more passes the change the last pass made to the estimate,
:math:`\Delta d` (its corrector), estimates it: the passes converge geometrically, each
removing a fraction of the remaining error, so what remains after the last pass is of
the order of the last correction (window-border truncation of elongated particle images,
flow structures smaller than the smoothed predictor resolves). The standard uncertainty
per axis is

.. math:: \sigma^2 = \sigma_{CS}^2 + \Delta d^2.

On noisy synthetic particle volumes 85-98 % of the true errors lie within
:math:`\pm 2\sigma` (the statistics alone: 50-85 %). A replaced vector gets the root sum
of squares of its neighbours' median uncertainty and the spread of the neighbours
(1.4826 times their median absolute residual). For plenoptic volumes
:mod:`plenopiv.piv.uncertainty` adds the chain's measured response; see
``docs/validation/uncertainty.md`` for the coverage of true errors on the vortex flows.


References
----------
F. Scarano, "Iterative image deformation methods in PIV", Measurement Science and
Technology 13, R1-R19 (2002). doi:10.1088/0957-0233/13/1/201

J. Westerweel and F. Scarano, "Universal outlier detection for PIV data", Experiments in
Fluids 39, 1096-1100 (2005). doi:10.1007/s00348-005-0016-6

C. E. Willert and M. Gharib, "Digital particle image velocimetry", Experiments in Fluids
10, 181-193 (1991). doi:10.1007/BF00190388

J. Westerweel, "Fundamentals of digital particle image velocimetry", Measurement
Science and Technology 8, 1379-1392 (1997). doi:10.1088/0957-0233/8/12/002

F. F. J. Schrijer and F. Scarano, "Effect of predictor-corrector filtering on the
stability and spatial resolution of iterative PIV interrogation", Experiments in Fluids
45, 927-941 (2008).

B. Wieneke, "PIV uncertainty quantification from correlation statistics", Measurement
Science and Technology 26, 074002 (2015). doi:10.1088/0957-0233/26/7/074002

"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from plenopiv.conventions import voxel_to_world
from plenopiv.piv.correlation import _correlate_pass, _peak_refinement
from plenopiv.piv.field import FLAG_EMPTY, FLAG_MASKED, FLAG_OUTLIER, VectorField
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

    Returns
    -------
    VectorField
        Displacements (metres) on the window-centre grid of the last pass, with each
        vector's quality (peak height, peak ratio, flag, replaced) and standard uncertainty.

    Raises
    ------
    PIVError
        If the volumes differ in shape, are not 3-D, hold non-finite values, do not fit the
        windows, or the grid is unusable.
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
    with _numba_threads(workers):
        return _multipass(
            vol_a, vol_b, origin, voxel, settings, workers, kernels, progress, mask=mask
        )


class _Pass(NamedTuple):
    """What one correlation pass measured, in voxels ``(z, y, x)``, flat over its windows.

    ``last`` is what its correlation saw: the two volumes (deformed or not), the window
    shifts of a discrete offset (or None) and the displacement it found between its windows;
    ``change`` is what the pass changed in the estimate (None for the first pass).
    """

    estimate: np.ndarray
    peak: np.ndarray
    snr: np.ndarray
    last: tuple
    change: np.ndarray | None


def _first_pass(vol_a, vol_b, layout, correlate):
    """Correlate the undeformed volumes on the windows of ``layout``."""
    estimate, peak, snr = correlate(vol_a, vol_b, layout, shift=None)
    return _Pass(estimate, peak, snr, (vol_a, vol_b, None, estimate), None)


def _deformed_pass(vol_a, vol_b, layout, predictor, previous, deform, correlate):
    """Deform both volumes by ``-/+ predictor / 2`` and add the corrector they give."""
    voxel_axes = tuple(np.arange(n, dtype=float) for n in vol_a.shape)
    # float32 throughout: ten times faster than float64 for a full-size field
    dense = _interpolate_field(predictor.astype(np.float32), previous.centres, voxel_axes)
    a_def = deform(vol_a, dense, -0.5, "a")
    b_def = deform(vol_b, dense, +0.5, "b")
    del dense
    corrector, peak, snr = correlate(a_def, b_def, layout, shift=None)
    at_centres = _interpolate_field(predictor, previous.centres, layout.centres)
    estimate = at_centres.reshape(3, -1).T + corrector
    return _Pass(estimate, peak, snr, (a_def, b_def, None, corrector), corrector)


def _offset_pass(vol_a, vol_b, layout, predictor, previous, correlate):
    """Shift each window pair by the predictor rounded to whole voxels (discrete offset)."""
    at_centres = _interpolate_field(predictor, previous.centres, layout.centres)
    shift = np.rint(at_centres.reshape(3, -1).T).astype(np.int64)
    corrector, peak, snr = correlate(vol_a, vol_b, layout, shift=shift)
    estimate = shift + corrector
    change = estimate - at_centres.reshape(3, -1).T
    return _Pass(estimate, peak, snr, (vol_a, vol_b, shift, corrector), change)


def _deformer(vol_a, vol_b, settings, kernels):
    """``deform(volume, field_vox, factor, which)`` for the passes, B-spline prefilter done once."""
    order = settings.deformation_order
    coeffs = {"a": None, "b": None}
    if settings.deformation and order > 1 and settings.passes > 1:
        coeffs = {"a": _spline_coefficients(vol_a, order), "b": _spline_coefficients(vol_b, order)}

    def deform(volume, field_vox, factor, which):
        return _deform(volume, field_vox, factor, order, kernels, coeffs[which])

    return deform


def _multipass(vol_a, vol_b, origin, voxel, settings, workers, kernels, progress, mask=None):
    """Run the WIDIM loop of :func:`correlate_volumes` on checked inputs."""
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
                           settings, kernels)
    sigma_vox, parts = _uncertainty(result, layout, final, in_mask, voxel, settings, kernels,
                                    earlier_change)
    return _vector_field(layout, origin, voxel, result, final, sigma_vox, parts, settings)


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


def _final_vectors(field_vox, validated, outlier, in_mask, empty, settings, kernels):
    """Flag the last pass's rejected vectors and replace them as ``settings.replacement`` says."""
    rejected = outlier | in_mask
    flag = (
        np.where(outlier & ~empty & ~in_mask, FLAG_OUTLIER, 0)
        | np.where(empty, FLAG_EMPTY, 0)
        | np.where(in_mask, FLAG_MASKED, 0)
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


def _vector_field(layout, origin, voxel, last_pass, final, sigma_vox, parts, settings):
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
    )
