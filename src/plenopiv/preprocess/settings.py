"""The preprocessing's settings: the ``[preprocess]`` table of an experiment file."""

from __future__ import annotations

from typing import Literal

from pydantic import field_validator

from plenopiv.settings import settings

__all__ = ["BACKGROUND_KINDS", "PreprocessSettings"]

#: The words ``background`` accepts besides the path of a background image.
BACKGROUND_KINDS = ("none", "minimum", "mean")


@settings
class PreprocessSettings:
    """``[preprocess]``: what is done to a recorded image before the reconstruction.

    dark : a dark frame or stack (TIFF, multi-page TIFF, PNG, ``file.h5:/path`` 2-D or 3-D),
        relative to the experiment file; its mean is subtracted from every image (and from
        the white and the background image), its hot and cold pixels are repaired.
    white : a white frame or stack taken at the recording's aperture: the flat field. Each
        micro-image's throughput (its lenslet's transmission and the vignetting) is divided
        out; pixels outside the micro-images, dead pixels and the rim below
        :data:`~plenopiv.preprocess.flat.RIM_FRACTION` of the white's local peak are masked.
    hot_pixels : "auto" (default): hot and dead pixels found from the dark and white frames
        and from the images (bright in every image of a batch, or far above their
        same-micro-image neighbours with no light spot to explain it) are repaired from
        neighbours in the same micro-image | "none": no repair.
    background : "none" (default) | "minimum" | "mean" (per-pixel minimum or mean of the
        batch's images, ``plenopiv run`` only) | the path of a background image (a recording
        without particles, taken like the images; a stack is averaged).
    """

    dark: str | None = None
    white: str | None = None
    hot_pixels: Literal["auto", "none"] = "auto"
    background: str = "none"

    @field_validator("dark", "white")
    @classmethod
    def _path(cls, v):
        if v is not None and not v.strip():
            raise ValueError("expected the path of an image file, got an empty string")
        return v

    @field_validator("background")
    @classmethod
    def _background(cls, v):
        if not v.strip():
            raise ValueError('expected "none", "minimum", "mean" or the path of a background '
                             "image, got an empty string")
        return v

    @property
    def background_kind(self) -> str:
        """``"none"``, ``"minimum"``, ``"mean"`` (formed over a batch) or ``"image"`` (a file)."""
        return self.background if self.background in BACKGROUND_KINDS else "image"

    @property
    def background_path(self) -> str | None:
        """The background image's path, or None for the other kinds."""
        return self.background if self.background_kind == "image" else None
