"""HDF5 products: atomic writes with units, conventions, version and config; checked reads.

A product is an HDF5 file whose root attributes carry the package version, the product kind,
the conventions and the resolved config as JSON; each dataset carries its ``units``.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from plenopiv import __version__
from plenopiv.errors import WriteError
from plenopiv.products.files import atomic_path, check_input_file, write_failure
from plenopiv.products.jsonio import to_json

CONVENTIONS = ("SI units; pixels (row, col) with the top-left pixel centre at (0, 0); "
               "volumes [z, y, x]; world points (x, y, z); Z grows away from the camera")


@contextlib.contextmanager
def open_product(path: str | Path, product: str, error: type[Exception]) -> Iterator[h5py.File]:
    """Open a plenopiv HDF5 product for reading, checking that it is one of kind ``product``.

    A missing file, another product, and a read inside the block that fails (``OSError``,
    ``KeyError``, ``ValueError``: a truncated file, a missing dataset or attribute) all raise
    ``error`` naming the file; an ``error`` raised inside the block passes unchanged.
    """
    p = check_input_file(path, product, error)
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
    """Close an HDF5 file being written; a failed close is raised once, the id released.

    A close fails when its last buffers cannot be flushed (a full disk); the file id is
    released either way.
    """
    try:
        fh.close()
    except (OSError, RuntimeError):
        with contextlib.suppress(Exception):
            fh.id.close()
        raise


def cf_axes(fh) -> None:
    """Make ``/x``, ``/y``, ``/z`` of an open HDF5 file dimension scales with CF attributes."""
    for axis in ("x", "y", "z"):
        fh[axis].make_scale(axis)
        fh[axis].attrs["axis"] = axis.upper()
        fh[axis].attrs["standard_name"] = {"x": "projection_x_coordinate",
                                           "y": "projection_y_coordinate",
                                           "z": "depth"}[axis]
