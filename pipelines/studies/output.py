"""Writing a validation study's outputs: PNG figures, Markdown and JSON, one set of conventions.

Every study computes plain data (dicts, lists, arrays) and renders it through these helpers, so
the figure format, the JSON dialect and the Markdown tables are the same in all reports:

- figures: PNG at 110 dpi, tight bounding box, drawn with the non-interactive Agg backend and
  closed once written;
- JSON: indented by one space, NaN and ±inf written as ``null``
  (:func:`plenopiv.products.jsonio.dumps`), never the bare ``NaN`` that JSON parsers reject;
- every file is written atomically (:func:`plenopiv.products.files.atomic_path`): a reader never
  sees half a report.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from plenopiv.products.files import atomic_path
from plenopiv.products.jsonio import dumps

#: Resolution of every validation figure, dots per inch.
FIGURE_DPI = 110


def pyplot():
    """``matplotlib.pyplot`` on the non-interactive Agg backend (figures go to files only)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def savefig(fig, path: str | Path) -> Path:
    """Write ``fig`` as a PNG at :data:`FIGURE_DPI` to ``path`` (atomically) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=FIGURE_DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically; return the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def write_json(path: str | Path, obj: Any, *,
               default: Callable[[Any], Any] | None = None) -> Path:
    """Write ``obj`` as JSON (indent 1, non-finite floats as ``null``) to ``path``.

    Parameters
    ----------
    path : path
        Output file.
    obj : object
        Dicts, lists, numbers, strings, NumPy arrays and scalars.
    default : callable, optional
        Converts what JSON cannot hold otherwise (``str`` for paths and the like); without it
        such an object raises ``TypeError``.
    """
    return write_text(path, dumps(obj, indent=1, default=default))


def fmt(value, spec: str, missing: str = "–") -> str:
    """``format(value, spec)``, or ``missing`` for None and non-finite values."""
    if value is None or not np.isfinite(value):
        return missing
    return format(value, spec)


def table_header(columns: Sequence[str]) -> list[str]:
    """The two header lines of a Markdown table with ``columns``."""
    return ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]


def table_row(cells: Iterable[Any]) -> str:
    """One Markdown table row of ``cells`` (already formatted, or turned into text by str)."""
    return "| " + " | ".join(str(c) for c in cells) + " |"


def table(columns: Sequence[str], rows: Iterable[Iterable[Any]]) -> list[str]:
    """A whole Markdown table: header lines and one line per row."""
    return [*table_header(columns), *(table_row(r) for r in rows)]


def section(title: str, level: int = 2) -> list[str]:
    """A Markdown heading followed by a blank line."""
    return ["#" * level + " " + title, ""]


def pair_study_main(doc: str, run: Callable, page: str) -> None:
    """The command line of a study over groups of pairs (``run(out, work) -> {"groups",
    "seconds"}``): ``--out`` (default docs/validation) and ``--work`` (default a temporary
    folder); prints the pairs, the time and the page ``page`` written."""
    import argparse
    import tempfile

    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--work", default=None, help="scratch folder (default: a temporary one)")
    a = ap.parse_args()
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix=f"{Path(page).stem}_"))
    r = run(a.out, work)
    print(f"{sum(len(g) for g in r['groups'].values())} pairs in {r['seconds']} s: "
          f"{a.out}/{page}")
