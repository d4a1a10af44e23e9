"""3-D PIV of two reconstructed volumes into the vectors product (physical coordinates).

The correlation (:func:`plenopiv.piv.correlate_volumes`), the per-vector uncertainty completed
by the chain's response where given, and the depth corrections of the volumes applied to the
field; then its depth component fitted to continuity (:func:`fitted_to_continuity`, ``[piv]
continuity``). See docs/methods.md#piv.
"""

from __future__ import annotations

from plenopiv.errors import PIVError, ReconstructionError
from plenopiv.products.images import warn_identical
from plenopiv.products.vectors import VectorResult, check_dt
from plenopiv.products.volume import VolumeResult

__all__ = ["correlate", "fitted_to_continuity"]


def correlate(result_a: VolumeResult, result_b: VolumeResult, settings=None, *, dt=None,
              workers=None, progress=None, mask=None, response=None,
              names=("volume A", "volume B")) -> VectorResult:
    """3-D PIV between two reconstructed volumes of the same grid, in physical coordinates.

    The volumes are on the effective (air-equivalent) grid; identical volumes are warned about
    (:func:`~plenopiv.products.images.warn_identical`, ``names``: how the warning names
    them; None: not checked, where the images they came from were).

    ``mask``: volume mask (bool ``[z, y, x]``, True outside the flow). ``response``: a
    callable ``response(field) -> Response`` (:func:`plenopiv.workflow.response.measure_response`)
    whose result completes the uncertainties (:func:`plenopiv.piv.uncertainty.combine`); None
    keeps the correlation statistics alone.
    """
    from plenopiv.piv import PIVSettings, correlate_volumes
    from plenopiv.piv.uncertainty import MIN_GAIN, combine
    from plenopiv.workflow.preprocess import IDENTICAL_PAIR

    for name, r in (("result_a", result_a), ("result_b", result_b)):
        if not isinstance(r, VolumeResult):
            raise PIVError(f"correlate: {name} is a {type(r).__name__}: expected a "
                           "VolumeResult (reconstruct_volume or load_volume)")
    if settings is not None and not isinstance(settings, PIVSettings):
        raise PIVError(f"correlate: settings is a {type(settings).__name__}: expected a "
                       "PIVSettings (or None for the defaults)")
    dt = check_dt(dt)
    if result_a.grid != result_b.grid:
        def text(g):
            return (f"{list(g.shape)} voxels of {[round(v * 1e3, 6) for v in g.voxel]} mm from "
                    f"{[round(v * 1e3, 6) for v in g.origin]} mm")
        raise ReconstructionError("the two volumes were reconstructed on different grids "
                                  f"(A: {text(result_a.grid)}; B: {text(result_b.grid)}): "
                                  "expected the same [volume] for both exposures")
    if names is not None:
        warn_identical(names, (result_a.volume, result_b.volume), consequence=IDENTICAL_PAIR)
    field = correlate_volumes(result_a.volume, result_b.volume, result_a.grid,
                              settings=settings, workers=workers, progress=progress, mask=mask,
                              # the windows' particles are the volumes' peaks, as the
                              # correlation sees them (a split peak counts once)
                              particles=(result_a.volume_peaks()[0],
                                         result_b.volume_peaks()[0]))
    method, gain_error = "correlation", None
    measured = None if response is None else response(field)
    if measured is not None:
        field = combine(field, measured)
        method, gain_error = "response", measured.gain_error(field.z, MIN_GAIN)[2]
    return VectorResult.from_field(field, result_a.correction, dt, uncertainty_method=method,
                                   grid=result_a.grid, w_gain_error=gain_error)


def fitted_to_continuity(vectors: VectorResult, settings=None) -> tuple[VectorResult, dict]:
    """The field with w fitted to the continuity of an incompressible flow, and the record.

    :func:`plenopiv.piv.continuity.depth_from_continuity` on the finished field (physical
    coordinates, depth corrections applied); w and its uncertainty become the fit's, u, v,
    their uncertainties and the flags are kept. Not applied where
    ``settings.continuity`` is off, where the field has fewer than two vectors along an axis
    or no uncertainties, or where the fit's misfit says the flow is not incompressible at the
    vectors' resolution (a warning names the figure and the key). Returns ``(vectors,
    record)``, the record the vectors product's ``continuity`` attribute.
    """
    import warnings
    from dataclasses import replace

    import numpy as np

    from plenopiv.errors import PlenopivWarning
    from plenopiv.piv import PIVSettings
    from plenopiv.piv.continuity import (
        CONSISTENCY_CHI2,
        column_gain_sigma,
        depth_from_continuity,
    )

    settings = PIVSettings() if settings is None else settings
    if not settings.continuity:
        return vectors, {"applied": False, "reason": "[piv] continuity = false"}
    if len(vectors.z) < 2:
        return vectors, {"applied": False, "reason": "one layer of vectors in depth"}
    if min(len(vectors.x), len(vectors.y)) < 2:
        return vectors, {"applied": False, "reason": "one vector along x or y: the lateral "
                                                     "divergence is not measured"}
    sigma = (vectors.u_uncertainty, vectors.v_uncertainty, vectors.w_uncertainty)
    if any(s is None or not np.isfinite(s).any() for s in sigma):
        return vectors, {"applied": False, "reason": "the vectors carry no uncertainty"}
    if vectors.w_gain_error is not None:
        sigma = (*sigma[:2], column_gain_sigma(vectors.w_uncertainty, vectors.w,
                                               vectors.w_gain_error))
    fit = depth_from_continuity(vectors.u, vectors.v, vectors.w, *sigma,
                                vectors.x, vectors.y, vectors.z)
    record = {"chi2_per_vector": round(fit.chi2_per_vector, 4), "vectors": fit.vectors,
              "max_chi2_per_vector": CONSISTENCY_CHI2}
    if not fit.consistent:
        warnings.warn(
            f"the vectors' depth component disagrees with the continuity of an incompressible "
            f"flow by a misfit of {fit.chi2_per_vector:.1f} per vector (at most "
            f"{CONSISTENCY_CHI2:g}): w is kept as measured. Set [piv] continuity = false "
            "for a flow that is not incompressible; otherwise check the calibration's depth "
            "and the windows against the flow's scale", PlenopivWarning, stacklevel=2)
        return vectors, {"applied": False, "reason": "misfit above the limit", **record}
    change = fit.w - vectors.w
    rms = float(np.sqrt(np.nanmean(change ** 2))) if np.isfinite(change).any() else 0.0
    sigma = np.where(np.isfinite(fit.sigma_w), fit.sigma_w, vectors.w_uncertainty)
    return replace(vectors, w=fit.w, w_uncertainty=sigma), \
        {"applied": True, **record, "rms_change_w_m": rms}
