"""plenopiv: tomographic plenoptic particle image velocimetry.

The package follows the data flow of one plenoptic 1.0 camera::

    camera -> calibration -> lightfield -> weights -> mart -> particles -> corrections -> piv

Conventions (stated once, see :mod:`plenopiv.conventions`): SI units (metres, seconds,
radians) everywhere inside; volumes are indexed ``[z, y, x]``; pixels are ``(row, col)`` with
the centre of the top-left pixel at (0, 0); world points are ``(N, 3)`` arrays of ``(x, y, z)``;
the volume depth Z grows away from the camera.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("plenopiv")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

from plenopiv.errors import (  # noqa: E402
    CalibrationError,
    ConfigError,
    ImageError,
    PIVError,
    PlenopivError,
    ReconstructionError,
)

__all__ = [
    "__version__",
    "PlenopivError",
    "ConfigError",
    "ImageError",
    "CalibrationError",
    "ReconstructionError",
    "PIVError",
]
