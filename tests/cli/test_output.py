"""What the command prints for people: short numbers, a table for ``run``, help for every
option, progress on a terminal only; the data-folder option of ``validate letters``; the
numba cache folder; the third-party data skip."""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys

import numpy as np
import pytest

import conftest
from plenopiv import cli
from plenopiv.cli import _print_human, build_parser, main
from plenopiv.cli._output import _fmt
from plenopiv.cli._progress import _StageBar


def test_numbers_are_short_and_plain():
    assert _fmt(np.float64(2.918e-14)) == "2.918e-14"
    assert _fmt(99.99216930370551) == "99.99"
    assert _fmt(np.float32(0.23903292629371992)) == "0.239"
    assert _fmt([0.23903292629371992, np.float64(0.0974), 0.8726439202612346]) == \
        "[0.239, 0.0974, 0.8726]"
    assert _fmt({"a": np.int64(3), "b": np.float64(1e-9)}) == "a 3, b 1.000e-09"
    assert _fmt(True) == "true" and _fmt(None) == "-" and _fmt(float("nan")) == "nan"


def test_human_output_has_no_numpy_reprs(capsys):
    summary = {"command": "calibrate", "image_distance_mm": np.float64(199.99216930370551),
               "rms_residual_px": np.float64(2.918e-14),
               "offset_um": [np.float64(0.12345678), np.float64(-0.5)],
               "methods": {"focal_point": {"image_distance_mm": np.float64(200.0012345),
                                           "std_mm": np.float64(0.00123456)}},
               "seconds": 3.14159}
    _print_human(summary)
    out = capsys.readouterr().out
    assert "np." not in out and "199.99216" not in out
    assert "image_distance_mm: 200" in out and "rms_residual_px: 2.918e-14" in out
    assert "focal_point: image_distance_mm 200, std_mm 0.001235" in out


def test_run_prints_a_table_with_units(capsys):
    summary = {"command": "run", "out": "out", "weights_from_cache": False, "weights_s": 1.234,
               "n_jobs": 3, "n_done": 1, "n_skipped": 1, "n_failed": 1, "seconds": 12.3456,
               "cluster": "local", "n_workers": 2, "threads_per_worker": 1,
               "summary_path": "out/batch_summary.json",
               "results": [
                   {"name": "p1", "status": "done", "seconds": 5.678, "start": 1.7e9,
                    "end": 1.7e9 + 5, "result": {"valid_fraction": 0.9612,
                                                 "n_particles_a": 251}},
                   {"name": "p2", "status": "skipped", "seconds": 0.0, "result": None},
                   {"name": "p3", "status": "failed", "seconds": 0.1, "result": None,
                    "error_type": "PIVError", "error": "windows larger than the volume"}]}
    _print_human(summary)
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].split() == ["pair", "status", "valid", "particles", "A", "time", "(s)"]
    assert lines[1].split() == ["p1", "done", "96%", "251", "5.7"]
    assert "1.7e" not in out and "start" not in out            # no epoch times
    assert "3 pairs: 1 done, 1 skipped, 1 failed in 12.3 s" in out
    assert "p3: PIVError: windows larger than the volume" in out
    assert "weights: built in 1.2 s" in out


def test_every_option_has_help():
    missing = []

    def walk(parser, name):
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for sub, sp in a.choices.items():
                    walk(sp, f"{name} {sub}")
            elif not a.help:
                missing.append(f"{name} {'/'.join(a.option_strings) or a.dest}")
    walk(build_parser(), "plenopiv")
    assert not missing, missing


def _parsers(parser, name="plenopiv"):
    """Every parser of the command, with its name ("plenopiv simulate pair")."""
    yield name, parser
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for sub, sp in a.choices.items():
                yield from _parsers(sp, f"{name} {sub}")


def test_every_help_ends_with_one_example_that_parses(capsys):
    names = []
    for name, parser in _parsers(build_parser()):
        names.append(name)
        lines = [ln for ln in parser.format_help().splitlines() if ln.strip()]
        assert lines[-1].startswith(f"example: {name} "), (name, lines[-1])
        assert sum("example:" in ln for ln in lines) == 1, name
        words = lines[-1].split()[2:]
        args = build_parser().parse_args(words)             # the example is a valid command
        assert args.func is not None
    assert {"plenopiv compare", "plenopiv piv", "plenopiv simulate pair",
            "plenopiv simulate"} <= set(names) and len(names) >= 17


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_stage_bar_only_on_a_terminal(monkeypatch, capsys):
    bar = _StageBar("demo", {"a": 1, "b": 3}, quiet=False)      # stderr is captured: no tty
    bar("a", 0.5)
    bar("b", 1.0)
    bar.close()
    assert capsys.readouterr().err == ""
    term = _Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    with _StageBar("demo", {"volume A": 1, "volume B": 1, "piv": 2}, quiet=False) as bar:
        bar("volume A: mart", 0.5)
        assert bar.bar.n == 12
        bar("volume B: mart", 0.5)
        assert bar.bar.n == 37
        bar("volume A: mart", 0.0)                                 # never goes back
        assert bar.bar.n == 37
        bar("piv pass 1/3", 1 / 3)                                 # counts for "piv"
        assert bar.bar.n == 66
    text = term.getvalue()
    assert "demo: volume B: mart" in text and "demo: piv pass 1/3" in text
    with _StageBar("demo", {"a": 1}, quiet=True) as bar:
        bar("a", 1.0)
    assert "demo: a" not in term.getvalue().split("demo: piv pass 1/3")[-1]


