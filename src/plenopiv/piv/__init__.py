"""Multi-pass 3-D cross-correlation of two reconstructed particle volumes (volumetric PIV).

:func:`correlate_volumes` turns two volumes of one grid, recorded ``dt`` apart, into a
:class:`VectorField` by WIDIM window deformation with a normalised median test between passes;
:class:`PIVSettings` holds the validated settings. Volumes are indexed ``[z, y, x]``; the
field holds window-centre coordinates and ``u, v, w`` (along x, y, z) in metres, and a
displacement ``d`` means the pattern of ``volume_a`` at ``p`` is found in ``volume_b`` at
``p + d`` (:mod:`plenopiv.conventions`). Modules in data order: ``settings``, ``inputs``,
``windows``, ``correlation``, ``outliers``, ``evidence``, ``statistics``, ``multipass``,
``field``, ``response``, ``uncertainty``; ``_kernels`` holds the numba kernels and their
NumPy twins.
Functions that need numba and scipy are imported on first use. See docs/methods.md#piv.
"""

import importlib

from plenopiv.piv.field import (
    FLAG_EMPTY,
    FLAG_FEW_PARTICLES,
    FLAG_MASKED,
    FLAG_OUTLIER,
    VectorField,
)
from plenopiv.piv.settings import (
    DEFORMATION_ORDERS,
    MIN_WINDOW_VOX,
    REPLACEMENT_METHODS,
    SUBPIXEL_METHODS,
    PIVSettings,
)

__all__ = [
    "DEFORMATION_ORDERS",
    "FLAG_EMPTY",
    "FLAG_FEW_PARTICLES",
    "FLAG_MASKED",
    "FLAG_OUTLIER",
    "MIN_WINDOW_VOX",
    "REPLACEMENT_METHODS",
    "SUBPIXEL_METHODS",
    "PIVSettings",
    "VectorField",
    "correlate_volumes",
    "normalized_median_test",
    "particle_image_size",
    "replace_outliers",
]

_LAZY = {
    "correlate_volumes": "multipass",
    "normalized_median_test": "outliers",
    "particle_image_size": "statistics",
    "replace_outliers": "outliers",
}
"""Public functions imported on first use: name -> module of :mod:`plenopiv.piv`."""


def __getattr__(name):
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
