"""Provenance: every product records what made it; every consumer refuses another origin.

The products are made once by the commands on the small CI camera (the module fixture
``chain``); each case then changes one recorded input or setting (enumerated from the records
themselves) and asserts that the consumer refuses, naming both files and what differs.
Schema versions, NaN and inf in every dataset of every product kind, and caches changed in
place are enumerated the same way. ``plenopiv run``'s resume: tests/cli/test_run_resume.py.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
import tifffile

from plenopiv import __version__
from plenopiv.calibration.model import Calibration
from plenopiv.camera.corrections import DepthCorrection
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import load_camera
from plenopiv.cli import main
from plenopiv.errors import CalibrationError, PlenopivWarning, ReconstructionError
from plenopiv.products import caches
from plenopiv.products.files import file_identity
from plenopiv.products.provenance import (
    PROVENANCE_ATTR,
    SCHEMA_ATTR,
    WORDS,
    check_readable,
    read_provenance,
    schema_version,
)
from plenopiv.products.tracks import load_tracks, write_tracks
from plenopiv.products.vectors import INF_DATASETS, NAN_DATASETS, VectorResult, load_vectors
from plenopiv.products.volume import NAN_DATASETS as VOLUME_NAN_DATASETS
from plenopiv.products.volume import VolumeResult, load_volume
from plenopiv.tracking.tracks import TrackResult
from plenopiv.workflow.provenance import PAIR_IGNORES, VOLUME_SETTINGS
from small_case import VOLUME, simulate_pair_argv

EXPERIMENT = """camera = "small_m1"
""" + VOLUME + """[reconstruction]
lateral_subdivision = 1
[piv]
windows = [[12, 12, 12]]
passes = 2
[mask]
image = "mask.npy"
[preprocess]
dark = "dark.tif"
[images]
dt_s = 1e-3
[output]
png = false
vtk = false
weights_cache = "cache"
"""


def run(*argv) -> tuple[int, str]:
    """``plenopiv ARGV`` in-process: (exit status, stderr)."""
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv] + ["--quiet"])
    return code, err.getvalue()


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    """A pair's products made by the commands, and those of another pair and calibration."""
    d = tmp_path_factory.mktemp("chain")
    cam = load_camera("small_m1")
    cal = Calibration.from_camera(cam)
    cal.save(d / "cal.h5")
    centre = cal.centre_px.copy()
    centre[0, 0] += 1e-3                          # the same camera, another calibration file
    dataclasses.replace(cal, centre_px=centre).save(d / "cal2.h5")
    Calibration.from_camera(load_camera("small_test")).save(d / "cal_small_test.h5")
    for seed, name in ((1, "pair"), (2, "pair2")):
        assert run(*simulate_pair_argv(d / f"{name}.h5", seed=seed))[0] == 0
    tifffile.imwrite(d / "dark.tif", np.full(cam.sensor.shape, 2, np.uint16))
    np.save(d / "mask.npy", np.zeros(cam.sensor.shape, bool))
    (d / "exp.toml").write_text(EXPERIMENT)
    volumes = {"va": ("cal", "pair", "a"), "vb": ("cal", "pair", "b"),
               "va2": ("cal", "pair2", "a"), "vb2": ("cal", "pair2", "b"),
               "vb_cal2": ("cal2", "pair", "b")}
    for out, (c, pair, tag) in volumes.items():
        code, err = run("reconstruct", d / f"{c}.h5", f"{d / pair}.h5:/image_{tag}", "--config",
                        d / "exp.toml", "--out", d / f"{out}.h5")
        assert code == 0, err
    for out, (a, b) in {"vec": ("va", "vb"), "vec2": ("va2", "vb2")}.items():
        code, err = run("piv", d / f"{a}.h5", d / f"{b}.h5", "--out", d / f"{out}.h5",
                        "--windows", 12, 12, 12, "--no-png", "--no-vtk")
        assert code == 0, err
    code, err = run("track", d / "cal.h5", f"{d}/pair.h5:/image_a", f"{d}/pair.h5:/image_b",
                    "--config", d / "exp.toml", "--out", d / "tracks.h5",
                    "--volume-a", d / "va.h5", "--volume-b", d / "vb.h5",
                    "--vectors", d / "vec.h5")
    assert code == 0, err
    return SimpleNamespace(d=d, **{k: d / f"{k}.h5" for k in (
        "cal", "cal2", "cal_small_test", "va", "vb", "va2", "vb2", "vb_cal2", "vec", "vec2",
        "tracks")}, image_a=f"{d}/pair.h5:/image_a", image_b=f"{d}/pair.h5:/image_b",
                           exp=d / "exp.toml")


