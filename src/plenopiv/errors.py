"""Exceptions that plenopiv raises for bad input.

Every message names the offending thing (config key, file, lenslet rows ...), the value found
and what was expected, so that a user can act on it without reading a traceback.
"""


class PlenopivError(Exception):
    """Base class of every error plenopiv raises on purpose."""


class ConfigError(PlenopivError, ValueError):
    """A camera or experiment configuration is invalid (key, unit, value or section)."""


class ImageError(PlenopivError, ValueError):
    """An image cannot be used: wrong size, unreadable, NaN, empty or saturated."""


class CalibrationError(PlenopivError):
    """Calibration failed or its inputs do not fit together (missing spots, wrong camera)."""


class ReconstructionError(PlenopivError):
    """Volume reconstruction inputs are inconsistent (grid outside the field of view ...)."""


class PIVError(PlenopivError):
    """Cross-correlation inputs are inconsistent (volumes of different grids ...)."""
