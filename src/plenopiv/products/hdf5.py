"""HDF5 products: atomic writes with units, conventions, versions, provenance; checked reads.

A product is an HDF5 file whose root attributes carry the package version, the product kind,
its schema version and provenance (:mod:`plenopiv.products.provenance`), the conventions and
the resolved config as JSON; each dataset carries its ``units``. :func:`open_product` refuses
another kind, a newer schema or a damaged file, and its arrays are read through
:meth:`ProductFile.array`, which refuses NaN and infinite values where none may be
(:func:`check_finite`).
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
from plenopiv.products.provenance import (
    PROVENANCE_ATTR,
    SCHEMA_ATTR,
    check_readable,
    make_provenance,
    read_provenance,
    schema_version,
)

CONVENTIONS = ("SI units; pixels (row, col) with the top-left pixel centre at (0, 0); "
               "volumes [z, y, x]; world points (x, y, z); Z grows away from the camera")


def check_finite(values, name: str, path: str | Path, error: type[Exception], *,
                 allow_nan: bool = False, allow_inf: bool = False,
                 product: str = "product",
                 advice: str = "the file is damaged; make it again") -> np.ndarray:
    """``values`` read from dataset ``name`` of ``path``, refused where NaN or inf may not be.

    Every array read from a product or cache goes through here (:meth:`ProductFile.array`).
    ``allow_nan``: NaN marks a missing value (a rejected vector); ``allow_inf``: +inf or -inf
    is a value (a correlation peak without a second peak). Integer and boolean arrays pass.
    The error names the file, the dataset, how many values and where the first lie.
    """
    a = np.asarray(values)
    if a.dtype.kind not in "fc":
        return a
    bad = np.zeros(a.shape, bool)
    if not allow_nan:
        bad |= np.isnan(a)
    if not allow_inf:
        bad |= np.isinf(a)
    if bad.any():
        where = np.argwhere(bad)[:3]
        at = ", ".join(str(tuple(int(i) for i in w)) if a.ndim > 1 else str(int(w[0]))
                       for w in where) if a.ndim else "its value"
        n_nan, n_inf = int(np.isnan(a[bad]).sum()), int(np.isinf(a[bad]).sum())
        what = " and ".join(t for t in (f"{n_nan} NaN" if n_nan else "",
                                        f"{n_inf} infinite" if n_inf else "") if t)
        allowed = "NaN only" if allow_nan else ("±inf only" if allow_inf else "none")
        raise error(f"{product} file {str(path)!r}: dataset {name} holds {what} values "
                    f"(at {at}{', ...' if int(bad.sum()) > 3 else ''}; allowed there: "
                    f"{allowed}): {advice}")
    return a


def check_writable(datasets: dict, path: str | Path, kind: str, *, may_be_nan: tuple = (),
                   may_be_inf: tuple = ()) -> None:
    """Refuse datasets about to be written with NaN or ±inf where the format has none.

    Raises :class:`~plenopiv.errors.WriteError` naming the file, the dataset and where.
    """
    for name, arr in datasets.items():
        check_finite(arr, name, path, WriteError, allow_nan=name in may_be_nan,
                     allow_inf=name in may_be_inf, product=kind,
                     advice="refused before writing; nothing was written under that name")


class ProductFile:
    """An open product, as :func:`open_product` yields it: attributes and checked arrays.

    ``attrs`` are the root attributes; ``name in product`` says whether a dataset exists;
    :meth:`array` reads one (the only way in, so that every array read is checked);
    :attr:`provenance` and :attr:`schema` are what the file records.
    """

    def __init__(self, fh: h5py.File, path: Path, product: str, error: type[Exception],
                 schema: int):
        self._fh, self.path, self.product, self.error = fh, path, product, error
        self.schema = schema

    @property
    def attrs(self):
        """The root attributes."""
        return self._fh.attrs

    def __contains__(self, name: str) -> bool:
        return name in self._fh

    @property
    def provenance(self) -> dict:
        """The ``provenance`` record ({} for a file of schema 1)."""
        return read_provenance(self._fh.attrs.get(PROVENANCE_ATTR))

    def array(self, name: str, *, allow_nan: bool = False,
              allow_inf: bool = False) -> np.ndarray:
        """Dataset ``name``, refused (``error``) where it holds NaN or inf it may not hold."""
        return check_finite(self._fh[name][()], name, self.path, self.error,
                            allow_nan=allow_nan, allow_inf=allow_inf, product=self.product)

    def number(self, name: str, *, allow_nan: bool = False) -> np.ndarray | float:
        """Numeric root attribute ``name`` (a number or small array), checked as :meth:`array`."""
        value = check_finite(np.asarray(self._fh.attrs[name], float), f"attribute {name}",
                             self.path, self.error, allow_nan=allow_nan, product=self.product)
        return float(value) if value.ndim == 0 else value


@contextlib.contextmanager
def open_product(path: str | Path, product: str, error: type[Exception]
                 ) -> Iterator[ProductFile]:
    """Open a plenopiv HDF5 product for reading, checking that it is one of kind ``product``.

    A missing file, another product, a newer or unknown schema or a newer major version
    (:func:`~plenopiv.products.provenance.check_readable`), and a read inside the block that
    fails (``OSError``, ``KeyError``, ``ValueError``: a truncated file, a missing dataset or
    attribute) all raise ``error`` naming the file; an ``error`` raised inside the block
    passes unchanged.
    """
    p = check_input_file(path, product, error)
    try:
        with h5py.File(p, "r") as fh:
            if fh.attrs.get("product") != product:
                raise error(f"{str(p)!r} is not a plenopiv {product} file "
                            f"(product = {fh.attrs.get('product')!r})")
            schema = check_readable(p, product, fh.attrs.get(SCHEMA_ATTR),
                                    fh.attrs.get("plenopiv_version"), error)
            yield ProductFile(fh, p, product, error, schema)
    except error:
        raise
    except (OSError, KeyError, ValueError) as exc:
        raise error(f"{product} file {str(p)!r} is corrupt or incomplete: "
                    f"{type(exc).__name__}: {exc}") from None


def product_provenance(path: str | Path, product: str, error: type[Exception]) -> dict:
    """The ``provenance`` record of a product of kind ``product`` (checked as it is opened)."""
    with open_product(path, product, error) as fh:
        return fh.provenance


def write_h5(path: str | Path, datasets: dict[str, np.ndarray], *,
             attrs: dict[str, Any] | None = None, units: dict[str, str] | None = None,
             config: dict | None = None, kind: str = "product",
             compress: bool = True, finalize=None, provenance: dict | None = None,
             may_be_nan: tuple = (), may_be_inf: tuple = ()) -> Path:
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
    provenance : dict, optional
        What made the product (:func:`~plenopiv.products.provenance.make_provenance` of
        ``kind``), stored as the JSON root attribute ``provenance``; without it, a record of
        the versions alone. The root attribute ``schema_version`` is written either way.
    may_be_nan, may_be_inf : tuple of str
        The datasets that may hold NaN, or ±inf; any other non-finite value is refused
        (:class:`~plenopiv.errors.WriteError`) before anything is written.
    """
    p = Path(path)
    check_writable(datasets, p, kind, may_be_nan=may_be_nan, may_be_inf=may_be_inf)
    attrs = dict(attrs or {})
    record = make_provenance(kind) if provenance is None else dict(provenance)
    record.update(product=kind, schema_version=schema_version(kind))
    attrs = {SCHEMA_ATTR: schema_version(kind), PROVENANCE_ATTR: to_json(record), **attrs}
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
