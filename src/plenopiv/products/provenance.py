"""Provenance and schema versions: what made each product, and which files belong together.

Every product records in its root attribute ``provenance`` (JSON) the package version, its
schema version (also the root attribute ``schema_version``) and the SHA-256 content hashes of
what made it: ``inputs`` (files: images, calibration, masks, preprocessing frames, products),
``settings`` (the camera and each experiment table as canonical JSON, :func:`json_hash`) and,
for a product made from products, their own provenance (``sources``). :func:`check_readable`
refuses a file of a newer or unknown schema or of a newer major version (a file without
``schema_version`` is schema 1, read as it is); :func:`differences` says what two records
disagree on, for the consumers that refuse products of other origins (docs/file-formats.md).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from plenopiv import __version__
from plenopiv.products.jsonio import to_json

__all__ = ["FIRST_SCHEMA", "PROVENANCE_ATTR", "SCHEMA_ATTR", "SCHEMA_VERSIONS",
           "check_readable", "differences", "json_hash", "make_provenance", "read_provenance",
           "schema_version", "short"]

#: Root attribute holding the schema version of a product (an integer).
SCHEMA_ATTR = "schema_version"
#: Root attribute holding the provenance of a product (JSON).
PROVENANCE_ATTR = "provenance"
#: The schema version each kind of file is written in. A reader refuses a newer one.
SCHEMA_VERSIONS = {"calibration": 2, "volume": 2, "vectors": 2, "tracks": 2,
                   "weights cache": 2, "response cache": 2, "batch summary": 2}
#: The schema version of the other files plenopiv writes (synthetic images and frames).
OTHER_SCHEMA = 2
#: A file written before schema versions were recorded is read as this one.
FIRST_SCHEMA = 1

#: How a message names each recorded input and setting.
WORDS = {
    "image": "image", "image_a": "first image", "image_b": "second image",
    "calibration": "calibration file", "dark": "dark frames", "white": "white frames",
    "background": "background frames", "mask_image": "[mask] image file",
    "mask_volume": "[mask] volume file", "volume_a": "first volume", "volume_b": "second volume",
    "vectors": "vectors", "focal_point": "focal-point image", "alignment": "alignment image",
    "ruler": "ruler image", "camera": "camera description", "volume": "[volume] grid",
    "reconstruction": "[reconstruction] settings", "particles": "[particles] settings",
    "preprocess": "[preprocess] settings", "mask": "[mask] table", "piv": "[piv] settings",
    "tracking": "[tracking] settings", "dt_s": "time between the exposures",
    "calibrate": "calibration options", "geometry": "weights geometry",
}


def schema_version(kind: str) -> int:
    """The schema version in which plenopiv writes files of ``kind``."""
    return SCHEMA_VERSIONS.get(kind, OTHER_SCHEMA)


def json_hash(obj: Any) -> str:
    """SHA-256 of ``obj`` as canonical JSON (sorted keys): equal settings, equal hashes.

    A camera or a table is hashed as resolved (units converted, defaults filled), so that a
    comment or a reordering of its TOML file is not a change.
    """
    return hashlib.sha256(to_json(obj).encode()).hexdigest()


def make_provenance(kind: str, *, inputs: Mapping[str, Any] | None = None,
                    settings: Mapping[str, Any] | None = None,
                    sources: Mapping[str, Mapping] | None = None) -> dict:
    """The provenance record of a product of ``kind`` (what :func:`write_h5` stores).

    Parameters
    ----------
    inputs : mapping
        Role -> content hash (:func:`plenopiv.products.files.file_identity`) of each input
        file; None values are left out.
    settings : mapping
        Name -> :func:`json_hash` of each setting that shaped the product.
    sources : mapping
        Role -> provenance of each product this one was made from.
    """
    return {"product": kind, "schema_version": schema_version(kind),
            "plenopiv_version": __version__,
            "inputs": {k: v for k, v in (inputs or {}).items() if v is not None},
            "settings": {k: v for k, v in (settings or {}).items() if v is not None},
            "sources": {k: dict(v) for k, v in (sources or {}).items() if v}}


def read_provenance(raw: Any) -> dict:
    """The provenance of a product's ``provenance`` attribute; {} when it has none."""
    if raw is None:
        return {}
    try:
        out = json.loads(raw)
    except (TypeError, ValueError):
        return {}
    return out if isinstance(out, dict) else {}


