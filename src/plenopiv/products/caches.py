"""The on-disk caches and their keys: the chain's response and the explicit weights.

The weights are built or loaded by :func:`plenopiv.reconstruction.build.cached_weights`;
this module holds how both caches are stored. Each carries a SHA-256 checksum of its content
and its schema version; a cache whose content does not match its checksum, holds NaN or inf
where none may be, or is of a newer schema is never used: it is computed again, with a
warning. A weights cache verified once is trusted while its file is untouched (its size,
inode, modification and change times, recorded beside it in ``weights-KEY.verified``).
"""

from __future__ import annotations

import hashlib
import json
import time
import warnings
from pathlib import Path

import numpy as np

from plenopiv.errors import PlenopivWarning
from plenopiv.piv.response import RESPONSE_VERSION, Response
from plenopiv.products.jsonio import dumps
from plenopiv.products.provenance import check_readable, json_hash, schema_version


class _Refused(Exception):
    """A cache this plenopiv may not read (a newer schema or version)."""


def _warn(message: str) -> None:
    warnings.warn(message, PlenopivWarning, stacklevel=3)


def response_key(*parts) -> str:
    """A stable hash of what a response depends on (any JSON-able parts)."""
    h = hashlib.sha256()
    h.update(dumps([RESPONSE_VERSION, *parts], sort_keys=True, default=str).encode())
    return h.hexdigest()


#: Entries of a response cache that must be finite (the others may be null: NaN).
RESPONSE_FINITE = ("z_m", "shifts_m", "cell_m", "n_particles")


def _response_problem(path: Path, d: dict) -> str | None:
    """Why the response cache ``d`` (of ``path``, its key already matched) may not be used."""
    try:
        check_readable(path, "response cache", d.get("schema_version"),
                       d.get("plenopiv_version"), _Refused)
    except _Refused as exc:
        return str(exc)
    stored = d.get("checksum")
    if stored is None:
        return None if "schema_version" not in d else "it has no checksum"
    body = {k: v for k, v in d.items() if k != "checksum"}
    if json_hash(body) != stored:
        return "its content does not match its checksum (changed since it was written)"
    for name, value in d.items():
        if isinstance(value, (list, int, float)) and not isinstance(value, bool):
            a = np.asarray(value, float)
            if np.isinf(a).any() or (name in RESPONSE_FINITE and np.isnan(a).any()):
                return (f"its {name} holds {'inf' if np.isinf(a).any() else 'NaN (null)'} "
                        "values")
    return None


def cached_response(path: Path | None, key: str, compute) -> tuple[Response | None, bool]:
    """The response stored at ``path`` under ``key``, else ``compute()`` (saved there).

    ``compute()`` returning None is not saved. Returns ``(response, from_cache)``; ``path``
    None disables the cache. A cache of ``key`` whose checksum fails, that holds inf (or NaN
    in :data:`RESPONSE_FINITE`), or of a newer schema is measured again, with a warning; one
    written before checksums is measured again silently.
    """
    if path is not None and path.exists():
        try:
            d = json.loads(path.read_text())
            if d.get("key") == key:
                problem = _response_problem(path, d)
                if problem is not None:
                    _warn(f"response cache {str(path)!r} not used: {problem}; measured again")
                elif "checksum" in d:
                    return Response.from_dict(d), True
        except (OSError, ValueError, KeyError, TypeError):
            pass   # unreadable or another version: measure again
    resp = compute()
    if path is not None and resp is not None:
        from plenopiv import __version__
        from plenopiv.products.files import atomic_path

        body = json.loads(dumps({"key": key, **resp.to_dict(),
                                 "schema_version": schema_version("response cache"),
                                 "plenopiv_version": __version__}))
        with atomic_path(path) as tmp:
            tmp.write_text(dumps({**body, "checksum": json_hash(body)}))
    return resp, False


# --------------------------------------------------------------------------------------------
# the weights cache
# --------------------------------------------------------------------------------------------


def weights_cache_path(cache_dir: str | Path, key: str) -> Path:
    """The file of the explicit weights of geometry ``key`` in ``cache_dir``."""
    return Path(cache_dir) / f"weights-{key[:24]}.h5"


#: The datasets of a weights cache, in the order the checksum reads them.
WEIGHT_DATASETS = ("/indptr", "/indices", "/data", "/pixel")
#: A weights file changed less than this long before its check was recorded may have changed
#: within its clock's resolution: it is checked again (nanoseconds).
RACY_NS = 2_000_000_000