def record(path) -> dict:
    with h5py.File(path, "r") as fh:
        return read_provenance(fh.attrs.get(PROVENANCE_ATTR))


def changed_copy(src, dst, section: str, key: str, nested: str | None = None) -> Path:
    """A copy of product ``src`` whose record holds another hash for ``section``/``key``."""
    shutil.copyfile(src, dst)
    with h5py.File(dst, "r+") as fh:
        rec = read_provenance(fh.attrs[PROVENANCE_ATTR])
        target = rec if nested is None else rec["sources"][nested]
        target[section][key] = "0" * 64
        fh.attrs[PROVENANCE_ATTR] = json.dumps(rec)
    return Path(dst)


# ---- what the producers record ----------------------------------------------------------------


def test_the_commands_record_what_made_each_product(chain):
    d = chain.d
    va = record(chain.va)
    assert va["product"] == "volume" and va["schema_version"] == schema_version("volume") == 2
    assert va["inputs"] == {"image": file_identity(chain.image_a),
                            "calibration": file_identity(chain.cal),
                            "dark": file_identity(d / "dark.tif"),
                            "mask_image": file_identity(d / "mask.npy")}
    assert set(va["settings"]) == set(VOLUME_SETTINGS)
    vec = record(chain.vec)
    assert vec["inputs"] == {"volume_a": file_identity(chain.va),
                             "volume_b": file_identity(chain.vb)}
    assert vec["sources"] == {"volume_a": va, "volume_b": record(chain.vb)}
    assert set(vec["settings"]) == {"piv", "dt_s"}
    tracks = record(chain.tracks)
    assert {"image_a", "image_b", "calibration", "volume_a", "volume_b", "vectors", "dark",
            "mask_image"} == set(tracks["inputs"])
    assert set(tracks["sources"]) == {"volume_a", "volume_b", "vectors"}
    binned = record(d / "tracks_binned.h5")
    assert binned["product"] == "vectors" and binned["inputs"] == tracks["inputs"]
    for path in (chain.cal, chain.va, chain.vec, chain.tracks):
        with h5py.File(path) as fh:
            assert fh.attrs[SCHEMA_ATTR] == 2 and fh.attrs["plenopiv_version"]


def test_calibrate_records_its_images_camera_and_options(tmp_path):
    fp = tmp_path / "fp.tif"
    assert run("simulate", "focal-point", "small_m1", "--out", fp)[0] == 0
    code, err = run("calibrate", "small_m1", "--focal-point", fp, "--no-report", "--out",
                    tmp_path / "cal.h5")
    assert code == 0, err
    rec = record(tmp_path / "cal.h5")
    assert rec["inputs"] == {"focal_point": file_identity(fp)}
    assert set(rec["settings"]) == {"camera", "calibrate"}


# ---- plenopiv piv: two volumes made alike --------------------------------------------------

#: Every input and setting of a volume's record that ``piv`` compares (all but PAIR_IGNORES).
PAIR_KEYS = [("inputs", "calibration"), ("inputs", "dark"), ("inputs", "mask_image"),
             ("settings", "camera"), ("settings", "volume"), ("settings", "reconstruction"),
             ("settings", "preprocess"), ("settings", "mask")]


