"""JSON text of summaries and configs: numpy values allowed, NaN and infinities as null."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np


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


def to_json(obj: Any) -> str:
    """Valid JSON text of ``obj``: numpy arrays and scalars allowed, NaN and ±inf as null.

    Never the bare ``NaN`` that JSON parsers reject.
    """
    return json.dumps(finite_json(obj), default=json_default, sort_keys=True, allow_nan=False)
