"""Multi-pass 3-D cross-correlation of two reconstructed particle volumes (volumetric PIV).

The stage turns two volumes of the same grid, recorded a time ``dt`` apart, into a field of
displacement vectors: one per interrogation window. It implements the iterative multigrid
window-deformation scheme WIDIM (Scarano 2002) with a normalised median test between passes
(Westerweel & Scarano 2005).

Conventions (see :mod:`plenopiv.conventions`): volumes are indexed ``[z, y, x]``; the grid's
``origin`` is the ``(x, y, z)`` position of voxel ``[0, 0, 0]`` and its ``voxel_size`` the edge
``(dx, dy, dz)``, both in metres. The returned :class:`VectorField` holds window-centre
coordinates ``x, y, z`` (1-D, metres) and the displacement components ``u`` (along x), ``v``
(along y), ``w`` (along z) as arrays of shape ``(nz, ny, nx)`` in metres. Inside the package
index-space quantities carry the suffix ``_vox`` and are ordered ``(z, y, x)``.

A displacement ``d`` means that the pattern of ``volume_a`` at position ``p`` is found in
``volume_b`` at ``p + d``.

Modules, in the order the data moves:

- :mod:`.settings`: :class:`PIVSettings`, the validated settings and their defaults;
- :mod:`.inputs`: checks of the volumes, grid, mask and options;
- :mod:`.windows`: window layout of a pass, field interpolation and volume deformation;
- :mod:`.correlation`: one correlation pass (staged FFTs, cross spectrum, peak fit);
- :mod:`.validation`: normalised median test and replacement of rejected vectors;
- :mod:`.statistics`: per-vector uncertainty by correlation statistics;
- :mod:`.multipass`: :func:`correlate_volumes`, the WIDIM driver;
- :mod:`.field`: :class:`VectorField`, the result;
- :mod:`.uncertainty`: the chain's measured response that completes the uncertainty;
- :mod:`._kernels`: the numba kernels, each with its NumPy twin.

The settings and the result are imported with the package; the functions that need numba and
scipy are imported on first use, so that the experiment configuration
(:mod:`plenopiv.config.experiment`) can take its ``[piv]`` defaults from :class:`PIVSettings`
without loading them.
"""

import importlib

from plenopiv.piv.field import FLAG_EMPTY, FLAG_MASKED, FLAG_OUTLIER, VectorField
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
