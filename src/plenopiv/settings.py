"""The one strict base of every settings type and every TOML model, and its error messages.

A stage owns its settings as a frozen, validated dataclass (:func:`settings`); the experiment
file's tables are those dataclasses themselves (:mod:`plenopiv.config.experiment`), so a field
is declared once, with its default, its bounds and its meaning. TOML models that are not a
stage's settings derive from :class:`StrictModel`. Both refuse unknown keys and non-finite
numbers; :func:`format_validation_error` turns pydantic's errors into one line per key that
names the key as the user wrote it.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError
from pydantic.dataclasses import dataclass as _pydantic_dataclass
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined, to_json

from plenopiv.errors import ConfigError

__all__ = ["STRICT", "StrictModel", "as_dict", "fields_of", "format_validation_error", "settings",
           "validate_table"]

STRICT = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)
"""Unknown keys, NaN or infinite numbers and values of another type are refused.

Strict types: a boolean is not a number, a number is not a text and a text is not a number;
an integer is a number. TOML tables are validated as JSON (:func:`validate_table`), where an
array stands for a tuple. Frozen: see :func:`settings`.
"""


class StrictModel(BaseModel):
    """Base of the TOML models: :data:`STRICT`, frozen."""

    model_config = ConfigDict(**STRICT, frozen=True)


def settings(cls):
    """Make ``cls`` a frozen dataclass validated on construction, from Python or TOML.

    Bounds are written on the fields (``Field(0.5, ge=0, lt=1)``); checks that involve several
    fields go in ``__post_init__`` and raise ``ValueError`` naming the field.
    """
    return _pydantic_dataclass(frozen=True, config=STRICT)(cls)


def validate_table(model, table: dict, what: str):
    """Validate a TOML table (a dict of TOML values) against ``model``, types strictly.

    The table is validated as JSON, so that arrays stand for tuples while a boolean stays no
    number (a TOML date becomes a text, which no number key takes). A value of the wrong type
    or range raises pydantic's ``ValidationError`` (the caller names the file with
    :func:`format_validation_error`).
    """
    try:
        text = to_json(table, inf_nan_mode="constants")   # NaN stays NaN: refused by name
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{what}: {exc}") from None
    return model.model_validate_json(text)


def as_dict(obj) -> dict:
    """The fields of a settings dataclass or a TOML model, as plain Python values."""
    if isinstance(obj, BaseModel):
        return obj.model_dump()
    return dataclasses.asdict(obj)


# --------------------------------------------------------------------------------------------
# error messages
# --------------------------------------------------------------------------------------------

_BRANCH_WORDS = {"float": "a number", "int": "an integer", "str": "a string",
                 "bool": "true or false", "dict": "a table", "none": "nothing",
                 "list": "a list", "tuple": "a list"}

_UNKNOWN_KEY = ("extra_forbidden", "unexpected_keyword_argument")


def _branch_text(part: str) -> str | None:
    """What a pydantic union branch in an error location expects; None for a field name."""
    if part in _BRANCH_WORDS:
        return _BRANCH_WORDS[part]
    if "[" in part:
        head, _, inner = part.partition("[")
        if head in ("tuple", "list"):
            items = [t.strip() for t in inner.rstrip("]").split(",") if t.strip()]
            if head == "tuple" and items and "..." not in items:
                kinds = {_BRANCH_WORDS.get(t, t) for t in items}
                word = "numbers" if kinds <= {"a number", "an integer"} else "values"
                return f"a list of {len(items)} {word}"
            return "a list"
        return part
    return None


def fields_of(model) -> dict[str, FieldInfo] | None:
    """``{name: FieldInfo}`` of a TOML model or a settings dataclass; None for anything else.

    A plain dataclass (``PIVSettings``) gets FieldInfos made from its annotations and defaults,
    so that the documentation and the error messages read every table the same way.
    """
    if not isinstance(model, type):
        return None
    fields = getattr(model, "model_fields", None)
    if fields is None:
        fields = getattr(model, "__pydantic_fields__", None)
    if fields is None and dataclasses.is_dataclass(model):
        hints = typing.get_type_hints(model)
        fields = {f.name: FieldInfo.from_annotated_attribute(
            hints[f.name], PydanticUndefined if f.default is dataclasses.MISSING else f.default)
            for f in dataclasses.fields(model)}
    return fields if isinstance(fields, dict) else None


def _submodel(model, loc: list[str]):
    """The model or settings class at ``loc`` inside ``model`` (None where none is)."""
    current: Any = model
    for part in loc:
        fields = fields_of(current)
        if fields is None or part not in fields:
            return None
        ann = getattr(fields[part], "annotation", None)
        args = getattr(ann, "__args__", None)
        if args:
            ann = next((a for a in args if fields_of(a) is not None), ann)
        current = ann
    return current if fields_of(current) is not None else None


def _valid_keys(model, loc: list[str]) -> list[str]:
    sub = _submodel(model, loc) if loc else model
    return sorted(fields_of(sub)) if sub is not None else []


def _location(raw) -> tuple[list[str], str | None, int]:
    """The key path of an error location, the union branch it stopped at, the parts read."""
    fields: list[str] = []
    branch = None
    for part in raw:
        b = _branch_text(part) if isinstance(part, str) else None
        if b is not None:
            branch = b
            break
        fields.append(str(part) if isinstance(part, str) else f"[{part}]")
    loc: list[str] = []
    for f in fields:       # list indices attach to the key before them: voxel_mm[1]
        if f.startswith("[") and loc:
            loc[-1] += f
        else:
            loc.append(f)
    return loc, branch, len(fields)


def format_validation_error(exc: ValidationError, what: str, model) -> str:
    """Turn a pydantic error into lines that name the key, the value and the expectation.

    A key that accepts several forms (``voxel_mm``: a number or a list of 3) gets one line
    naming the value and the forms, not one line per form. A check of a whole table (a
    settings class's ``__post_init__``) is reported under the table's name.
    """
    lines: list[str] = []
    unions: dict[str, tuple[Any, list[str]]] = {}
    for err in exc.errors():
        raw = list(err["loc"])
        loc, branch, n = _location(raw)
        section = ".".join(loc[:-1])
        key = loc[-1] if loc else "?"
        where = f"[{section}] {key}" if section else key
        kind = err["type"]
        if branch is not None:
            value, forms = unions.setdefault(where, (None, []))
            if raw[n] == raw[-1] or value is None:
                value = err.get("input") if raw[n] == raw[-1] else value
            if branch not in forms:
                forms.append(branch)
            unions[where] = (value, forms)
            continue
        if kind in _UNKNOWN_KEY:
            valid = _valid_keys(model, loc[:-1])
            lines.append(f"unknown key {where!s}; valid keys here: {', '.join(valid)}")
        elif kind == "missing" or kind == "missing_argument":
            if _submodel(model, loc) is not None:
                lines.append(f"missing section [{'.'.join(loc)}]")
            else:
                lines.append(f"missing key {where}")
        elif kind == "value_error" and _submodel(model, loc) is not None:
            msg = err["msg"].removeprefix("Value error, ")
            table = ".".join(loc)
            if msg.startswith("unknown key "):
                lines.append(f"unknown key [{table}] {msg.removeprefix('unknown key ')}")
            else:
                lines.append(f"[{table}] {msg}")
        else:
            lines.append(f"{where} = {err.get('input')!r}: {err['msg'].lower()}")
    for where, (value, forms) in unions.items():
        lines.append(f"{where} = {value!r}: expected {' or '.join(forms)}")
    return f"{what}: " + "; ".join(lines)
