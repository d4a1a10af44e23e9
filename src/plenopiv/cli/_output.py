"""Summaries for people: ``key: value`` lines with numbers to 4 significant digits."""

from __future__ import annotations

import math

import numpy as np


def _fmt(value) -> str:
    """A value for people: numbers to 4 significant digits, numpy scalars as numbers.

    Lists and small dicts on one line.
    """
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, bool) or value is None:
        return str(value).lower() if isinstance(value, bool) else "-"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        if value != 0 and (abs(value) >= 1e6 or abs(value) < 1e-3):
            return f"{value:.3e}"
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    if isinstance(value, dict):
        return ", ".join(f"{k} {_fmt(v)}" for k, v in value.items())
    return str(value)


def _print_lines(summary: dict, indent: str = "") -> None:
    """``key: value`` lines; a dict of dicts or lists of dicts as an indented block."""
    for k, v in summary.items():
        if isinstance(v, dict) and (any(isinstance(x, (dict, list)) for x in v.values())
                                    or len(_fmt(v)) > 90):
            print(f"{indent}{k}:")
            _print_lines(v, indent + "  ")
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            print(f"{indent}{k}:")
            for x in v:
                print(f"{indent}  - {_fmt(x)}")
        else:
            print(f"{indent}{k}: {_fmt(v)}")
