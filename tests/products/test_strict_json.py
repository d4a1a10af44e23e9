"""Every JSON plenopiv writes or prints is strict: null for NaN and infinities, never the bare
``NaN``/``Infinity`` tokens that strict parsers reject; all of it through products.jsonio."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from plenopiv.cli import main
from plenopiv.products.jsonio import dump, dumps, to_json

SRC = Path(__file__).resolve().parents[2] / "src" / "plenopiv"


def strict_loads(text: str):
    """JSON as strict parsers read it: the bare NaN and Infinity tokens are refused."""
    return json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))


def test_the_strict_parser_refuses_bare_nan():
    with pytest.raises(ValueError, match="NaN"):
        strict_loads(json.dumps({"gain": float("nan")}))


def test_every_json_dump_of_the_package_goes_through_jsonio():
    offenders = []
    for path in SRC.rglob("*.py"):
        if path.name == "jsonio.py":
            continue
        for i, line in enumerate(path.read_text().splitlines(), 1):
            if re.search(r"\bjson\.dumps?\(", line):
                offenders.append(f"{path.relative_to(SRC)}:{i}: {line.strip()}")
    assert not offenders, "write JSON with plenopiv.products.jsonio.dumps:\n" + "\n".join(
        offenders)


def test_dumps_turns_non_finite_values_into_null(tmp_path):
    obj = {"nan": float("nan"), "inf": [np.inf, -np.inf, 1.0], "f32": np.float32("nan"),
           "array": np.array([1.0, np.nan]), "int": np.int64(3), "path": tmp_path,
           "nested": ({"x": np.float64("inf")},)}
    text = dumps(obj, indent=1)
    assert strict_loads(text) == {"nan": None, "inf": [None, None, 1.0], "f32": None,
                                  "array": [1.0, None], "int": 3, "path": str(tmp_path),
                                  "nested": [{"x": None}]}
    # what a default= turns an object into is made finite too
    assert strict_loads(dumps({"a": object()}, default=lambda o: float("nan"))) == {"a": None}
    assert strict_loads(dumps({"a": object()}, default=str))["a"].startswith("<object")
    with pytest.raises(TypeError):
        dumps({"a": object()})
    with open(tmp_path / "x.json", "w") as fh:
        dump({"b": np.nan}, fh, sort_keys=True)
    assert strict_loads((tmp_path / "x.json").read_text()) == {"b": None}
    assert to_json({"b": 1, "a": np.nan}) == '{"a": null, "b": 1}'


def test_finite_text_is_what_json_dumps_writes():
    """Keys hashed from the text (weights, responses) stay as they were."""
    obj = {"v": 3, "camera": {"a": [1.5, 2], "b": "x"}, "t": (1, 2.25), "none": None}
    assert dumps(obj, sort_keys=True) == json.dumps(obj, sort_keys=True)
    assert dumps(obj, indent=1) == json.dumps(obj, indent=1)


def _vectors_product(path):
    from plenopiv.camera.grid import VolumeGrid
    from plenopiv.products.vectors import VectorResult

    grid = VolumeGrid((0.0, 0.0, 0.0), (1e-4, 1e-4, 1e-4), (8, 8, 8))
    x = y = z = 1e-4 * np.array([1.5, 3.5, 5.5])
    shape = (3, 3, 3)
    u = np.broadcast_to(x, shape) * 0.1
    vec = VectorResult(x, y, z, u, np.zeros(shape), np.zeros(shape), np.ones(shape, bool),
                       np.full(shape, np.inf), grid=grid, window_vox=(4, 4, 4))
    vec.save(path, config={"piv": {"gain": float("nan")}, "dt_s": float("inf")})
    return path


def test_compare_json_with_a_nan_gain_is_strict(tmp_path, capsys):
    p = _vectors_product(tmp_path / "v.h5")
    assert main(["compare", str(p), str(p), "--json"]) == 0
    text = capsys.readouterr().out
    s = strict_loads(text)
    assert s["overall"]["v"]["gain"] is None and s["overall"]["w"]["gain"] is None
    assert "NaN" not in text and "Infinity" not in text


def test_product_attributes_hold_strict_json(tmp_path):
    from plenopiv.calibration.model import Calibration
    from plenopiv.camera.model import load_camera

    p = _vectors_product(tmp_path / "v.h5")
    with h5py.File(p) as fh:
        cfg = strict_loads(fh.attrs["config"])
    assert cfg == {"piv": {"gain": None}, "dt_s": None}
    cal = Calibration.from_camera(load_camera("small_m1"))
    cal = replace(cal, extra={"point_spread_sigma_px": float("nan"), "n": np.int64(4),
                              "r": np.float32(0.5)})
    cal.save(tmp_path / "cal.h5", config={"summary": {"sigma_mm": np.nan}})
    with h5py.File(tmp_path / "cal.h5") as fh:
        for key in ("extra", "camera", "config"):
            strict_loads(fh.attrs[key])
    back = Calibration.load(tmp_path / "cal.h5")
    assert back.point_spread_sigma_px is None and back.extra["n"] == 4


def test_verbs_print_strict_json(tmp_path, capsys):
    runs = [["presets", "--json"],
            ["plan", "small_m1", "--no-measure", "--json", "--x-mm", "-2", "2", "--y-mm", "-1",
             "1", "--z-mm", "-2", "2"],
            ["piv", str(tmp_path / "none.h5"), str(tmp_path / "none.h5"), "--out",
             str(tmp_path / "w.h5"), "--dt", "nan", "--json"]]
    for argv in runs:
        main(argv)
        text = capsys.readouterr().out
        obj = strict_loads(text)
        assert isinstance(obj, dict) and "NaN" not in text, argv


def test_reports_summaries_caches_and_image_metadata_are_strict(tmp_path):
    import tifffile

    from pipelines.studies.output import write_json
    from plenopiv import batch
    from plenopiv.piv.response import RESPONSE_VERSION
    from plenopiv.products.caches import cached_response
    from plenopiv.products.images import write_image

    write_json(tmp_path / "report.json", {"gain": np.nan, "rms": [np.inf, 0.5]})
    assert strict_loads((tmp_path / "report.json").read_text()) == {"gain": None,
                                                                     "rms": [None, 0.5]}
    done = batch.JobResult("p", "done", str(tmp_path / "p.h5"), 1.0,
                           result={"gain": [np.nan, 1.0], "rms": np.float32("inf")})
    s = batch._write_summary((done,), tmp_path / "summary.json", seconds=float("nan"))
    written = strict_loads((tmp_path / "summary.json").read_text())
    assert written["results"][0]["result"] == {"gain": [None, 1.0], "rms": None}
    assert strict_loads(json.dumps(s.to_dict()))["seconds"] is None

    class Stub:
        def to_dict(self):
            return {"version": RESPONSE_VERSION, "gain": [np.nan, 1.0]}

    cached_response(tmp_path / "response.json", "k", Stub)
    assert strict_loads((tmp_path / "response.json").read_text())["gain"] == [None, 1.0]
    write_image(tmp_path / "i.tif", np.zeros((4, 4), np.uint16),
                metadata={"max": np.nan, "shape": np.array([4, 4])})
    with tifffile.TiffFile(tmp_path / "i.tif") as tif:
        assert strict_loads(tif.pages[0].description) == {"max": None, "shape": [4, 4]}


def test_vortex_summary_text_is_strict():
    """The vortex case's summary.json: dumps with ``default=str`` (case objects as text)."""
    from plenopiv.workflow.vortex_case import VortexCase

    summary = {"case": VortexCase().__dict__, "errors": {"gain": [np.nan, 1.0, np.inf]}}
    obj = strict_loads(dumps(summary, indent=1, default=str))
    assert obj["errors"]["gain"] == [None, 1.0, None]
