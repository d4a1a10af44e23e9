"""3-D PIV of two reconstructed volumes into the vectors product (physical coordinates).

The correlation (:func:`plenopiv.piv.correlate_volumes`), the per-vector uncertainty completed
by the chain's response where given, and the depth corrections of the volumes applied to the
field. See docs/methods.md#piv.
"""

from __future__ import annotations

from plenopiv.errors import PIVError, ReconstructionError
from plenopiv.products.images import warn_identical
from plenopiv.products.vectors import VectorResult, check_dt
from plenopiv.products.volume import VolumeResult

__all__ = ["correlate"]


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
    from plenopiv.piv.uncertainty import combine
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
                              particles=(result_a.volume_position_effective,
                                         result_b.volume_position_effective))
    method = "correlation"
    measured = None if response is None else response(field)
    if measured is not None:
        field = combine(field, measured)
        method = "response"
    return VectorResult.from_field(field, result_a.correction, dt, uncertainty_method=method,
                                   grid=result_a.grid)
