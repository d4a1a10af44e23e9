"""Reading and writing images and products; every write is atomic.

Images: TIFF (8/16-bit or float), PNG, or an HDF5 dataset named ``file.h5:/path``, returned
as the sensor reads out, ``image[row, col]``, never flipped. Products are HDF5 files whose
attributes carry units, conventions, the package version and the resolved config as JSON.
A file is written under a temporary name in the same folder and renamed when complete, so a
crash never leaves a half-written product under the final name.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import math
import os
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from plenopiv import __version__
from plenopiv.errors import ImageError, OutputError, PlenopivWarning, WriteError

CONVENTIONS = ("SI units; pixels (row, col) with the top-left pixel centre at (0, 0); "
               "volumes [z, y, x]; world points (x, y, z); Z grows away from the camera")

IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".h5", ".hdf5")


def _file_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _file_mode()


def _reason(exc: BaseException) -> str:
    """A short reason of a failed write (h5py folds errno into long RuntimeError texts)."""
    text = str(exc)
    if getattr(exc, "errno", None) == errno.ENOSPC or "No space left on device" in text \
            or "errno = 28" in text:
        return "no space left on device"
    if getattr(exc, "errno", None) == errno.EDQUOT or "Disk quota exceeded" in text:
        return "disk quota exceeded"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror.lower()
    return (text.splitlines() or [type(exc).__name__])[0]


def write_failure(path: str | Path, exc: BaseException) -> WriteError:
    """The :class:`WriteError` for a write of ``path`` that raised ``exc``."""
    return WriteError(f"writing {str(path)!r} failed: {_reason(exc)} "
                      f"({type(exc).__name__}); nothing was written under that name")


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` if the block succeeds.

    The temporary is ``.NAME.XXXXXXXX.part`` in the same folder; it is deleted whatever
    happens. A write that fails with ``OSError`` (a full disk) becomes a
    :class:`~plenopiv.errors.WriteError` naming the path and the reason.
    """
    final = Path(path)
    if final.is_dir():
        raise OutputError(f"output {str(final)!r} is a folder: expected a file name")
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".part", dir=final.parent)
        os.close(fd)
    except OSError as exc:
        raise OutputError(f"output {str(final)!r} cannot be written: {_reason(exc)}") from None
    tmp_path = Path(tmp)
    try:
        try:
            yield tmp_path
            os.chmod(tmp_path, _FILE_MODE)   # mkstemp makes 0600; give the usual permissions
            os.replace(tmp_path, final)
        except OSError as exc:
            raise write_failure(final, exc) from None
    finally:
        with contextlib.suppress(OSError):
            if tmp_path.exists():
                tmp_path.unlink()
        with contextlib.suppress(OSError):   # a writer that appends its own suffix (.vti)
            for extra in tmp_path.parent.glob(glob_escape(tmp_path.name) + ".*"):
                extra.unlink()


def glob_escape(name: str) -> str:
    """``name`` with the glob wildcards escaped."""
    import glob

    return glob.escape(name)


def check_output_path(path: str | Path, *, suffixes: tuple[str, ...] | None = None,
                      inputs=(), what: str = "--out", folder: bool = False) -> Path:
    """Check an output path before any work; return it.

    Refused (:class:`~plenopiv.errors.OutputError`, naming the path): a wrong suffix, an
    existing folder (or, with ``folder=True``, an existing file), something that is not a
    regular file (a device), one of the command's ``inputs`` (same resolved path or the same
    file through a link), a parent that is a file, and a folder where no file can be created
    (probed by creating and deleting a temporary file: read-only mounts, /proc, /sys, no
    permission). Nothing is left behind.
    """
    p = Path(path)
    if not str(path).strip():
        raise OutputError(f"{what} {str(path)!r}: expected a file name")
    if suffixes is not None and not folder and p.suffix.lower() not in suffixes:
        raise OutputError(f"{what} {str(path)!r}: expected a file ending in "
                          f"{' or '.join(suffixes)}")
    if folder:
        if p.exists() and not p.is_dir():
            raise OutputError(f"{what} {str(path)!r} is an existing file: expected a folder "
                              "(new or existing) for the products")
    elif p.is_dir():
        raise OutputError(f"{what} {str(path)!r} is a folder: expected a file name "
                          f"ending in {' or '.join(suffixes or ('the product suffix',))}")
    elif p.exists() and not p.is_file():
        raise OutputError(f"{what} {str(path)!r} exists and is not a regular file: expected "
                          "a new file or a product to replace")
    for inp in inputs:
        if inp is None:
            continue
        ip, _ = split_dataset_spec(inp)
        same = p.resolve() == ip.resolve()
        if not same and p.exists() and ip.exists():
            with contextlib.suppress(OSError):
                same = os.path.samefile(p, ip)
        if same:
            raise OutputError(f"{what} {str(path)!r} is the input {str(inp)!r}: it would be "
                              "overwritten; choose another output name")
    _probe_writable(p if folder else p.parent, what, str(path))
    return p


