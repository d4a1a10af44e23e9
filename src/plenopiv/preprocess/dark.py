"""Dark frames: the master dark of a frame or a stack, and its subtraction.

A dark frame is recorded with the lens capped at the images' exposure time: it holds the
sensor's black level (with its fixed pattern), the dark current of hot pixels and the
amplifier glow, which every image holds too. The master dark is the stack's mean; its
per-pixel noise comes from the stack's spread: the variance of one frame (the noise an image
carries) and that of the mean (what the subtraction adds), both in counts².
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plenopiv.errors import ImageError

__all__ = ["MasterDark", "master_dark", "subtract_dark"]


@dataclass(frozen=True)
class MasterDark:
    """A master dark.

    Attributes
    ----------
    mean : (rows, cols) float64
        The mean of the frames, counts.
    frame_variance : (rows, cols) float64 or None
        The per-pixel variance of one frame, counts² (the frames' spread, ddof = 1); None
        from a single frame, whose noise cannot be told from its pattern.
    n_frames : int
        Frames averaged.
    """

    mean: np.ndarray
    frame_variance: np.ndarray | None
    n_frames: int

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols)."""
        return tuple(self.mean.shape)

    @property
    def variance(self) -> np.ndarray | None:
        """Variance of the master dark itself, counts² (frame variance / n_frames), or None."""
        if self.frame_variance is None:
            return None
        return self.frame_variance / self.n_frames

    @property
    def level(self) -> float:
        """The black level: the median of the master dark, counts."""
        return float(np.median(self.mean))

    @property
    def noise(self) -> float | None:
        """The typical noise of one frame, counts (None from a single frame).

        The square root of the median frame variance.
        """
        if self.frame_variance is None:
            return None
        return float(np.sqrt(np.median(self.frame_variance)))


def master_dark(frames, *, name: str = "dark") -> MasterDark:
    """The master dark of one frame (rows, cols) or a stack (n, rows, cols), in counts.

    The mean and the per-pixel variance are accumulated frame by frame in float64 (a stack of
    integer frames is never copied whole into floats).

    Raises
    ------
    ImageError
        Not 2-D or 3-D, empty, or holding NaN, infinity or complex values; ``name`` names the
        frames in the message.
    """
    a = np.asarray(frames)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or a.shape[0] == 0 or 0 in a.shape[1:]:
        raise ImageError(f"{name} has shape {np.shape(frames)}: expected one frame "
                         "(rows, cols) or a stack (frames, rows, cols)")
    if np.iscomplexobj(a) or not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
        raise ImageError(f"{name} has dtype {a.dtype}: expected real counts")
    n = a.shape[0]
    total = np.zeros(a.shape[1:])
    for f in a:
        total += f
    mean = total / n
    if not np.isfinite(mean).all():
        raise ImageError(f"{name} holds NaN or infinite values: expected finite counts")
    var = None
    if n > 1:
        acc = np.zeros(a.shape[1:])
        for f in a:
            acc += (f - mean) ** 2
        var = acc / (n - 1)
    return MasterDark(mean, var, n)


def subtract_dark(image, dark: MasterDark, *, name: str = "image") -> np.ndarray:
    """``image - dark.mean`` in float64 counts (negative noise kept; clip it where needed).

    Raises
    ------
    ImageError
        When the image and the dark differ in shape.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.shape != dark.shape:
        raise ImageError(f"{name} is {img.shape[0]} × {img.shape[1]} pixels but the dark is "
                         f"{dark.shape[0]} × {dark.shape[1]}: expected frames of one sensor")
    return img - dark.mean