def test_the_cases_cover_every_recorded_input_and_setting(chain):
    rec = record(chain.vb)
    recorded = {(s, k) for s in ("inputs", "settings") for k in rec[s] if k not in PAIR_IGNORES}
    assert recorded == set(PAIR_KEYS)


@pytest.mark.parametrize(("section", "key"), PAIR_KEYS)
def test_piv_refuses_volumes_not_made_alike(chain, tmp_path, section, key):
    other = changed_copy(chain.vb, tmp_path / "vb_other.h5", section, key)
    out = tmp_path / "v.h5"
    code, err = run("piv", chain.va, other, "--out", out, "--no-png", "--no-vtk")
    assert code == 2 and err.startswith("error: the volumes ")
    assert str(chain.va) in err and str(other) in err and WORDS[key] in err, err
    assert not out.exists()


def test_piv_refuses_volumes_of_two_calibrations(chain, tmp_path):
    code, err = run("piv", chain.va, chain.vb_cal2, "--out", tmp_path / "v.h5", "--no-png")
    assert code == 2 and str(chain.vb_cal2) in err and "calibration file" in err


# ---- plenopiv track: products of this pair only ------------------------------------------------


def track_case(chain, tmp_path, name: str):
    """``(calibration, {option: product}, the two files the refusal must name)``."""
    c = chain
    cases = {
        "volume-a of another pair": (c.cal, {"--volume-a": c.va2}, (c.va2, c.image_a)),
        "volume-b is volume A": (c.cal, {"--volume-b": c.va}, (c.va, c.image_b)),
        "vectors of other volumes": (c.cal, {"--volume-a": c.va, "--volume-b": c.vb,
                                             "--vectors": c.vec2}, (c.vec2, c.va)),
        "vectors of other images": (c.cal, {"--vectors": c.vec2}, (c.vec2, c.image_a)),
        "volume of another calibration": (c.cal2, {"--volume-a": c.va}, (c.va, c.cal2)),
        "vectors of another calibration": (c.cal2, {"--vectors": c.vec}, (c.vec, c.cal2)),
    }
    for key in ("camera", "volume", "reconstruction"):
        path = changed_copy(c.va, tmp_path / f"va_{key}.h5", "settings", key)
        cases[f"volume of another {key}"] = (c.cal, {"--volume-a": path}, (path, WORDS[key]))
    vec = changed_copy(c.vec, tmp_path / "vec_image.h5", "inputs", "image", nested="volume_b")
    cases["vectors whose volume B is of another image"] = (c.cal, {"--vectors": vec},
                                                           (vec, c.image_b))
    return cases[name]


TRACK_CASES = ["volume-a of another pair", "volume-b is volume A", "vectors of other volumes",
               "vectors of other images", "volume of another calibration",
               "vectors of another calibration", "volume of another camera",
               "volume of another volume", "volume of another reconstruction",
               "vectors whose volume B is of another image"]


@pytest.mark.parametrize("case", TRACK_CASES)
def test_track_refuses_products_of_another_pair(chain, tmp_path, case):
    cal, given, names = track_case(chain, tmp_path, case)
    out = tmp_path / "t.h5"
    argv = ["track", cal, chain.image_a, chain.image_b, "--config", chain.exp, "--out", out]
    for option, path in given.items():
        argv += [option, path]
    code, err = run(*argv)
    assert code == 2 and "products of another pair" in err, err
    assert all(str(n) in err for n in names), err
    assert not out.exists()


# ---- a calibration of another camera -------------------------------------------------------------


@pytest.mark.parametrize("verb", ["reconstruct", "track", "plan experiment", "plan camera",
                                  "run"])
