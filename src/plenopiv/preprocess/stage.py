"""The preprocessing of one image or one pair, from the frames known beforehand.

::

    raw counts ──dark──> light + noise ──background──> particle light ──hot/dead pixels──>
        repaired (within micro-images) ──flat──> throughput divided out, mask ──clip at 0──>
        (a pair) ──normalise──> both exposures on A's scale

:func:`prepare_frames` makes what every image shares (the master dark, the flat field, the
light-space background, the pixels bad in every image); :func:`prepare_image` and
:func:`prepare_pair` apply it. Arrays in, arrays out: the files are read by the workflow
(:mod:`plenopiv.workflow.preprocess`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from plenopiv.errors import ImageError
from plenopiv.preprocess.background import subtract_background
from plenopiv.preprocess.dark import MasterDark, subtract_dark
from plenopiv.preprocess.flat import FlatField, apply_flat, flat_field
from plenopiv.preprocess.intensity import normalise_pair
from plenopiv.preprocess.microimages import MicroImages
from plenopiv.preprocess.pixels import (
    dark_defects,
    isolated_pixels,
    repair_pixels,
    robust_sigma,
)

__all__ = ["Frames", "Prepared", "prepare_frames", "prepare_image", "prepare_pair"]

HOT_PIXEL_MODES = ("auto", "none")


@dataclass(frozen=True)
class Frames:
    """What every image of an experiment shares.

    Attributes
    ----------
    micro : MicroImages
        The calibration's micro-images (the cells repairs stay inside).
    hot_pixels : str
        ``"auto"`` (find and repair) or ``"none"``.
    dark : MasterDark or None
    flat : FlatField or None
    background : (rows, cols) float64 or None
        The background in light counts (its dark taken off).
    bad : (rows, cols) bool
        Pixels repaired in every image: hot and cold in the dark, stuck and dead in the
        white, isolated and bright in the background (bright in every image of a batch),
        with ``hot_pixels = "auto"``.
    counts : dict
        How many of each: ``dark_hot``, ``dark_cold``, ``white_stuck``, ``white_dead``,
        ``background_hot``.
    """

    micro: MicroImages
    hot_pixels: str = "auto"
    dark: MasterDark | None = None
    flat: FlatField | None = None
    background: np.ndarray | None = None
    bad: np.ndarray | None = None
    counts: dict = field(default_factory=dict)

    @property
    def noise(self) -> float | None:
        """The noise of one frame from the dark stack's spread, counts (None without one)."""
        return None if self.dark is None else self.dark.noise


@dataclass(frozen=True)
class Prepared:
    """One preprocessed image.

    Attributes
    ----------
    image : (rows, cols) float64
        Particle light, counts (A's scale in a pair), ≥ 0; 0 where masked.
    mask : (rows, cols) bool or None
        Pixels to leave out of the reconstruction (the flat's mask, unrepairable pixels).
    variance : (rows, cols) float64 or None
        Its noise variance, counts², where a dark stack measured it.
    figures : dict
        ``hot_pixels`` (repaired here), ``hot_pixels_in_image`` (found in this image),
        ``unrepaired``, ``masked_pixels``, ``scale`` (the pair's factor on it).
    """

    image: np.ndarray
    mask: np.ndarray | None
    variance: np.ndarray | None
    figures: dict


def _shape_check(a: np.ndarray, shape, name: str) -> None:
    if a.shape != tuple(shape):
        raise ImageError(f"{name} is {' × '.join(str(s) for s in a.shape)} pixels: expected "
                         f"the sensor's {shape[0]} × {shape[1]} (rows × cols)")


