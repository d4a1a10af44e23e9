"""Images: read (TIFF, PNG, ``file.h5:/dataset``), check, and write atomically.

Images are returned as the sensor reads out, ``image[row, col]``, never flipped.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import h5py
import numpy as np

from plenopiv.errors import ImageError, OutputError, PlenopivWarning
from plenopiv.products.files import atomic_path, check_input_file, split_dataset_spec
from plenopiv.products.jsonio import dumps

IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".h5", ".hdf5")


def read_image(spec: str | Path) -> np.ndarray:
    """Read a 2-D image from TIFF, PNG or ``file.h5:/dataset``.

    Raises
    ------
    ImageError
        When the file is missing, unreadable, truncated or corrupt, or not a 2-D image.
    """
    img = _read_array(spec)
    if img.ndim != 2:
        raise ImageError(f"image {str(spec)!r} has shape {img.shape}: expected a 2-D "
                         "(rows, cols) image")
    return img


def read_frames(spec: str | Path, *, what: str = "frames") -> np.ndarray:
    """Read one frame or a stack as ``(n, rows, cols)``, in the file's own dtype.

    A TIFF (a multi-page TIFF is a stack), a PNG, or ``file.h5:/dataset`` holding a 2-D or
    3-D array (frames along the first axis). ``what`` names the file in messages.

    Raises
    ------
    ImageError
        When the file is missing, unreadable, corrupt, or holds no 2-D or 3-D array.
    """
    try:
        a = _read_array(spec)
    except ImageError as exc:
        raise ImageError(f"{what}: {exc}") from None
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or 0 in a.shape:
        raise ImageError(f"{what} {str(spec)!r} has shape {a.shape}: expected one frame "
                         "(rows, cols) or a stack (frames, rows, cols)")
    return a


def _read_array(spec: str | Path) -> np.ndarray:
    """The array of an image file (TIFF pages stacked; a colour PNG averaged), checked real."""
    path, dataset = split_dataset_spec(spec)
    check_input_file(path, "image", ImageError)
    suffix = path.suffix.lower()
    try:
        if dataset is not None or suffix in (".h5", ".hdf5"):
            with h5py.File(path, "r") as fh:
                name = dataset or _default_image_dataset(fh, path)
                if name not in fh or not isinstance(fh[name], h5py.Dataset):
                    raise ImageError(f"{str(path)!r} has no image dataset {name!r}; datasets: "
                                     f"{', '.join(_datasets(fh)) or 'none'}")
                img = fh[name][()]
        elif suffix in (".tif", ".tiff"):
            import tifffile

            img = tifffile.imread(path)
        elif suffix == ".png":
            import skimage.io

            img = skimage.io.imread(path)
        else:
            raise ImageError(f"image file {str(path)!r}: unknown format {suffix!r}; expected "
                             f"one of {', '.join(IMAGE_SUFFIXES)} or file.h5:/dataset")
    except ImageError:
        raise
    except Exception as exc:  # noqa: BLE001 - any reader failure means a corrupt/truncated file
        raise ImageError(f"image file {str(path)!r} cannot be read (corrupt or truncated?): "
                         f"{type(exc).__name__}: {exc}") from None
    img = np.asarray(img)
    _refuse_non_real(img, repr(str(spec)))
    if img.ndim == 3 and img.shape[-1] in (3, 4) and suffix == ".png":
        img = img[..., :3].mean(axis=-1)   # a colour PNG of a monochrome sensor
    return img


def _datasets(fh: h5py.File) -> list[str]:
    names: list[str] = []
    fh.visititems(lambda n, o: names.append("/" + n) if isinstance(o, h5py.Dataset) else None)
    return names


def _default_image_dataset(fh: h5py.File, path: Path) -> str:
    for name in ("/image", "/image_a"):
        if name in fh:
            return name
    raise ImageError(f"{str(path)!r}: name the image dataset as {path}:/DATASET; datasets: "
                     f"{', '.join(_datasets(fh)) or 'none'}")


def _refuse_non_real(img: np.ndarray, name: str) -> None:
    if np.iscomplexobj(img):
        raise ImageError(f"image {name} holds complex values (dtype {img.dtype}): expected "
                         "real intensities (take the magnitude or the real part first)")
    if not (np.issubdtype(img.dtype, np.number) or img.dtype == np.bool_):
        raise ImageError(f"image {name} has dtype {img.dtype}: expected numbers")


#: Below this fraction of pixels at the ceiling an image is not reported as saturated.
SATURATION_WARNING = 1e-3
#: A particle image whose bright tail rises less than this many times the spread of its
#: dark tail above its median is pure noise (uniform noise gives 1, Gaussian noise 1).
NOISE_CONTRAST = 3.0


def saturation(img: np.ndarray) -> tuple[float, float, str]:
    """``(fraction, ceiling, what)``: the share of pixels at the data's actual ceiling.

    Integers: the ceiling is the largest value when it is 2^k - 1 for a bit depth k the
    dtype holds (4095 for 12-bit data in a uint16 file), else the dtype's maximum. Floats:
    the largest value when more than one pixel holds it (a clipped image), else none.
    """
    a = np.asarray(img)
    if a.size == 0:
        return 0.0, math.nan, ""
    top = a.max()
    if np.issubdtype(a.dtype, np.integer):
        bits = np.iinfo(a.dtype).bits
        t = int(top)
        k = (t + 1).bit_length() - 1
        if t > 0 and (t + 1) == (1 << k) and 8 <= k <= bits:
            what = f"{k}-bit data" + ("" if k == bits else f" in {a.dtype}")
            return float(np.count_nonzero(a == top)) / a.size, float(t), what
        ceiling = np.iinfo(a.dtype).max
        return (float(np.count_nonzero(a == ceiling)) / a.size, float(ceiling),
                f"{a.dtype} maximum")
    if np.issubdtype(a.dtype, np.floating) and np.isfinite(top):
        n = int(np.count_nonzero(a == top))
        if 1 < n < a.size and top > 0:
            return n / a.size, float(top), "clipped floats"
    return 0.0, float(top) if np.isfinite(top) else math.nan, ""


def check_image(image: np.ndarray, *, shape: tuple[int, int] | None = None, name: str = "image",
                saturation_fraction: float = 0.05, particles: bool = False) -> np.ndarray:
    """Validate a recorded image; return it as float64.

    Checks: real numbers (complex refused), 2-D, the camera's sensor ``shape`` (when given),
    no NaN/inf, not all dark or constant, saturation at the data's actual ceiling
    (:func:`saturation`: more than ``saturation_fraction`` is an error, more than 0.1 % a
    :class:`~plenopiv.errors.PlenopivWarning` with the fraction), and negative values: a
    negative background (median < 0) is refused, a few negative pixels (background
    subtraction) are clipped at 0 with a warning when more than 1 % of them. With
    ``particles=True`` (particle images) an image whose bright pixels do not stand out of its
    noise (:data:`NOISE_CONTRAST`) is refused as pure noise.
    """
    img = np.asarray(image)
    _refuse_non_real(img, name)
    if img.ndim != 2:
        raise ImageError(f"{name} has shape {img.shape}: expected a 2-D (rows, cols) image")
    if shape is not None and tuple(img.shape) != tuple(shape):
        raise ImageError(f"{name} is {img.shape[0]} × {img.shape[1]} pixels but the camera's "
                         f"sensor is {shape[0]} × {shape[1]} (rows × cols): wrong camera or "
                         "a cropped/rotated image")
    frac, ceiling, what = saturation(img)
    if frac > saturation_fraction:
        raise ImageError(f"{name} is saturated: {frac:.1%} of the pixels are at {ceiling:g} "
                         f"({what}); expected at most {saturation_fraction:.0%}; reduce the "
                         "exposure")
    out = img.astype(np.float64)
    bad = ~np.isfinite(out)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise ImageError(f"{name} has {int(bad.sum())} NaN/inf pixels (first at row {r}, "
                         f"col {c}): expected finite values")
    if out.max() <= 0:
        raise ImageError(f"{name} is all dark (max = {out.max():g}): expected a lit image")
    if out.max() == out.min():
        raise ImageError(f"{name} is constant ({out.max():g}): expected an image with structure")
    if frac > SATURATION_WARNING:
        warnings.warn(f"{name} is saturated: {frac:.2%} of the pixels are at {ceiling:g} "
                      f"({what}); their intensities are clipped", PlenopivWarning, stacklevel=2)
    neg = out < 0
    if neg.any():
        share = float(neg.mean())
        med = float(np.median(out))
        if med < 0:
            raise ImageError(f"{name} has a negative background: median {med:g}, {share:.1%} "
                             f"of the pixels below 0 (min {out.min():g}): expected intensities "
                             ">= 0 on a dark background near 0; add the offset back or clip "
                             "the image at 0")
        if share > 0.01:
            warnings.warn(f"{name}: {share:.1%} of the pixels are negative (min "
                          f"{out.min():g}); clipped at 0", PlenopivWarning, stacklevel=2)
        out = np.clip(out, 0.0, None)
    if particles:
        lo, med, hi = np.percentile(out, [0.1, 50.0, 99.9])
        spread = med - lo
        if spread > 0 and (hi - med) < NOISE_CONTRAST * spread:
            raise ImageError(f"{name} looks like pure noise: its bright pixels (99.9th "
                             f"percentile {hi:g}) rise only {(hi - med) / spread:.2f} times as "
                             f"far above the median ({med:g}) as its dark pixels (0.1st "
                             f"percentile {lo:g}) fall below it; expected particle images "
                             f"that stand out of the background (ratio >= {NOISE_CONTRAST:g})")
    return out


def warn_identical(names, arrays, *, consequence: str) -> list[tuple[str, str]]:
    """Warn for every two of ``arrays`` that hold the same values; None entries are skipped.

    Two exposures, volumes or calibration images that are equal are the same file or the
    same frame given twice: what is computed from them runs, and says nothing. The warning
    (:class:`~plenopiv.errors.PlenopivWarning`) names both (``names``, one per array) and
    ``consequence``, what the result then is. Returns the pairs of names warned about.
    """
    given = [(n, np.asarray(a)) for n, a in zip(names, arrays, strict=True) if a is not None]
    same = []
    for i, (a, x) in enumerate(given):
        for b, y in given[i + 1:]:
            if x.shape == y.shape and np.array_equal(x, y):
                same.append((a, b))
                warnings.warn(f"{a} and {b} are identical (the same file or frame given "
                              f"twice?): {consequence}", PlenopivWarning, stacklevel=2)
    return same


def write_image(path: str | Path, image: np.ndarray, *, metadata: dict | None = None) -> Path:
    """Write an image atomically as TIFF (or ``.png`` for 8/16-bit) and return the path."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".tif", ".tiff", ".png"):
        raise OutputError(f"output {str(p)!r}: expected a .tif/.tiff or .png file name")
    with atomic_path(p) as tmp:
        if suffix in (".tif", ".tiff"):
            import tifffile

            tifffile.imwrite(tmp, image, metadata=None,
                             description=dumps(metadata or {}))
        elif suffix == ".png":
            import skimage.io

            skimage.io.imsave(tmp, image, check_contrast=False, extension=".png")
        else:
            raise ImageError(f"output {str(p)!r}: expected a .tif/.tiff or .png file name")
    return p


def write_image_stack(path: str | Path, frames: np.ndarray, *,
                      metadata: dict | None = None) -> Path:
    """Write frames ``(n, rows, cols)`` atomically as one multi-page TIFF; return the path.

    Each frame is one page; ``metadata`` is JSON in the first page's description.
    """
    p = Path(path)
    stack = np.asarray(frames)
    if p.suffix.lower() not in (".tif", ".tiff"):
        raise OutputError(f"output {str(p)!r}: a stack of frames is written as .tif/.tiff")
    if stack.ndim != 3:
        raise ImageError(f"frames of shape {stack.shape}: expected (n, rows, cols)")
    with atomic_path(p) as tmp:
        import tifffile

        tifffile.imwrite(tmp, stack, photometric="minisblack", metadata=None,
                         description=dumps(metadata or {}))
    return p
