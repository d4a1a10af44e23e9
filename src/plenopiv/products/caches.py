"""The on-disk cache of the chain's response, with its key.

The weights cache is :func:`plenopiv.reconstruction.select.cached_weights`.
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

