"""The experiment file: its tables declared once, on :class:`Experiment`, and read back whole."""

from __future__ import annotations

import dataclasses

import pytest

from plenopiv.config.experiment import TABLES, Experiment, ExperimentFile, experiment_from_dict
from plenopiv.errors import ConfigError

VOLUME = {"x_mm": [-1.0, 1.0], "y_mm": [-1.0, 1.0], "z_mm": [-1.0, 1.0], "voxel_mm": 0.25}


def test_the_file_takes_exactly_the_tables_of_the_experiment_with_their_defaults():
    declared = {f.name: f.default for f in dataclasses.fields(Experiment) if f.name in TABLES}
    assert set(declared) == set(TABLES)
    assert set(ExperimentFile.model_fields) == set(TABLES) | {"camera", "volume"}
    for name, default in declared.items():
        assert ExperimentFile.model_fields[name].default == default, name


def test_a_minimal_file_gives_every_table_its_default():
    exp = experiment_from_dict({"camera": "small_test", "volume": VOLUME})
    for name in TABLES:
        assert getattr(exp, name) == next(
            f.default for f in dataclasses.fields(Experiment) if f.name == name), name


@pytest.mark.parametrize("table", [t for t in TABLES if t != "preprocess"])
def test_every_table_read_from_its_resolved_form_is_the_same(table):
    """The resolved configuration written into products reads back to the same settings."""
    exp = experiment_from_dict({"camera": "small_test", "volume": VOLUME})
    resolved = exp.to_dict()
    again = experiment_from_dict({"camera": "small_test", "volume": VOLUME,
                                  table: resolved[table]})
    assert getattr(again, table) == getattr(exp, table)


def test_an_unknown_table_is_refused_naming_it_and_the_known_ones():
    with pytest.raises(ConfigError, match="pivv") as err:
        experiment_from_dict({"camera": "small_test", "volume": VOLUME, "pivv": {}})
    assert "piv" in str(err.value)
