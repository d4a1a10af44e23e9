"""Exceptions and warnings that plenopiv raises on purpose.

Every message names the offending thing (config key, file, lenslet rows ...), the value found
and what was expected, so that a user can act on it without reading a traceback.

Each class carries the exit status the ``plenopiv`` command ends with (``exit_status``):
2 for input that is refused (a bad argument, config, image or calibration), 1 for a
computation or a write that failed (a full disk, a batch with failed pairs).
"""

#: Exit status of the ``plenopiv`` command: success.
EXIT_OK = 0
#: A computation, a write or a pair of a batch failed.
EXIT_FAILED = 1
#: Bad input, refused before any work (argument, config, image, calibration, output path).
EXIT_BAD_INPUT = 2
#: Stopped by Ctrl-C (SIGINT); a batch leaves its summary and a resumable state.
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143
"""Exit status after SIGTERM (128 + 15, what SLURM sends on a cancel or at the wall time)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the process is, so that it ends the way Ctrl-C ends it."""



class PlenopivError(Exception):
    """Base class of every error plenopiv raises on purpose."""

    exit_status = EXIT_BAD_INPUT


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


class ComparisonError(PlenopivError):
    """The inputs of a comparison do not fit: not the products expected, or different grids."""


class ProvenanceError(PlenopivError):
    """Products that do not belong together: made from other inputs, or by a newer plenopiv.

    The message names both files (or the file and the input) and what differs.
    """


class ResourceError(PlenopivError):
    """A size beyond what this machine can do (memory, voxel count), refused before work."""


class OutputError(PlenopivError):
    """An output path is unusable (refused before any work).

    A directory, not writable, or one of the command's inputs.
    """


class WriteError(OutputError):
    """A write failed part way (a full disk, a lost mount).

    Nothing is left under the final name and no product is marked complete.
    """

    exit_status = EXIT_FAILED


class ComputationError(PlenopivError):
    """A computation ran and failed (e.g. pairs of a batch failed)."""

    exit_status = EXIT_FAILED


class PlenopivWarning(UserWarning):
    """A doubtful input that is used anyway (a saturated image, a clipped background ...)."""
