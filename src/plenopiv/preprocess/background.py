"""Background removal: the per-pixel minimum or mean of a batch, or a given background image.

What is still lit where no particle is — a reflection of the laser sheet on a window, stray
light, a glow — is the same in every image of a steady set-up, while the particles move. The
per-pixel minimum over a batch keeps what is always there (particles leave it, except where a
pixel is lit in every image), the mean keeps it with the particles' average light on top
(smoother; for dense seeding the minimum is the safer choice). Either is subtracted from
every image; negative noise left by it is clipped at 0 later (:mod:`plenopiv.preprocess.stage`).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from plenopiv.errors import ImageError

__all__ = ["BATCH_KINDS", "batch_background", "subtract_background"]

#: The backgrounds formed over the images of a batch.
BATCH_KINDS = ("minimum", "mean")


def batch_background(images: Iterable, kind: str) -> tuple[np.ndarray, int]:
    """The per-pixel ``"minimum"`` or ``"mean"`` of a batch's images, counts (float64).

    ``images``: 2-D arrays of one shape (an iterable, read one at a time, or a 3-D array).
    Returns ``(background, number of images)``.

    Raises
    ------
    ImageError
        No image, images of different shapes, non-finite values.
    ValueError
        An unknown ``kind``.
    """
    if kind not in BATCH_KINDS:
        raise ValueError(f"kind = {kind!r}: expected one of {BATCH_KINDS}")
    acc = None
    n = 0
    for img in images:
        a = np.asarray(img, dtype=np.float64)
        if a.ndim != 2:
            raise ImageError(f"batch image {n} has shape {a.shape}: expected a 2-D image")
        if acc is None:
            acc = a.copy()
        elif a.shape != acc.shape:
            raise ImageError(f"batch image {n} is {a.shape[0]} × {a.shape[1]} pixels, the "
                             f"first {acc.shape[0]} × {acc.shape[1]}: expected images of one "
                             "sensor")
        elif kind == "minimum":
            np.minimum(acc, a, out=acc)
        else:
            acc += a
        n += 1
    if acc is None:
        raise ImageError("the batch holds no image to form a background from")
    if kind == "mean":
        acc /= n
    if not np.isfinite(acc).all():
        raise ImageError("the batch's images hold NaN or infinite values")
    return acc, n


def subtract_background(image, background, *, name: str = "image") -> np.ndarray:
    """``image - background`` in float64 counts (negative noise kept)."""
    img = np.asarray(image, dtype=np.float64)
    bg = np.asarray(background, dtype=np.float64)
    if img.shape != bg.shape:
        raise ImageError(f"{name} has shape {img.shape} but the background {bg.shape}: "
                         "expected frames of one sensor")
    return img - bg
