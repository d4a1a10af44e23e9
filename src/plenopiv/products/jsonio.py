"""JSON text of summaries, configs and keys: strict JSON, numpy values allowed, NaN as null.

Every JSON that plenopiv writes or prints goes through :func:`dumps` (or :func:`to_json`,
:func:`dump`): command summaries (``--json``), the batch's ``summary.json``, the resolved
configs stored in products, caches and the validation reports. Non-finite floats (NaN,
±inf) become ``null``, so that the text is strict JSON (RFC 8259), never holding the bare
``NaN`` or ``Infinity`` tokens that strict parsers (JavaScript's ``JSON.parse``, jq, Go)
reject. Text of finite values is what :func:`json.dumps` writes with the same options, so
keys hashed from it do not change.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import numpy as np

__all__ = ["dump", "dumps", "finite_json", "json_default", "to_json"]


def json_default(o: Any):
    """``default=`` of :func:`json.dumps`: numpy arrays and scalars, and paths, as JSON."""
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


def dumps(obj: Any, *, indent: int | str | None = None, sort_keys: bool = False,
          default: Callable[[Any], Any] | None = None,
          separators: tuple[str, str] | None = None) -> str:
    """Strict JSON text of ``obj``: :func:`json.dumps` with NaN and ±inf as ``null``.

    Parameters
    ----------
    obj : object
        Dicts, lists, tuples, numbers, strings, None, NumPy arrays and scalars, paths.
    indent, sort_keys, separators
        As for :func:`json.dumps`.
    default : callable, optional
        Converts what JSON cannot hold otherwise (``str``, say), after numpy values and paths
        (:func:`json_default`); its result is made finite too. Without it such an object
        raises ``TypeError``.

    Examples
    --------
    >>> dumps({"gain": float("nan"), "rms": np.float32(0.5), "n": np.int64(3)})
    '{"gain": null, "rms": 0.5, "n": 3}'
    """
    def convert(o):
        try:
            return finite_json(json_default(o))
        except TypeError:
            if default is None:
                raise
            return finite_json(default(o))

    return json.dumps(finite_json(obj), default=convert, sort_keys=sort_keys, indent=indent,
                      separators=separators, allow_nan=False)


def dump(obj: Any, fh: IO[str], **kwargs) -> None:
    """Write :func:`dumps` of ``obj`` to the open text file ``fh`` (same keywords)."""
    fh.write(dumps(obj, **kwargs))


def to_json(obj: Any) -> str:
    """Strict JSON text of ``obj`` with sorted keys (the ``--json`` summaries, configs).

    Numpy arrays and scalars allowed, NaN and ±inf as null: never the bare ``NaN`` that
    JSON parsers reject.
    """
    return dumps(obj, sort_keys=True)
