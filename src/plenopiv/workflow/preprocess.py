"""The ``[preprocess]`` table applied: its files read and hashed, every image prepared and judged.

:class:`ImagePreparation` is made once per experiment and calibration (a pair processor or a
batch worker keeps it): it reads the dark, the white and the background named by the
experiment's ``[preprocess]`` table (paths relative to the experiment file), records their
SHA-256 content hashes, and builds the stage's :class:`~plenopiv.preprocess.stage.Frames`.
Each image then goes through :meth:`ImagePreparation.image` or :meth:`ImagePreparation.pair`:
the image check (:func:`~plenopiv.products.images.check_image`: refusals first), the stage,
and one warning per image whose condition is off (black level, saturation, hot pixels), naming
the figures and the key to set. Without a ``[preprocess]`` table the images are used as they
were recorded and judged all the same. Every product records what was applied in its
``preprocess`` attribute (:meth:`ImagePreparation.record`, docs/file-formats.md).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plenopiv.calibration.defects import DarkFrame
from plenopiv.calibration.model import Calibration
from plenopiv.errors import ConfigError, ImageError, PlenopivWarning
from plenopiv.preprocess.background import batch_background
from plenopiv.preprocess.condition import advice, image_condition
from plenopiv.preprocess.dark import master_dark
from plenopiv.preprocess.microimages import MicroImages, gap_level, micro_images
from plenopiv.preprocess.pixels import dark_defects
from plenopiv.preprocess.stage import Frames, prepare_frames, prepare_image, prepare_pair
from plenopiv.products.images import check_image, saturation

__all__ = ["ATTRIBUTE", "ImagePreparation", "PreparedImage", "calibration_dark",
           "form_batch_background", "union"]

#: The root attribute of every product that records what was applied (JSON).
ATTRIBUTE = "preprocess"

#: What a frame file may be, for messages.
FRAME_FILES = "a TIFF (a multi-page TIFF is a stack), a PNG, or file.h5:/path holding a 2-D " \
              "or 3-D array"


@dataclass(frozen=True)
class PreparedImage:
    """An image ready for the reconstruction.

    ``image``: counts, float64, ≥ 0; ``mask``: pixels to leave out (or None); ``figures``:
    what was done and measured (the product's ``exposures`` entry).
    """

    image: np.ndarray
    mask: np.ndarray | None
    figures: dict


def union(*masks) -> np.ndarray | None:
    """The pixels any of the image masks leaves out (None when none is given)."""
    given = [np.asarray(m, dtype=bool) for m in masks if m is not None]
    if not given:
        return None
    out = given[0].copy()
    for m in given[1:]:
        out |= m
    return out


def _frames_of(spec: str, base_dir: Path, what: str, expected: str) -> tuple[np.ndarray, dict]:
    """Read a frame file of the ``[preprocess]`` table: ``(frames, {file, sha256, frames})``."""
    from plenopiv.products.files import file_identity, split_dataset_spec
    from plenopiv.products.images import read_frames

    path, dataset = split_dataset_spec(spec)
    full = path if path.is_absolute() else base_dir / path
    shown = str(full) + ("" if dataset is None else f":{dataset}")
    if not full.exists():
        raise ImageError(f"{what} = {spec!r}: file {str(full)!r} not found: expected {expected} "
                         f"({FRAME_FILES})")
    frames = read_frames(shown, what=f"{what} = {spec!r}")
    return frames, {"file": shown, "sha256": file_identity(shown), "frames": len(frames)}


def _mean(frames: np.ndarray) -> np.ndarray:
    total = np.zeros(frames.shape[1:])
    for f in frames:
        total += f
    return total / len(frames)


class ImagePreparation:
    """The preprocessing of one experiment and calibration, its frames read once.

    Parameters
    ----------
    experiment : Experiment
        Its ``[preprocess]`` table (None: images used as recorded), ``[reconstruction]``
        ``f_number`` (the micro-images' size) and ``pixel_threshold`` (the dark threshold
        the condition is judged against), its folder (relative paths).
    calibration : Calibration
        The lattice: micro-image centres and pitch.
    batch_background : (rows, cols) array, optional
        The per-pixel minimum or mean of the batch's images (raw counts), for ``background =
        "minimum"`` or ``"mean"`` (:func:`form_batch_background`).
    batch_record : dict, optional
        What to record of it: ``file``, ``sha256``, ``images``.

    Raises
    ------
    ConfigError
        ``background = "minimum"`` or ``"mean"`` without a batch background.
    ImageError
        A frame file missing, unreadable, of another shape than the sensor, or a white that is
        no white; each message names the key and the file.
    """

    def __init__(self, experiment, calibration: Calibration, *, batch_background=None,
                 batch_record: dict | None = None):
        self.settings = experiment.preprocess
        self.shape = calibration.camera.sensor.shape
        self.dark_fraction = experiment.reconstruction.pixel_threshold
        s = self.settings
        kind = None if s is None else s.background_kind
        if batch_background is None:
            self.refuse_batch_background(experiment)
        self.micro: MicroImages = micro_images(calibration,
                                               f_number=experiment.reconstruction.f_number)
        self._files: dict = {}
        self.frames: Frames | None = None
        if s is None:
            return
        base = experiment.base_dir
        dark = white = background = None
        if s.dark is not None:
            stack, self._files["dark"] = _frames_of(s.dark, base, "[preprocess] dark",
                                                    "a dark frame or stack")
            dark = master_dark(stack, name=f"[preprocess] dark {s.dark!r}")
        if s.white is not None:
            stack, self._files["white"] = _frames_of(s.white, base, "[preprocess] white",
                                                     "a white frame or stack at the "
                                                     "recording's aperture")
            white = _mean(stack)
        if kind == "image":
            stack, self._files["background"] = _frames_of(
                s.background, base, "[preprocess] background", "a background image "
                "(a recording without particles)")
            background = _mean(stack)
        elif kind in ("minimum", "mean"):
            background = np.asarray(batch_background, dtype=np.float64)
            self._files["background"] = dict(batch_record or {})
        names = {k: f"[preprocess] {k} {getattr(s, k)!r}" for k in ("dark", "white",
                                                                     "background")}
        if kind in ("minimum", "mean"):
            names["background"] = f"the batch's {kind} background"
        self.frames = prepare_frames(self.micro, dark=dark, white=white, background=background,
                                     hot_pixels=s.hot_pixels, names=names)

    @property
    def static_mask(self) -> np.ndarray | None:
        """The pixels every image leaves out (the white's mask), or None."""
        f = self.frames
        return None if f is None or f.flat is None else f.flat.mask

    @staticmethod
    def refuse_batch_background(experiment) -> None:
        """Refuse ``background = "minimum"`` or ``"mean"`` where there is no batch.

        Raises :class:`~plenopiv.errors.ConfigError` naming the key and what to do instead
        (``plenopiv reconstruct``, ``plenopiv track``: one image, one pair).
        """
        s = experiment.preprocess
        kind = None if s is None else s.background_kind
        if kind in ("minimum", "mean"):
            raise ConfigError(
                f'[preprocess] background = "{kind}" is the per-pixel {kind} of a batch\'s '
                "images, and a single image or pair has no batch to form it from: give the "
                'path of a background image (background = "background.tif", a recording '
                "without particles) or run the batch (plenopiv run)")

    # ---- one image, one pair ---------------------------------------------------------------

    def _check(self, raw, name: str) -> tuple[np.ndarray, np.ndarray | None, float, list]:
        """The image check first (refusals), its warnings held.

        Returns ``(image, saturated pixels or None, saturated share, held warnings)``.
        """
        raw = np.asarray(raw)
        frac, ceiling, _ = saturation(raw) if raw.ndim == 2 else (0.0, np.nan, "")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            img = check_image(raw, shape=self.shape, name=name, particles=True)
        sat = (raw >= ceiling) if frac > 0 else None
        return img, sat, frac, list(caught)

    def _judge(self, prepared: np.ndarray, checked: np.ndarray, mask, frac: float, held: list,
               name: str, figures: dict) -> dict:
        """Measure the prepared image; one warning when it is off (held warnings folded in)."""
        s = self.settings
        cond = image_condition(prepared, self.micro, saturated_fraction=frac,
                               count_hot=s is None or s.hot_pixels == "none", exclude=mask)
        text = advice(cond, dark_fraction=self.dark_fraction, applied=s is not None,
                      dark=s is not None and s.dark is not None,
                      hot_pixels="none" if s is None else s.hot_pixels)
        notes = [w for w in held if issubclass(w.category, PlenopivWarning)]
        others = [w for w in held if not issubclass(w.category, PlenopivWarning)]
        for w in others:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        if text is not None:
            extra = "".join(f"; {w.message}" for w in notes)
            warnings.warn(f"{name}: {text}{extra}", PlenopivWarning, stacklevel=3)
        else:
            for w in notes:
                warnings.warn(str(w.message), PlenopivWarning, stacklevel=3)
        # hot_pixels: repaired ones (hot_pixels = "auto"), else those found and left
        out = {**cond.to_dict(), **figures,
               "raw_black_level_counts": float(gap_level(checked, self.micro))}
        if cond.hot_pixels is not None:
            out["hot_pixels"] = cond.hot_pixels
            out.pop("hot_pixels_in_image", None)
        return out

    def image(self, raw, name: str = "image") -> PreparedImage:
        """One image (raw counts as recorded) ready for the reconstruction."""
        checked, _sat, frac, held = self._check(raw, name)
        if self.frames is None:
            img, mask, figures = checked, None, {}
        else:
            p = prepare_image(checked, self.frames, name=name)
            img, mask, figures = p.image, p.mask, p.figures
        figures = self._judge(img, checked, mask, frac, held, name, figures)
        return PreparedImage(img, mask, figures)

    def pair(self, raw_a, raw_b, names=("image A", "image B")
             ) -> tuple[PreparedImage, PreparedImage, dict | None]:
        """Both exposures of a pair, B on A's scale; ``(A, B, the normalisation's figures)``."""
        ca, sat_a, frac_a, held_a = self._check(raw_a, names[0])
        cb, sat_b, frac_b, held_b = self._check(raw_b, names[1])
        if self.frames is None:
            pa = PreparedImage(ca, None, {})
            pb = PreparedImage(cb, None, {})
            norm = None
        else:
            a, b, norm = prepare_pair(ca, cb, self.frames, saturated=(sat_a, sat_b),
                                      names=names)
            pa = PreparedImage(a.image, a.mask, a.figures)
            pb = PreparedImage(b.image, b.mask, b.figures)
        fa = self._judge(pa.image, ca, pa.mask, frac_a, held_a, names[0], pa.figures)
        fb = self._judge(pb.image, cb, pb.mask, frac_b, held_b, names[1], pb.figures)
        return (PreparedImage(pa.image, pa.mask, fa), PreparedImage(pb.image, pb.mask, fb),
                norm)

    # ---- what a product records ------------------------------------------------------------

    def record(self, exposures: dict, normalisation: dict | None = None) -> dict:
        """The ``preprocess`` attribute of a product: what was applied, with the files' hashes.

        ``exposures``: ``{"image": figures}`` or ``{"A": ..., "B": ...}``
        (:attr:`PreparedImage.figures`); ``normalisation``: the pair's figures.
        """
        s = self.settings
        out: dict = {"applied": s is not None, "exposures": exposures}
        if s is None:
            return out
        f = self.frames
        dark = None
        if f.dark is not None:
            dark = {**self._files["dark"], "level_counts": f.dark.level,
                    "noise_counts": f.dark.noise,
                    "hot_pixels": f.counts.get("dark_hot", 0),
                    "cold_pixels": f.counts.get("dark_cold", 0)}
        white = None
        if f.flat is not None:
            white = {**self._files["white"], **f.flat.to_dict(),
                     "stuck_pixels": int(f.flat.stuck.sum())}
        background = {"kind": s.background_kind, **self._files.get("background", {})}
        if f.background is not None:
            background["level_counts"] = float(np.median(f.background))
            background["hot_pixels"] = f.counts.get("background_hot", 0)
        out.update(dark=dark, white=white, hot_pixels=s.hot_pixels, background=background,
                   bad_pixels=0 if f.bad is None else int(f.bad.sum()))
        if normalisation is not None:
            out["normalisation"] = normalisation
        return out


def form_batch_background(specs, kind: str) -> tuple[np.ndarray, int]:
    """The per-pixel ``"minimum"`` or ``"mean"`` of the images ``specs`` (raw counts).

    Read one at a time (:func:`~plenopiv.preprocess.background.batch_background`). Returns
    ``(background, number of images)``.
    """
    from plenopiv.products.images import read_image

    return batch_background((read_image(s) for s in specs), kind)


# ---- the calibration's dark ------------------------------------------------------------------


def calibration_dark(spec: str | Path, shape) -> tuple[DarkFrame, dict]:
    """The dark of ``plenopiv calibrate --dark``: ``(dark frame, record)``.

    ``shape``: the sensor's (rows, cols). The frame is the master dark (the frames' mean),
    subtracted from every calibration image by
    :func:`~plenopiv.calibration.calibrate.calibrate`, unclipped (clipped, the gaps' noise
    becomes a positive floor that a flat field amplifies at the micro-images' rims); its
    pixels to ignore are the dark's hot and cold ones
    (:func:`~plenopiv.preprocess.pixels.dark_defects`).

    Raises
    ------
    ImageError
        The file is missing, unreadable or of another shape than the sensor.
    """
    from plenopiv.products.files import file_identity, split_dataset_spec
    from plenopiv.products.images import read_frames

    if not split_dataset_spec(spec)[0].exists():
        raise ImageError(f"--dark {str(spec)!r}: file not found: expected a dark frame or "
                         f"stack at the calibration images' exposure ({FRAME_FILES})")
    frames = read_frames(spec, what=f"--dark {str(spec)!r}")
    if tuple(frames.shape[1:]) != tuple(shape):
        raise ImageError(f"--dark {str(spec)!r} is {frames.shape[1]} × {frames.shape[2]} pixels: "
                         f"expected the sensor's {shape[0]} × {shape[1]} (rows × cols)")
    dark = master_dark(frames, name=f"--dark {str(spec)!r}")
    hot, cold = dark_defects(dark.mean)
    record = {"file": str(spec), "sha256": file_identity(spec), "frames": dark.n_frames,
              "level_counts": dark.level, "noise_counts": dark.noise,
              "hot_pixels": int(hot.sum()), "cold_pixels": int(cold.sum())}
    return DarkFrame(np.asarray(dark.mean, np.float32), hot | cold), record
