"""docs/configuration.md documents every key of the camera and experiment TOML files, and no other.

The keys are read from the pydantic models the loaders validate against, walked recursively
(sub-tables and arrays of tables); the page's keys from its "## ... keys" sections, one
``### `[table]` `` heading per table and one ``| `key` |`` row per key.
"""

from __future__ import annotations

import re
import types
import typing

from conftest import REPO
from plenopiv.settings import fields_of

PAGE = REPO / "docs" / "configuration.md"


def config_models():
    """The models of the two TOML files: the one place this test knows where they live.

    Returns ``{file: root model}`` and ``{(file, table): model}`` for the tables a root model
    types as a plain dict (the experiment's ``[volume]``), and the keys whose dict branch is
    not a table of its own (the experiment's ``camera``: a name, a path or the camera's keys).
    """
    from plenopiv.camera.grid import _VolumeCfg
    from plenopiv.camera.model import _CameraCfg
    from plenopiv.config.experiment import ExperimentFile

    return ({"camera": _CameraCfg, "experiment": ExperimentFile},
            {("experiment", "volume"): _VolumeCfg}, {("experiment", "camera")})


def _table_model(annotation):
    """The model of a table (or of an array of tables) the annotation holds, else None."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        inner = [a for a in typing.get_args(annotation) if a is not type(None)]
        annotation = inner[0] if len(inner) == 1 else None
    if typing.get_origin(annotation) is list:
        (annotation,) = typing.get_args(annotation)
    if fields_of(annotation) is not None:
        return annotation
    return None


def model_keys() -> dict[str, set[str]]:
    """``{file: {"table.key", ...}}`` of every leaf key of the models, tables walked."""
    roots, dict_tables, leaves_only = config_models()
    out = {}
    for file, root in roots.items():
        keys: set[str] = set()
        stack = [("", root)]
        while stack:
            table, model = stack.pop()
            for key, info in fields_of(model).items():
                path = f"{table}.{key}" if table else key
                sub = dict_tables.get((file, path)) or _table_model(info.annotation)
                if sub is not None and (file, path) not in leaves_only:
                    stack.append((path, sub))
                else:
                    keys.add(path)
        out[file] = keys
    return out


def documented_keys(text: str) -> dict[str, set[str]]:
    """``{file: {"table.key", ...}}`` of the key rows of the page's key sections."""
    out: dict[str, set[str]] = {}
    file = table = None
    for line in text.splitlines():
        h2 = re.match(r"^## (Camera|Experiment) file keys", line)
        if h2:
            file, table = h2.group(1).lower(), ""
            out[file] = set()
            continue
        if line.startswith("## "):
            file = None
            continue
        h3 = re.match(r"^### (?:Top level|`\[\[?([\w.]+)\]\]?`)", line)
        if file and h3:
            table = h3.group(1) or ""
            continue
        row = re.match(r"^\| `(\w+)` \|", line)
        if file and row:
            out[file].add(f"{table}.{row.group(1)}" if table else row.group(1))
    return out


def test_every_model_key_is_documented_and_no_other():
    models, docs = model_keys(), documented_keys(PAGE.read_text())
    assert set(docs) == {"camera", "experiment"}, "configuration.md lacks a key section"
    for file in models:
        missing = sorted(models[file] - docs[file])
        unknown = sorted(docs[file] - models[file])
        assert not missing, f"{file} keys missing from docs/configuration.md: {missing}"
        assert not unknown, f"docs/configuration.md documents unknown {file} keys: {unknown}"


#: A key's unit suffix and the unit its row must give.
SUFFIX_UNITS = {"mm": "mm", "um": "µm", "s": "s", "rad": "rad", "gb": "GB", "vox": "voxels",
                "cells": "resolution cells"}


def test_units_in_the_key_names_match_the_unit_column():
    rows = re.findall(r"^\| `(\w+)` \| ([^|]+) \|", PAGE.read_text(), re.M)
    assert rows
    for key, unit in rows:
        suffix = key.rsplit("_", 1)[-1] if "_" in key else None
        if suffix in SUFFIX_UNITS:
            assert unit.strip() == SUFFIX_UNITS[suffix], (key, unit)


def test_the_generated_tables_are_current():
    """The page's tables are what ``docs/gen_configuration.py`` makes of the models now."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("gen_configuration",
                                                  REPO / "docs" / "gen_configuration.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    assert gen.main(["--check"]) == 0, "run: python docs/gen_configuration.py"