def test_a_calibration_of_another_camera_is_refused(chain, tmp_path, verb):
    c, other = chain, chain.cal_small_test
    exp = tmp_path / "exp.toml"
    exp.write_text(EXPERIMENT.replace('dark = "dark.tif"', f'dark = "{c.d}/dark.tif"')
                   .replace('"mask.npy"', f'"{c.d}/mask.npy"')
                   .replace("[images]", f'[images]\npairs = "{c.d}/pair.h5"\n'
                            f'calibration = "{other}"'))
    argv = {"reconstruct": ["reconstruct", other, c.image_a, "--config", exp, "--out",
                            tmp_path / "v.h5"],
            "track": ["track", other, c.image_a, c.image_b, "--config", exp, "--out",
                      tmp_path / "t.h5"],
            "plan experiment": ["plan", exp, "--calibration", other, "--no-measure"],
            "plan camera": ["plan", "small_m1", "--calibration", other, "--no-measure"],
            "run": ["run", exp]}[verb]
    code, err = run(*argv)
    assert code == 2 and f"the calibration {str(other)!r} was made for camera" in err, err
    assert "lattice 41 × 61 square ≠" in err or "sensor" in err


# ---- schema and package versions --------------------------------------------------------------


def _volume(path, rng):
    grid = VolumeGrid((0.0, 0.0, 0.0), (1e-4, 1e-4, 2e-4), (3, 4, 5))
    pos = rng.uniform(0, 3e-4, (3, 3))
    VolumeResult(rng.random(grid.shape).astype(np.float32), grid, DepthCorrection(1.33, 1.0),
                 pos, pos, np.ones(3), np.full((3, 3), 1e-4),
                 particle_centroid_effective=pos).save(path)


def _vectors(path, rng):
    shape = (2, 3, 4)
    x, y, z = (np.linspace(-1e-3, 1e-3, n) for n in shape[::-1])
    u, v, w = (rng.normal(0, 1e-5, shape) for _ in range(3))
    s = np.full(shape, 1e-6)
    VectorResult(x, y, z, u, v, w, np.ones(shape, bool), np.full(shape, 2.0), 1e-3,
                 peak_height=np.full(shape, 0.5), u_uncertainty=s, v_uncertainty=s,
                 w_uncertainty=s, grid=VolumeGrid((0, 0, 0), (1e-4,) * 3, (8, 8, 8)),
                 window_vox=(8, 8, 8)).save(path)


def _tracks(path, rng):
    n = 5
    pa = rng.uniform(-1e-3, 1e-3, (n, 3))
    s = np.full((n, 3), 1e-5)
    write_tracks(path, TrackResult(pa, pa + 1e-5, s, s, np.ones(n), np.zeros(n), np.arange(n),
                                   np.arange(n), np.full(n, 6), np.full(n, 7), 1e-3,
                                   {"tracks": n}), vtk=False)


#: Each product kind: how to write a small one, its reader and the reader's error.
KINDS = {
    "calibration": (lambda p, rng: Calibration.from_camera(load_camera("small_m1")).save(p),
                    Calibration.load, CalibrationError),
    "volume": (_volume, load_volume, ReconstructionError),
    "vectors": (_vectors, load_vectors, ReconstructionError),
    "tracks": (_tracks, load_tracks, ReconstructionError),
}


@pytest.fixture(scope="module")
def small_products(tmp_path_factory):
    d = tmp_path_factory.mktemp("small")
    rng = np.random.default_rng(35)
    for kind, (write, _, _) in KINDS.items():
        write(d / f"{kind}.h5", rng)
    return d


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize(("attr", "value", "readable", "words"), [
    (SCHEMA_ATTR, 3, False, "schema version 3, newer than the 2"),
    (SCHEMA_ATTR, "two", False, "unknown schema version 'two'"),
    (SCHEMA_ATTR, 0, False, "unknown schema version 0"),
    (SCHEMA_ATTR, 1.5, False, "unknown schema version 1.5"),
    (SCHEMA_ATTR, None, True, ""),                # written before schema versions: schema 1
    ("plenopiv_version", "99.0.0", False, "written by plenopiv 99.0.0, a newer major"),
    ("plenopiv_version", "0.0.1", True, ""),
])
def test_schema_and_version_of_every_product_kind(small_products, tmp_path, kind, attr, value,
                                                  readable, words):
    _, read, error = KINDS[kind]
    path = tmp_path / f"{kind}.h5"
    shutil.copyfile(small_products / f"{kind}.h5", path)
    with h5py.File(path, "r+") as fh:
        if value is None:
            del fh.attrs[attr]
        else:
            fh.attrs[attr] = value
    if readable:
        read(path)
        return
    with pytest.raises(error) as info:
        read(path)
    assert words in str(info.value) and str(path) in str(info.value)
    assert f"({__version__})" in str(info.value)                    # this version named too


