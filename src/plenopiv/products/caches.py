"""The on-disk caches and their keys: the chain's response and the explicit weights.

The weights are built or loaded by :func:`plenopiv.reconstruction.build.cached_weights`;
this module holds how both caches are stored.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from plenopiv.piv.response import RESPONSE_VERSION, Response
from plenopiv.products.jsonio import dumps


def response_key(*parts) -> str:
    """A stable hash of what a response depends on (any JSON-able parts)."""
    h = hashlib.sha256()
    h.update(dumps([RESPONSE_VERSION, *parts], sort_keys=True, default=str).encode())
    return h.hexdigest()


def cached_response(path: Path | None, key: str, compute) -> tuple[Response | None, bool]:
    """The response stored at ``path`` under ``key``, else ``compute()`` (saved there).

    ``compute()`` returning None is not saved. Returns ``(response, from_cache)``; ``path``
    None disables the cache.
    """
    if path is not None and path.exists():
        try:
            d = json.loads(path.read_text())
            if d.get("key") == key:
                return Response.from_dict(d), True
        except (OSError, ValueError, KeyError, TypeError):
            pass   # unreadable or another version: measure again
    resp = compute()
    if path is not None and resp is not None:
        from plenopiv.products.files import atomic_path

        with atomic_path(path) as tmp:
            tmp.write_text(dumps({"key": key, **resp.to_dict()}))
    return resp, False


# --------------------------------------------------------------------------------------------
# the weights cache
# --------------------------------------------------------------------------------------------


def weights_cache_path(cache_dir: str | Path, key: str) -> Path:
    """The file of the explicit weights of geometry ``key`` in ``cache_dir``."""
    return Path(cache_dir) / f"weights-{key[:24]}.h5"


def weights_cached(path: Path, key: str) -> bool:
    """Whether ``path`` holds the weights of ``key`` (the key inside the file is checked)."""
    import h5py

    try:
        with h5py.File(path, "r") as fh:
            return fh.attrs.get("key") == key
    except (OSError, KeyError, ValueError):
        return False


def read_weights(path: Path, key: str):
    """``(indptr, indices, data, pixel)`` of the cached weights of ``key``, or None.

    None where the file is missing, unreadable, or holds another geometry's weights: the
    caller builds them again. The arrays are W in CSR (rows: the lit pixels ``pixel``, flat
    sensor indices) as :func:`write_weights` stored them.
    """
    import h5py

    try:
        with h5py.File(path, "r") as fh:
            if fh.attrs.get("key") != key:
                return None
            return (fh["/indptr"][()], fh["/indices"][()], fh["/data"][()],
                    fh["/pixel"][()])
    except (OSError, KeyError, ValueError):
        return None


def write_weights(path: Path, key: str, grid_key: str, indptr, indices, data, pixel) -> Path:
    """Store explicit weights (CSR and their pixels) under ``key``, atomically."""
    from plenopiv.products.hdf5 import write_h5

    return write_h5(path, {"/indptr": indptr, "/indices": indices, "/data": data,
                           "/pixel": pixel}, attrs={"key": key, "grid": grid_key},
                    kind="weights cache", compress=False)
