"""plenopiv: tomographic plenoptic particle image velocimetry.

The package follows the data flow of one plenoptic 1.0 camera::

    camera -> calibration -> lightfield -> weights -> mart -> particles -> corrections -> piv

Conventions (stated once, see :mod:`plenopiv.conventions`): SI units (metres, seconds,
radians) everywhere inside; volumes are indexed ``[z, y, x]``; pixels are ``(row, col)`` with
the centre of the top-left pixel at (0, 0); world points are ``(N, 3)`` arrays of ``(x, y, z)``;
the volume depth Z grows away from the camera.
"""

import os
import sys
from importlib.metadata import PackageNotFoundError, version

from plenopiv.errors import (
    CalibrationError,
    ConfigError,
    ImageError,
    PIVError,
    PlenopivError,
    ReconstructionError,
)


def cache_dir() -> str:
    """Return plenopiv's cache folder.

    ``$PLENOPIV_CACHE_DIR``, else ``plenopiv`` in the user's cache folder (``$XDG_CACHE_HOME``
    or ``~/.cache``; ``%LOCALAPPDATA%`` on Windows).
    """
    if os.environ.get("PLENOPIV_CACHE_DIR"):
        return os.environ["PLENOPIV_CACHE_DIR"]
    if sys.platform == "win32" and os.environ.get("LOCALAPPDATA"):
        base = os.environ["LOCALAPPDATA"]
    else:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"),
                                                                 ".cache")
    return os.path.join(base, "plenopiv")


def _use_numba_cache_dir() -> None:
    """Compiled numba kernels go to ``cache_dir()/numba`` unless ``NUMBA_CACHE_DIR`` is set.

    numba's own default writes ``__pycache__`` beside the sources, which a site-packages
    install may not allow; a folder the user owns keeps the kernels compiled once per machine
    (and shared by the batch's worker processes, which inherit the variable).
    """
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    path = os.path.join(cache_dir(), "numba")
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return                       # numba then falls back to its own locations
    if not os.access(path, os.W_OK):
        return
    os.environ["NUMBA_CACHE_DIR"] = path
    if "numba" in sys.modules:       # imported before plenopiv: its config is already read
        sys.modules["numba"].config.CACHE_DIR = path


_use_numba_cache_dir()

try:
    __version__ = version("plenopiv")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = [
    "__version__",
    "cache_dir",
    "PlenopivError",
    "ConfigError",
    "ImageError",
    "CalibrationError",
    "ReconstructionError",
    "PIVError",
]