def _probe_writable(folder: Path, what: str, shown: str) -> None:
    target = folder
    while not target.exists():
        if target.parent == target:
            break
        target = target.parent
    if not target.is_dir():
        raise OutputError(f"{what} {shown!r}: {str(target)!r} is a file, not a folder")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".plenopiv-probe.", suffix=".part", dir=target)
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        raise OutputError(f"{what} {shown!r}: cannot create files in {str(target)!r} "
                          f"({_reason(exc)}): expected a writable folder") from None


def file_identity(spec: str | Path) -> str:
    """Identity of an input file (or ``file.h5:/dataset``): the SHA-256 of its bytes,
    with the dataset name. Two copies of one file are the same input; an edited or
    replaced file is another."""
    path, dataset = split_dataset_spec(spec)
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    except OSError as exc:
        raise ImageError(f"input {str(path)!r} cannot be read: {_reason(exc)}") from None
    return h.hexdigest() + ("" if dataset is None else f":{dataset}")


def split_dataset_spec(spec: str | Path) -> tuple[Path, str | None]:
    """Split ``file.h5:/path`` into the file and the dataset path (None for other files)."""
    s = str(spec)
    for suffix in (".h5:", ".hdf5:"):
        if suffix in s:
            i = s.index(suffix) + len(suffix) - 1
            return Path(s[:i]), s[i + 1:] or "/"
    return Path(s), None


def read_image(spec: str | Path) -> np.ndarray:
    """Read a 2-D image from TIFF, PNG or ``file.h5:/dataset``.

    Raises
    ------
    ImageError
        When the file is missing, unreadable, truncated or corrupt, or not a 2-D image.
    """
    path, dataset = split_dataset_spec(spec)
    if not path.exists():
        raise ImageError(f"image file {str(path)!r} not found")
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
    if img.ndim != 2:
        raise ImageError(f"image {str(spec)!r} has shape {img.shape}: expected a 2-D "
                         "(rows, cols) image")
    return img


@contextlib.contextmanager
def open_product(path: str | Path, product: str, error: type[Exception]) -> Iterator[h5py.File]:
    """Open a plenopiv HDF5 product for reading, checking that it is one of kind ``product``.

    A missing file, another product, and a read inside the block that fails (``OSError``,
    ``KeyError``, ``ValueError``: a truncated file, a missing dataset or attribute) all raise
    ``error`` naming the file; an ``error`` raised inside the block passes unchanged.
    """
    p = Path(path)
    if not p.exists():
        raise error(f"{product} file {str(p)!r} not found")
    try:
        with h5py.File(p, "r") as fh:
            if fh.attrs.get("product") != product:
                raise error(f"{str(p)!r} is not a plenopiv {product} file "
                            f"(product = {fh.attrs.get('product')!r})")
            yield fh
    except error:
        raise
    except (OSError, KeyError, ValueError) as exc:
        raise error(f"{product} file {str(p)!r} is corrupt or incomplete: "
                    f"{type(exc).__name__}: {exc}") from None


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
                             description=json.dumps(metadata or {}, default=_jsonable))
        elif suffix == ".png":
            import skimage.io

            skimage.io.imsave(tmp, image, check_contrast=False, extension=".png")
        else:
            raise ImageError(f"output {str(p)!r}: expected a .tif/.tiff or .png file name")
    return p