def test_pair_progress_names_each_volume_and_pass():
    """process_pair reports the weights, each volume and each PIV pass, in order."""
    from plenopiv.calibration.model import Calibration
    from plenopiv.camera.model import load_camera
    from plenopiv.config.experiment import Experiment, ImagesConfig, OutputConfig
    from plenopiv.piv.settings import PIVSettings
    from plenopiv.synthetic.flows import Uniform
    from plenopiv.synthetic.seeding import SeedingBox, simulate_pair
    from plenopiv.workflow.pair import process_pair
    from plenopiv.workflow.vortex_case import VortexCase, aligned_grid

    cam = load_camera("small_m1")
    grid = aligned_grid(cam, VortexCase(depth=1.5e-3, lateral_fill=0.4))
    box = SeedingBox(tuple(grid.bounds[0]), tuple(grid.bounds[1]), (-1.5e-3, 1.5e-3))
    pair = simulate_pair(cam, Uniform((0.125, 0.0, 0.0)), dt=1e-3, box=box, n_particles=30,
                         rng=np.random.default_rng(3), rays_per_particle=256)
    exp = Experiment(camera=cam, volume=grid, piv=PIVSettings(windows=[(12, 12, 12)], passes=2),
                     images=ImagesConfig(dt_s=1e-3), output=OutputConfig(weights_cache=""))
    seen = []
    process_pair(Calibration.from_camera(cam), pair.image_a, pair.image_b, exp,
                 progress=lambda stage, f: seen.append((stage, f)))
    stages = [s for s, _ in seen]
    assert stages[0] == "weights"
    a = [i for i, s in enumerate(stages) if s.startswith("volume A")]
    b = [i for i, s in enumerate(stages) if s.startswith("volume B")]
    p = [i for i, s in enumerate(stages) if s.startswith("piv pass")]
    assert a and b and p and max(a) < min(b) and max(b) < min(p)
    assert stages[p[-1]] == "piv pass 2/2"
    assert all(0.0 <= f <= 1.0 for _, f in seen)
    # the demo's bar over these stages only moves forward and ends at the PIV
    with _StageBar("demo", {"weights": 1, "volume A": 1, "volume B": 1, "piv": 1},
                   quiet=True) as bar:
        last = 0
        for stage, f in seen:
            bar(stage, f)
            assert bar.bar.n >= last
            last = bar.bar.n
    assert last == 100


@pytest.mark.study
def test_validate_letters_names_a_missing_data_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PLENOPIV_REPO", str(conftest.REPO))     # the study is in pipelines/
    missing = tmp_path / "no_data"
    code = main(["validate", "letters", "--out", str(tmp_path / "out"), "--data", str(missing)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ")
    assert str(missing) in err and "plenoptomos" in err and "--data" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.study
def test_letters_data_folder_may_be_the_parent_or_the_set(monkeypatch):
    from pipelines.studies import letters_data as letters

    # skipped on a clone without the data, a failure under CI (conftest.shared_data_path)
    parent = conftest.shared_data_path(letters.DATA_NAME).parent
    assert letters.find_data_dir(parent) == parent / letters.DATA_NAME
    assert letters.find_data_dir(parent / letters.DATA_NAME) == parent / letters.DATA_NAME
    monkeypatch.setenv("PLENOPIV_DATA", str(parent))
    assert letters.find_data_dir() == parent / letters.DATA_NAME


def test_third_party_data_missing_is_a_failure(tmp_path, monkeypatch):
    monkeypatch.setattr(conftest, "SHARED_DATA", tmp_path / "absent")
    for ci in ("", "true"):
        monkeypatch.setenv("CI", ci)
        with pytest.raises(pytest.fail.Exception, match="absent.*PLENOPIV_DATA.*plenoptomos"):
            conftest.shared_data_path("plenopticam_spots")
    # a folder that is present but lacks a file is always a failure
    (tmp_path / "present").mkdir()
    monkeypatch.setattr(conftest, "SHARED_DATA", tmp_path / "present")
    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.fail.Exception, match="incomplete"):
        conftest.shared_data_path("plenopticam_spots", "b.png")


def _numba_cache_dir(env):
    code = "import plenopiv, os; print(os.environ.get('NUMBA_CACHE_DIR'))"
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR",
                                                           "PLENOPIV_CACHE_DIR")} | env
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, check=True).stdout.strip()


def test_numba_cache_goes_to_a_user_folder(tmp_path):
    assert _numba_cache_dir({"PLENOPIV_CACHE_DIR": str(tmp_path)}) == str(tmp_path / "numba")
    assert (tmp_path / "numba").is_dir()
    assert _numba_cache_dir({"XDG_CACHE_HOME": str(tmp_path / "xdg")}) == str(
        tmp_path / "xdg" / "plenopiv" / "numba")
    # a folder the user chose is kept
    assert _numba_cache_dir({"NUMBA_CACHE_DIR": str(tmp_path / "mine")}) == str(
        tmp_path / "mine")


def test_json_output_unchanged_by_the_human_format(capsys):
    """--json prints the summary as it is (full precision), not the rounded lines."""
    assert main(["plan", "small_test", "--no-measure", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    depth = s["resolution_cell_mm"]["depth"]
    assert isinstance(depth, float) and len(repr(depth)) > 8
    assert cli.__name__ == "plenopiv.cli"