def test_check_readable_names_both_versions():
    with pytest.raises(ValueError, match=r"'f.h5' is of schema version 7, newer than the 2 "
                                         r"this plenopiv \(.+\) reads \(written by plenopiv 5"):
        check_readable("f.h5", "volume", 7, "5.0.0", ValueError)
    assert check_readable("f.h5", "volume", None, None, ValueError) == 1
    assert check_readable("f.h5", "volume", np.int64(2), "0.1.0", ValueError) == 2


# ---- finite values on read ---------------------------------------------------------------------


def float_datasets(path) -> list[str]:
    out = []
    with h5py.File(path, "r") as fh:
        fh.visititems(lambda name, obj: out.append("/" + name) if isinstance(
            obj, h5py.Dataset) and obj.dtype.kind == "f" else None)
    return sorted(out)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_and_inf_in_every_dataset_are_refused_on_read(small_products, tmp_path, kind, bad):
    """Every float dataset of the product, in turn; NaN and inf only where the format says."""
    _, read, error = KINDS[kind]
    names = float_datasets(small_products / f"{kind}.h5")
    assert len(names) >= 2
    for name in names:
        path = tmp_path / f"{kind}{name.replace('/', '_')}.h5"
        shutil.copyfile(small_products / f"{kind}.h5", path)
        with h5py.File(path, "r+") as fh:
            a = fh[name][()]
            a.flat[a.size // 2] = bad
            fh[name][...] = a
        allowed = ((kind == "vectors" and (name in INF_DATASETS if np.isinf(bad)
                                           else name in NAN_DATASETS))
                   or (kind == "volume" and np.isnan(bad) and name in VOLUME_NAN_DATASETS))
        if allowed:
            read(path)
            continue
        with pytest.raises(error) as info:
            read(path)
        assert f"{str(path)!r}: dataset {name} holds" in str(info.value), name


@pytest.mark.parametrize(("kind", "attr"), [
    ("calibration", "image_distance_m"), ("calibration", "offset_m"),
    ("calibration", "rotation_rad"), ("volume", "depth_correction_external"),
    ("volume", "depth_correction_internal"), ("vectors", "dt_s"), ("vectors", "voxel_m"),
    ("vectors", "volume_origin_m"), ("tracks", "dt_s")])
def test_nan_or_inf_in_a_numeric_attribute_is_refused(small_products, tmp_path, kind, attr):
    _, read, error = KINDS[kind]
    path = tmp_path / f"{kind}.h5"
    shutil.copyfile(small_products / f"{kind}.h5", path)
    with h5py.File(path, "r+") as fh:
        value = np.array(fh.attrs[attr], float)
        value.flat[0] = np.inf
        fh.attrs[attr] = value
    with pytest.raises(error, match=f"attribute {attr} holds 1 infinite"):
        read(path)


# ---- caches -----------------------------------------------------------------------------------


def _weights(cache_dir):
    from plenopiv.reconstruction.build import cached_weights

    grid = VolumeGrid.from_bounds((-1e-3, 1e-3), (-1e-3, 1e-3), (-1e-3, 1e-3), voxel=0.25e-3)
    return cached_weights(Calibration.from_camera(load_camera("small_test")), grid,
                          cache_dir=cache_dir, projector="sparse")


def _edit_weights(path, edit):
    with h5py.File(path, "r+") as fh:
        for name, value in edit(fh).items():
            fh[name][...] = value


def test_weights_changed_in_place_are_rebuilt_with_a_warning(tmp_path):
    built, hit = _weights(tmp_path)
    assert not hit
    (path,) = tmp_path.glob("weights-*.h5")
    size = path.stat().st_size
    rng = np.random.default_rng(1)
    changed = rng.choice(len(built.projector.data), 1000, replace=False)

    def scale(fh):
        data = fh["/data"][()]
        data[changed] *= 1.3
        return {"/data": data}

    _edit_weights(path, scale)
    assert path.stat().st_size == size
    with pytest.warns(PlenopivWarning, match=r"weights cache '.+' not used: its weights do not "
                                             r"match their checksum"):
        again, hit = _weights(tmp_path)
    assert not hit
    np.testing.assert_array_equal(again.projector.data, built.projector.data)
    loaded, hit = _weights(tmp_path)                      # the rebuilt cache is used, silently
    assert hit
    np.testing.assert_array_equal(loaded.projector.data, built.projector.data)


@pytest.mark.parametrize("damage", ["nan weights", "newer schema", "newer version"])
def test_weights_cache_that_may_not_be_used_is_rebuilt_with_a_warning(tmp_path, damage):
    built, _ = _weights(tmp_path)
    (path,) = tmp_path.glob("weights-*.h5")
    with h5py.File(path, "r+") as fh:
        if damage == "nan weights":         # written with NaN: the checksum holds, the values not
            data = fh["/data"][()]
            data[5] = np.nan
            fh["/data"][...] = data
            fh.attrs["checksum"] = caches.weights_checksum(
                [fh[n][()] for n in caches.WEIGHT_DATASETS])
        elif damage == "newer schema":
            fh.attrs[SCHEMA_ATTR] = 3
        else:
            fh.attrs["plenopiv_version"] = "99.0.0"
    words = {"nan weights": "dataset /data holds 1 NaN", "newer schema": "schema version 3",
             "newer version": "plenopiv 99.0.0"}[damage]
    with pytest.warns(PlenopivWarning, match=words):
        again, hit = _weights(tmp_path)
    assert not hit
    np.testing.assert_array_equal(again.projector.data, built.projector.data)


def test_a_verified_weights_cache_is_read_without_hashing_until_it_changes(tmp_path,
                                                                          monkeypatch):
    _weights(tmp_path)
    (path,) = tmp_path.glob("weights-*.h5")
    monkeypatch.setattr(caches, "RACY_NS", -10**12)      # the record counts at once
    assert caches.read_weights(path, h5py.File(path, "r").attrs["key"]) is not None
    hashed = []
    real = caches.weights_checksum
    monkeypatch.setattr(caches, "weights_checksum", lambda a: hashed.append(1) or real(a))
    assert _weights(tmp_path)[1] and not hashed           # untouched: no full check
    _edit_weights(path, lambda fh: {"/data": fh["/data"][()]})    # rewritten, same bytes
    assert _weights(tmp_path)[1] and hashed == [1]        # checked in full, and still good


def _response_cache(path):
    from plenopiv.piv.response import Response

    n, nz = 2, 3
    a = np.full((n, 3, nz), 0.5)
    resp = Response(np.linspace(-1e-3, 1e-3, nz), np.ones((n, 3)) * 1e-4, a, a, a, 16,
                    np.full(3, 1e-4), a, a, a, np.ones((3, 3)), np.zeros(3))
    return caches.cached_response(path, "k", lambda: resp)


@pytest.mark.parametrize(("damage", "words"), [
    ("number changed", "does not match its checksum"),
    ("inf, checksum made again", "its z_m holds inf"),
    ("null shift, checksum made again", "its shifts_m holds NaN"),
    ("newer schema", "schema version 3"),
])
def test_response_cache_that_may_not_be_used_is_measured_again(tmp_path, damage, words):
    path = tmp_path / "response-k.json"
    resp, hit = _response_cache(path)
    assert not hit and _response_cache(path)[1]
    d = json.loads(path.read_text())
    if damage == "number changed":
        d["gain"][0][0][0] = 0.7
    elif damage.startswith("inf"):
        d["z_m"][0] = float("inf")
    elif damage.startswith("null"):
        d["shifts_m"][0][0] = None
    else:
        d["schema_version"] = 3
    if "checksum made again" in damage:
        d["checksum"] = caches.json_hash({k: v for k, v in d.items() if k != "checksum"})
    path.write_text(json.dumps(d))
    with pytest.warns(PlenopivWarning, match=f"response cache '.+' not used: .*{words}"):
        again, hit = _response_cache(path)
    assert not hit and np.array_equal(again.gain, resp.gain)
    assert _response_cache(path)[1]


def test_a_response_cache_without_checksum_is_measured_again_silently(tmp_path):
    path = tmp_path / "response-k.json"
    _response_cache(path)
    d = json.loads(path.read_text())
    for key in ("checksum", "schema_version", "plenopiv_version"):
        d.pop(key)
    path.write_text(json.dumps(d))
    assert not _response_cache(path)[1]


def test_an_earlier_batch_summary_of_a_newer_schema_is_not_read(tmp_path):
    from plenopiv.batch.jobs import finished_before

    path = tmp_path / "batch_summary.json"
    summary = {"schema_version": 2, "results": [{"name": "p", "status": "done"}]}
    path.write_text(json.dumps(summary))
    assert finished_before(path) == {"p"}
    path.write_text(json.dumps({**summary, "schema_version": 3}))
    assert finished_before(path) == set()


# ---- finite values on write -------------------------------------------------------------------


def test_nan_and_inf_are_refused_before_writing_where_the_format_has_none(tmp_path, rng):
    """The same rule as on read, before anything is written: a volume's positions, a
    calibration's centres, a vector field's coordinates refused (WriteError naming the
    dataset, no file left, no .vti beside it); NaN in a rejected vector and an unmeasured
    particle size written."""
    from plenopiv.errors import WriteError

    grid = VolumeGrid((0.0, 0.0, 0.0), (1e-4, 1e-4, 2e-4), (3, 4, 5))
    pos = rng.uniform(0, 3e-4, (3, 3))
    size = np.full((3, 3), 1e-4)
    bad = pos.copy()
    bad[1, 2] = np.nan

    def volume(p, s):
        return VolumeResult(rng.random(grid.shape).astype(np.float32), grid,
                            DepthCorrection(1.33, 1.0), p, p, np.ones(3), s)
    with pytest.raises(WriteError, match="position_m holds 1 NaN.*refused before writing"):
        volume(bad, size).save(tmp_path / "v.h5")
    assert not (tmp_path / "v.h5").exists()
    unmeasured = size.copy()
    unmeasured[0, 2] = np.nan
    load_volume(volume(pos, unmeasured).save(tmp_path / "ok.h5"))

    cal = Calibration.from_camera(load_camera("small_m1"))
    centres = cal.centre_px.copy()
    centres[3, 0] = np.inf
    with pytest.raises(WriteError, match="centre_px holds 1 infinite"):
        dataclasses.replace(cal, centre_px=centres).save(tmp_path / "c.h5")
    assert not (tmp_path / "c.h5").exists()

    shape = (2, 3, 4)
    x, y, z = (np.linspace(-1e-3, 1e-3, n) for n in shape[::-1])
    u = rng.normal(0, 1e-5, shape)
    u[0, 0, 0] = np.nan                      # a rejected vector: written
    VectorResult(x, y, z, u, u, u, np.ones(shape, bool), np.full(shape, 2.0)).save(
        tmp_path / "f.h5", vtk=False)
    x = x.copy()
    x[1] = np.inf
    with pytest.raises(WriteError, match="dataset /x holds 1 infinite"):
        VectorResult(x, y, z, u, u, u, np.ones(shape, bool), np.full(shape, 2.0)).save(
            tmp_path / "g.h5", vtk=True)
    assert not list(tmp_path.glob("g*"))