def _major(version: Any) -> int | None:
    try:
        return int(str(version).split(".")[0])
    except ValueError:
        return None


def check_readable(path: str | Path, kind: str, schema: Any, version: Any,
                   error: type[Exception]) -> int:
    """The schema version of a file of ``kind``; ``error`` if this plenopiv cannot read it.

    Refused, naming the file and both versions: a schema newer than :func:`schema_version`,
    one that is not a whole number ≥ 1, and a file of a newer major package version. A file
    without a schema version (``schema`` None) is schema :data:`FIRST_SCHEMA`.
    """
    shown = str(path)
    if hasattr(schema, "item"):          # a numpy scalar, as HDF5 attributes come back
        schema = schema.item()
    if schema is None:
        number = FIRST_SCHEMA
    else:
        try:
            number = int(schema)
            valid = number >= FIRST_SCHEMA and float(schema) == number \
                and not isinstance(schema, bool)
        except (TypeError, ValueError):
            valid = False
        if not valid:
            raise error(f"{kind} file {shown!r} has an unknown schema version {schema!r}: "
                        f"this plenopiv ({__version__}) reads {kind} files of schema "
                        f"{FIRST_SCHEMA} to {schema_version(kind)}")
    if number > schema_version(kind):
        raise error(f"{kind} file {shown!r} is of schema version {number}, newer than the "
                    f"{schema_version(kind)} this plenopiv ({__version__}) reads (written by "
                    f"plenopiv {version}): read it with a newer plenopiv, or make it again")
    mine, theirs = _major(__version__), _major(version)
    if version is not None and (theirs is None or (mine is not None and theirs > mine)):
        raise error(f"{kind} file {shown!r} was written by plenopiv {version}, a newer major "
                    f"version than this one ({__version__}): read it with plenopiv "
                    f"{theirs if theirs is not None else '?'}.x, or make it again")
    return number


def short(value: Any) -> str:
    """A hash shortened for a message: its first 12 characters, and a ``:/dataset`` it names."""
    digest, sep, dataset = str(value).partition(":")
    return (digest if len(digest) <= 16 else f"{digest[:12]}…") + sep + dataset


def differences(a: Mapping, b: Mapping, *, ignore: Iterable[str] = (),
                sections: Iterable[str] = ("inputs", "settings"),
                form: str = "{word} ({a} ≠ {b})") -> list[str]:
    """What two provenance records disagree on, in words (those both record).

    An input or setting that only one of them records (a product of schema 1 records none)
    is not compared. ``form`` phrases each: ``word`` names it, ``a`` and ``b`` are the two
    hashes, shortened.
    """
    skip = set(ignore)
    out = []
    for section in sections:
        x, y = a.get(section) or {}, b.get(section) or {}
        for key in sorted(set(x) & set(y) - skip):
            if x[key] != y[key]:
                out.append(form.format(word=WORDS.get(key, key), a=short(x[key]),
                                       b=short(y[key])))
    return out


def mismatched_inputs(record: Mapping, expected: Mapping[str, tuple[str, str]]) -> list[str]:
    """The inputs of ``record`` that are not the files ``expected`` names, in words.

    ``expected``: role -> ``(content hash, the file as the user named it)``. A role the record
    does not hold is not compared.
    """
    inputs = record.get("inputs") or {}
    out = []
    for role, (digest, shown) in expected.items():
        if role in inputs and inputs[role] != digest:
            out.append(f"its {WORDS.get(role, role)} is {short(inputs[role])}, not "
                       f"{shown!r} ({short(digest)})")
    return out