def prepare_frames(micro: MicroImages, *, dark: MasterDark | None = None, white=None,
                   background=None, hot_pixels: str = "auto",
                   names: dict | None = None) -> Frames:
    """The frames every image shares, from arrays.

    Parameters
    ----------
    micro : MicroImages
    dark : MasterDark, optional
        :func:`~plenopiv.preprocess.dark.master_dark` of the dark frames.
    white : (rows, cols) array_like, optional
        The mean white, raw counts (the dark is taken off here).
    background : (rows, cols) array_like, optional
        The background, raw counts as recorded (a background image, or a batch's minimum or
        mean); the dark is taken off here. With ``hot_pixels = "auto"`` its isolated bright
        pixels (:func:`~plenopiv.preprocess.pixels.isolated_pixels`) are bright in every
        image: hot.
    hot_pixels : {"auto", "none"}
    names : dict, optional
        ``{"dark": ..., "white": ..., "background": ...}``: how messages name them.

    Raises
    ------
    ImageError
        A frame of another shape than the sensor's (naming it), a white that is no white.
    """
    if hot_pixels not in HOT_PIXEL_MODES:
        raise ValueError(f"hot_pixels = {hot_pixels!r}: expected one of {HOT_PIXEL_MODES}")
    names = {"dark": "dark", "white": "white", "background": "background", **(names or {})}
    shape = micro.shape
    label = micro.label
    bad = np.zeros(shape, bool)
    counts: dict = {}
    offset = 0.0
    if dark is not None:
        _shape_check(dark.mean, shape, names["dark"])
        offset = dark.mean
        if hot_pixels == "auto":
            hot, cold = dark_defects(dark.mean)
            bad |= hot | cold
            counts.update(dark_hot=int(hot.sum()), dark_cold=int(cold.sum()))
    flat = None
    if white is not None:
        w = np.asarray(white, dtype=np.float64)
        _shape_check(w, shape, names["white"])
        flat = flat_field(w - offset, micro, bad=bad, name=names["white"])
        counts.update(white_dead=int(flat.dead.sum()), white_stuck=int(flat.stuck.sum()))
        if hot_pixels == "auto":
            bad |= flat.stuck | flat.dead
    bg = None
    if background is not None:
        b = np.asarray(background, dtype=np.float64)
        _shape_check(b, shape, names["background"])
        bg = b - offset
        if hot_pixels == "auto":
            noise = dark.noise if dark is not None and dark.noise is not None else (
                robust_sigma(bg[micro.gap]) if micro.gap.any() else 0.0)
            persistent = isolated_pixels(bg, label, noise=noise, exclude=bad)
            bad |= persistent
            counts["background_hot"] = int(persistent.sum())
    return Frames(micro, hot_pixels, dark, flat, bg, bad, counts)


def prepare_image(image, frames: Frames, *, name: str = "image") -> Prepared:
    """Preprocess one image (raw counts) with ``frames``.

    Dark, background, hot and dead pixels (repaired inside their micro-images), flat field,
    negative noise clipped at 0. With ``hot_pixels = "auto"`` the image's own isolated bright
    pixels (:func:`~plenopiv.preprocess.pixels.isolated_pixels`) are repaired too.
    """
    micro = frames.micro
    img = np.asarray(image, dtype=np.float64)
    _shape_check(img, micro.shape, name)
    x = img if frames.dark is None else subtract_dark(img, frames.dark, name=name)
    if frames.background is not None:
        x = subtract_background(x, frames.background, name=name)
    bad = np.zeros(micro.shape, bool) if frames.bad is None else frames.bad.copy()
    found = 0
    if frames.hot_pixels == "auto":
        noise = frames.noise
        if noise is None:
            gap = micro.gap
            noise = robust_sigma(x[gap]) if gap.any() else 0.0
        own = isolated_pixels(x, micro.label, noise=noise, exclude=bad)
        found = int(own.sum())
        bad |= own
    else:
        bad[:] = False
    unrepaired = np.zeros(micro.shape, bool)
    if bad.any():
        x, unrepaired = repair_pixels(x, bad, micro.label)
    variance = None
    if frames.dark is not None and frames.dark.frame_variance is not None:
        variance = frames.dark.frame_variance + frames.dark.variance
    mask = unrepaired if unrepaired.any() else None
    if frames.flat is not None:
        x = apply_flat(x, frames.flat)
        mask = frames.flat.mask if mask is None else (mask | frames.flat.mask)
        if variance is not None:
            variance = np.where(frames.flat.mask, 0.0, variance / frames.flat.gain ** 2)
    x = np.clip(x, 0.0, None)
    if mask is not None:
        x[mask] = 0.0
    figures = {"hot_pixels": int(bad.sum()), "hot_pixels_in_image": found,
               "unrepaired": int(unrepaired.sum()),
               "masked_pixels": 0 if mask is None else int(mask.sum()), "scale": 1.0}
    return Prepared(x, mask, variance, figures)


def prepare_pair(image_a, image_b, frames: Frames, *, saturated=(None, None),
                 names=("image A", "image B")) -> tuple[Prepared, Prepared, dict]:
    """Preprocess both exposures of a pair and put B on A's scale.

    :func:`prepare_image` on each, then :func:`~plenopiv.preprocess.intensity.normalise_pair`
    with ``saturated`` (each exposure's pixels at the recording's ceiling, or None). Returns
    ``(A, B, the normalisation's figures)``.
    """
    pa = prepare_image(image_a, frames, name=names[0])
    pb = prepare_image(image_b, frames, name=names[1])
    mask = pa.mask if pb.mask is None else (pb.mask if pa.mask is None else pa.mask | pb.mask)
    a, b, norm = normalise_pair(pa.image, pb.image, mask=mask, saturated=saturated)
    scale = norm["scale_b"]
    pa = dataclasses.replace(pa, image=a)
    pb = dataclasses.replace(pb, image=b, figures={**pb.figures, "scale": scale},
                             variance=None if pb.variance is None else pb.variance * scale ** 2)
    return pa, pb, norm