def _jsonable(o: Any):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def finite_json(obj: Any) -> Any:
    """``obj`` with every non-finite float (NaN, ±inf) replaced by None (JSON null)."""
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite_json(obj.tolist())
    if isinstance(obj, np.generic):
        return finite_json(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def to_json(obj: Any) -> str:
    """Valid JSON text of ``obj`` (numpy arrays and scalars allowed; NaN and ±inf become
    null, never the bare ``NaN`` that JSON parsers reject)."""
    return json.dumps(finite_json(obj), default=_jsonable, sort_keys=True, allow_nan=False)


def write_h5(path: str | Path, datasets: dict[str, np.ndarray], *,
             attrs: dict[str, Any] | None = None, units: dict[str, str] | None = None,
             config: dict | None = None, kind: str = "product",
             compress: bool = True, finalize=None) -> Path:
    """Write an HDF5 product atomically.

    The file is written under a temporary name and renamed when closed; the root attribute
    ``complete`` (when ``attrs`` holds it) is written last, after every dataset and after
    ``finalize(fh)``, so that a failed write never leaves a product marked complete. A write
    that fails (a full disk) raises :class:`~plenopiv.errors.WriteError`.

    Parameters
    ----------
    datasets : dict
        ``{"/group/name": array}``.
    attrs : dict
        Root attributes (numbers, strings, small arrays).
    units : dict
        ``{"/group/name": "m"}``, stored as each dataset's ``units`` attribute.
    config : dict
        The resolved configuration, stored as JSON in the root attribute ``config``.
    compress : bool
        gzip the larger datasets (off for caches that must load fast).
    finalize : callable, optional
        ``finalize(fh)`` on the open file after the datasets (e.g. dimension scales).
    """
    p = Path(path)
    attrs = dict(attrs or {})
    complete = attrs.pop("complete", None)
    size = sum(np.asarray(a).nbytes for a in datasets.values())
    with atomic_path(p) as tmp:
        if size <= IN_MEMORY_BYTES:
            # HDF5 built in memory, then written with plain writes: a full disk is a clean
            # OSError here, never an HDF5 library error (h5py can crash when it later frees
            # the objects of a file whose writes failed)
            import io as _io

            buf = _io.BytesIO()
            _write_h5_file(buf, datasets, attrs, units, config, kind, compress, finalize,
                           complete)
            with open(tmp, "wb") as fh:
                fh.write(buf.getbuffer())
                fh.flush()
                os.fsync(fh.fileno())
        else:
            _check_free_space(p, size)
            try:
                _write_h5_file(tmp, datasets, attrs, units, config, kind, compress, finalize,
                               complete)
            except RuntimeError as exc:      # h5py reports a failed flush or close so
                raise write_failure(p, exc) from None
    return p


#: Products up to this size are built in memory and written with plain file writes.
IN_MEMORY_BYTES = 1 << 29


def _check_free_space(path: Path, nbytes: int) -> None:
    import shutil

    try:
        free = shutil.disk_usage(path.parent).free
    except OSError:
        return
    if free < nbytes:
        raise WriteError(f"writing {str(path)!r} needs up to {nbytes / 1e6:.4g} MB but its "
                         f"disk has {free / 1e6:.4g} MB free: no space left on device; "
                         "nothing was written under that name")


def _write_h5_file(tmp, datasets, attrs, units, config, kind, compress, finalize,
               complete) -> None:
    fh = h5py.File(tmp, "w")
    try:
        fh.attrs["plenopiv_version"] = __version__
        fh.attrs["product"] = kind
        fh.attrs["conventions"] = CONVENTIONS
        if config is not None:
            fh.attrs["config"] = to_json(config)
        for k, v in attrs.items():
            fh.attrs[k] = v
        for name, arr in datasets.items():
            a = np.asarray(arr)
            big = compress and a.size > 4096
            kw = {"compression": "gzip", "compression_opts": 4} if big else {}
            ds = fh.create_dataset(name, data=a, **kw)
            if units and name in units:
                ds.attrs["units"] = units[name]
        if finalize is not None:
            finalize(fh)
        if complete is not None:
            fh.flush()
            fh.attrs["complete"] = complete
    finally:
        _close_h5(fh)


def _close_h5(fh) -> None:
    """Close an HDF5 file being written; a close that fails (its last buffers could not be
    flushed: a full disk) is raised once, and the file id is released either way."""
    try:
        fh.close()
    except (OSError, RuntimeError):
        with contextlib.suppress(Exception):
            fh.id.close()
        raise
