"""Reading and writing images and products; every write is atomic.

Images: TIFF (8/16-bit or float), PNG, or an HDF5 dataset named ``file.h5:/path``, returned
as the sensor reads out, ``image[row, col]``, never flipped. Products are HDF5 files whose
attributes carry units, conventions, the package version and the resolved config as JSON.
A file is written under a temporary name in the same folder and renamed when complete, so a
crash never leaves a half-written product under the final name.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from plenopiv import __version__
from plenopiv.errors import ImageError

CONVENTIONS = ("SI units; pixels (row, col) with the top-left pixel centre at (0, 0); "
               "volumes [z, y, x]; world points (x, y, z); Z grows away from the camera")

IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".h5", ".hdf5")


def _file_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


_FILE_MODE = _file_mode()


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` if the block succeeds."""
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".part", dir=final.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, _FILE_MODE)   # mkstemp makes 0600; give the usual permissions
        os.replace(tmp_path, final)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


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


def check_image(image: np.ndarray, *, shape: tuple[int, int] | None = None, name: str = "image",
                saturation_fraction: float = 0.05) -> np.ndarray:
    """Validate a recorded image; return it as float64.

    Checks: 2-D, the camera's sensor ``shape`` (when given), no NaN/inf, not all dark or
    constant, not saturated (more than ``saturation_fraction`` of the pixels at the integer
    dtype's maximum).
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ImageError(f"{name} has shape {img.shape}: expected a 2-D (rows, cols) image")
    if shape is not None and tuple(img.shape) != tuple(shape):
        raise ImageError(f"{name} is {img.shape[0]} × {img.shape[1]} pixels but the camera's "
                         f"sensor is {shape[0]} × {shape[1]} (rows × cols): wrong camera or "
                         "a cropped/rotated image")
    if np.issubdtype(img.dtype, np.integer):
        top = np.iinfo(img.dtype).max
        frac = float(np.count_nonzero(img == top)) / img.size
        if frac > saturation_fraction:
            raise ImageError(f"{name} is saturated: {frac:.1%} of the pixels are at {top}; "
                             f"expected at most {saturation_fraction:.0%}; reduce the exposure")
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
    return out


def write_image(path: str | Path, image: np.ndarray, *, metadata: dict | None = None) -> Path:
    """Write an image atomically as TIFF (or ``.png`` for 8/16-bit) and return the path."""
    p = Path(path)
    suffix = p.suffix.lower()
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


def to_json(obj: Any) -> str:
    """JSON text of ``obj`` (numpy arrays and scalars allowed)."""
    return json.dumps(obj, default=_jsonable, sort_keys=True)


def write_h5(path: str | Path, datasets: dict[str, np.ndarray], *,
             attrs: dict[str, Any] | None = None, units: dict[str, str] | None = None,
             config: dict | None = None, kind: str = "product",
             compress: bool = True, finish=None) -> Path:
    """Write an HDF5 product atomically.

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
    finish : callable, optional
        ``finish(h5py.File)``, called on the open temporary file after the datasets are
        written (e.g. to attach dimension scales), so that the renamed file is complete.
    """
    p = Path(path)
    with atomic_path(p) as tmp:
        with h5py.File(tmp, "w") as fh:
            fh.attrs["plenopiv_version"] = __version__
            fh.attrs["product"] = kind
            fh.attrs["conventions"] = CONVENTIONS
            if config is not None:
                fh.attrs["config"] = to_json(config)
            for k, v in (attrs or {}).items():
                fh.attrs[k] = v
            for name, arr in datasets.items():
                a = np.asarray(arr)
                big = compress and a.size > 4096
                kw = {"compression": "gzip", "compression_opts": 4} if big else {}
                ds = fh.create_dataset(name, data=a, **kw)
                if units and name in units:
                    ds.attrs["units"] = units[name]
            if finish is not None:
                finish(fh)
    return p