def weights_checksum(arrays) -> str:
    """``sha256:`` + SHA-256 of the arrays of :data:`WEIGHT_DATASETS`, names and bytes."""
    h = hashlib.sha256()
    for name, a in zip(WEIGHT_DATASETS, arrays, strict=True):
        a = np.ascontiguousarray(a)
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(memoryview(a).cast("B"))
    return "sha256:" + h.hexdigest()


def _verified_path(path: Path) -> Path:
    return path.with_suffix(".verified")


def _stamp(path: Path) -> dict:
    st = path.stat()
    return {"size": st.st_size, "inode": st.st_ino, "mtime_ns": st.st_mtime_ns,
            "ctime_ns": st.st_ctime_ns}


def _trusted(path: Path, checksum: str) -> bool:
    """Whether ``path``, with ``checksum``, was verified and is untouched since."""
    try:
        record = json.loads(_verified_path(path).read_text())
        stamp = _stamp(path)
    except (OSError, ValueError):
        return False
    return (isinstance(record, dict) and record.get("checksum") == checksum
            and record.get("stamp") == stamp
            and record.get("recorded_ns", 0) - max(stamp["mtime_ns"], stamp["ctime_ns"])
            > RACY_NS)


def _remember(path: Path, checksum: str) -> None:
    """Record that ``path`` holds ``checksum`` now (best effort: a read-only cache skips it)."""
    from plenopiv.products.files import atomic_path

    try:
        record = {"checksum": checksum, "stamp": _stamp(path), "recorded_ns": time.time_ns()}
        with atomic_path(_verified_path(path)) as tmp:
            tmp.write_text(dumps(record))
    except Exception:  # noqa: BLE001 - a cache folder we cannot write: verify every time
        pass


def _weights_problem(path: Path, stored, arrays) -> str | None:
    """Why weights read from ``path`` may not be used (None: they may)."""
    if weights_checksum(arrays) != stored:
        return "its weights do not match their checksum (changed since written)"
    from plenopiv.errors import ReconstructionError
    from plenopiv.products.hdf5 import check_finite

    try:
        check_finite(arrays[2], "/data", path, ReconstructionError, product="weights cache")
    except ReconstructionError as exc:
        return str(exc)
    return None


def read_weights(path: Path, key: str, *, arrays: bool = True):
    """``(indptr, indices, data, pixel)`` of the cached weights of ``key``, or None.

    None where the file is missing, unreadable, holds another geometry's weights, was
    written before checksums, or may not be used (a newer schema, content that does not
    match its checksum, NaN or inf weights: each with a warning): the caller builds them
    again. The arrays are W in CSR (rows: the lit pixels ``pixel``, flat sensor indices) as
    :func:`write_weights` stored them. ``arrays=False``: True instead of the arrays, read only
    where the file is not known untouched since its last check.
    """
    import h5py

    try:
        with h5py.File(path, "r") as fh:
            if fh.attrs.get("key") != key:
                return None
            check_readable(path, "weights cache", fh.attrs.get("schema_version"),
                           fh.attrs.get("plenopiv_version"), _Refused)
            stored = fh.attrs.get("checksum")
            if stored is None:
                return None     # written before checksums: built again
            trusted = _trusted(path, stored)
            if trusted and not arrays:
                return True
            out = tuple(fh[name][()] for name in WEIGHT_DATASETS)
    except _Refused as exc:
        _warn(f"{exc}; its weights are built again")
        return None
    except (OSError, KeyError, ValueError):
        return None
    if not trusted:
        problem = _weights_problem(path, stored, out)
        if problem is not None:
            _warn(f"weights cache {str(path)!r} not used: {problem}; its weights are built "
                  "again")
            return None
        _remember(path, stored)
    return out if arrays else True


def weights_cached(path: Path, key: str) -> bool:
    """Whether ``path`` holds usable weights of ``key`` (:func:`read_weights`'s checks)."""
    return read_weights(path, key, arrays=False) is not None


def write_weights(path: Path, key: str, grid_key: str, indptr, indices, data, pixel) -> Path:
    """Store explicit weights (CSR and their pixels) under ``key``, atomically.

    The root attribute ``checksum`` (:func:`weights_checksum`) covers the four arrays.
    """
    from plenopiv.products.hdf5 import write_h5
    from plenopiv.products.provenance import make_provenance

    arrays = tuple(np.asarray(a) for a in (indptr, indices, data, pixel))
    checksum = weights_checksum(arrays)
    out = write_h5(path, dict(zip(WEIGHT_DATASETS, arrays, strict=True)),
                   attrs={"key": key, "grid": grid_key, "checksum": checksum},
                   kind="weights cache", compress=False,
                   provenance=make_provenance("weights cache", settings={"geometry": key}))
    _remember(Path(path), checksum)
    return out
