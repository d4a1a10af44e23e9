"""The light field: pixels as rays, perspective views and refocusing.

- :mod:`~plenopiv.lightfield.rays`: every lit pixel of a calibrated camera as a ray
  (:class:`LightField`, :func:`light_field`);
- :mod:`~plenopiv.lightfield.views`: perspective (sub-aperture) views (:func:`perspective_view`);
- :mod:`~plenopiv.lightfield.refocusing`: refocused images on a synthetic lenslet plane
  (:func:`refocus`);
- :mod:`~plenopiv.lightfield._kernels`: the numba kernel of the lit fraction and its NumPy twin.

The public names are importable from :mod:`plenopiv.lightfield` itself.
"""

from plenopiv.lightfield.rays import (
    MIN_RAYS_PER_LENSLET,
    LightField,
    LightFieldWarning,
    light_field,
)
from plenopiv.lightfield.refocusing import REFOCUS_METHODS, refocus
from plenopiv.lightfield.views import PERSPECTIVE_INTERPOLATIONS, perspective_view

__all__ = [
    "MIN_RAYS_PER_LENSLET",
    "PERSPECTIVE_INTERPOLATIONS",
    "REFOCUS_METHODS",
    "LightField",
    "LightFieldWarning",
    "light_field",
    "perspective_view",
    "refocus",
]
