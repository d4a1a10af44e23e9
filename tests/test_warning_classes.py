"""Every warning plenopiv gives is a PlenopivWarning, so that every consumer shows it as one.

The command line prints them as ``warning: ...`` lines, and a batch worker relays them to the
command as its pair's warnings (docs/batch.md). A plain ``UserWarning`` from the library would
reach a batch's terminal as a raw Python warning with a source line instead. The test reads
every ``warnings.warn`` call of the package and checks its category.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import plenopiv
import plenopiv.lightfield  # noqa: F401  (defines a subclass)
from plenopiv.errors import PlenopivWarning

SRC = Path(plenopiv.__file__).parent


def _subclass_names(cls) -> set[str]:
    return {cls.__name__}.union(*(_subclass_names(c) for c in cls.__subclasses__()))


def _warn_calls() -> list[tuple[str, ast.Call]]:
    calls = []
    for path in sorted(SRC.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr == "warn" and isinstance(node.func.value, ast.Name)
                    and node.func.value.id == "warnings"):
                calls.append((f"{path.relative_to(SRC)}:{node.lineno}", node))
    return calls


CALLS = _warn_calls()


def test_the_package_is_read():
    assert len(CALLS) >= 20


@pytest.mark.parametrize("where, call", CALLS, ids=[w for w, _ in CALLS])
def test_every_warning_is_a_plenopiv_warning(where, call):
    category = call.args[1] if len(call.args) > 1 else next(
        (k.value for k in call.keywords if k.arg == "category"), None)
    assert category is not None, f"{where}: warnings.warn without a category (a UserWarning)"
    name = (category.id if isinstance(category, ast.Name)
            else category.attr if isinstance(category, ast.Attribute) else None)
    assert name in _subclass_names(PlenopivWarning), (
        f"{where}: category {ast.unparse(category)}, not PlenopivWarning or a subclass")
