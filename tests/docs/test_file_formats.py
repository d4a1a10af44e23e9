"""docs/file-formats.md documents every dataset and attribute the products hold.

A small product of each kind is written the way the commands write it; every dataset, every
attribute (root and dataset) and every JSON key found in it must be named in the page, in the
product's section or in the section common to every product.
"""

from __future__ import annotations

import json
import re

import h5py
import numpy as np
import pytest

from conftest import REPO

PAGE = REPO / "docs" / "file-formats.md"


def page_sections() -> dict[str, str]:
    parts = re.split(r"^## (.+)$", PAGE.read_text(), flags=re.M)
    return dict(zip(parts[1::2], parts[2::2], strict=True))


def h5_names(path) -> tuple[set[str], set[str]]:
    """Every dataset (``/a/b``) and every attribute name (root and datasets) of a file."""
    datasets, attrs = set(), set(h5py.File(path, "r").attrs)
    with h5py.File(path, "r") as fh:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                datasets.add("/" + name)
                attrs.update(obj.attrs)
        fh.visititems(visit)
    return datasets, attrs


def assert_documented(section: str, datasets=(), attrs=(), keys=()):
    text = page_sections()
    body, common = text[section], text["Common to every product"]
    missing = [d for d in datasets if f"`{d}`" not in body]
    missing += [a for a in attrs if f"`{a}`" not in body and f"`{a}`" not in common]
    missing += [k for k in keys if f"`{k}`" not in body]
    assert not missing, f"docs/file-formats.md, {section}: not documented: {sorted(missing)}"


# ---- the products ---------------------------------------------------------------------------


def _grid():
    from plenopiv.camera.grid import VolumeGrid

    return VolumeGrid.from_bounds((-1e-3, 1e-3), (-1e-3, 1e-3), (-1e-3, 1e-3), voxel=0.25e-3)


def _vectors(rng):
    from plenopiv.products.vectors import VectorResult

    shape = (2, 3, 4)
    x, y, z = (np.linspace(-1e-3, 1e-3, n) for n in shape[::-1])
    u, v, w = (rng.normal(0, 1e-5, shape) for _ in range(3))
    return VectorResult(x, y, z, u, v, w, np.ones(shape, bool), np.full(shape, 2.0), 1e-3,
                        u_uncertainty=np.full(shape, 1e-6), v_uncertainty=np.full(shape, 1e-6),
                        w_uncertainty=np.full(shape, 2e-6), uncertainty_method="response")


def test_calibration_product(tmp_path, small_camera):
    from plenopiv.calibration.model import Calibration

    path = Calibration.from_camera(small_camera).save(tmp_path / "cal.h5",
                                                      config={"inputs": {}, "summary": {}})
    datasets, attrs = h5_names(path)
    assert datasets and "image_distance_m" in attrs
    assert_documented("Calibration", datasets, attrs)
    with h5py.File(path) as fh:
        keys = set(json.loads(fh.attrs["extra"]))
    keys |= {"n_missing", "sigma_image_distance_m", "focal_spot_rms_radius_px", "spot_method",
             "point_spread_sigma_px", "micro_image_diameter_px"}   # what calibrate records
    assert_documented("Calibration", keys=keys)


def test_volume_product(tmp_path, rng):
    from plenopiv.camera.corrections import DepthCorrection
    from plenopiv.products.volume import VolumeResult

    grid = _grid()
    pos = rng.uniform(-1e-3, 1e-3, (3, 3))
    res = VolumeResult(np.ones(grid.shape, np.float32), grid, DepthCorrection(1.33, 1.0), pos,
                       pos, np.ones(3), np.full((3, 3), 1e-4),
                       particle_centroid_effective=pos)
    datasets, attrs = h5_names(res.save(tmp_path / "vol.h5", config={}))
    assert "/particles/centroid_effective_m" in datasets
    assert_documented("Volume", datasets, attrs)


def test_vectors_product_as_run_writes_it(tmp_path, rng):
    files = _vectors(rng).save(tmp_path / "vec.h5", config={}, extra_attrs={
        "complete": True, "identity": json.dumps({"settings": "0" * 64})})
    datasets, attrs = h5_names(files[0])
    assert {"/u", "/w_uncertainty", "/flag"} <= datasets and "identity" in attrs
    assert_documented("Vectors", datasets, attrs)


def test_tracks_products(tmp_path, rng):
    from plenopiv.products.tracks import save_track_products
    from plenopiv.tracking.tracks import TrackResult

    n = 6
    pa = rng.uniform(-1e-3, 1e-3, (n, 3))
    s = np.full((n, 3), 1e-5)
    # the counts the tracking records (plenopiv.workflow.tracking.match_tracks)
    counts = {k: 0 for k in ("particles_a", "particles_b", "bundle_failed_a", "bundle_failed_b",
                             "rejected_two_way", "rejected_median", "rejected_few_lenslets",
                             "tracks", "refined_grid_a", "refined_local_a", "refined_grid_b",
                             "refined_local_b")}
    tracks = TrackResult(pa, pa + 1e-5, s, s, np.ones(n), np.zeros(n), np.arange(n),
                         np.arange(n), np.full(n, 6), np.full(n, 7), 1e-3, counts)
    paths = save_track_products(tracks, _vectors(rng), tmp_path / "t.h5", config={})
    assert_documented("Tracks", *h5_names(paths["tracks"]))
    datasets, attrs = h5_names(paths["binned"])
    assert_documented("Vectors", datasets, attrs - {"source", "snr_meaning"})
    assert_documented("Tracks", attrs=attrs & {"source", "snr_meaning"})


@pytest.mark.parametrize("kind", ["pair", "particles"])
def test_synthetic_products(tmp_path, kind, capsys):
    from plenopiv.cli import main

    out = tmp_path / f"{kind}.h5"
    argv = ["simulate", kind, "small_test", "--n-particles", "4", "--rays-per-particle", "64",
            "--lenslets", "9", "11", "--out", str(out), "--json", "--quiet"]
    if kind == "pair":
        argv = [a for a in argv if a not in ("--lenslets", "9", "11")] + ["--no-tiff"]
    assert main(argv) == 0, capsys.readouterr().err
    section = {"pair": "Synthetic pair", "particles": "Synthetic particle image"}[kind]
    assert_documented(section, *h5_names(out))


@pytest.mark.parametrize("kind", ["dark", "white"])
def test_synthetic_frames(tmp_path, kind, capsys):
    from plenopiv.cli import main

    out = tmp_path / f"{kind}.h5"
    assert main(["simulate", kind, "small_test", "--lenslets", "5", "7", "--realistic",
                 "--frames", "2", "--out", str(out), "--quiet"]) == 0, capsys.readouterr().err
    assert_documented("Synthetic dark and white frames", *h5_names(out))


def test_weights_cache(tmp_path, small_camera):
    from plenopiv.calibration.model import Calibration
    from plenopiv.reconstruction.build import cached_weights

    cached_weights(Calibration.from_camera(small_camera), _grid(), cache_dir=tmp_path,
                   projector="sparse")
    (path,) = tmp_path.glob("weights-*.h5")
    assert_documented("Caches", *h5_names(path))


def test_response_cache(tmp_path):
    from plenopiv.piv.response import Response
    from plenopiv.products.caches import cached_response

    n, nz = 2, 3
    a = np.zeros((n, 3, nz))
    resp = Response(np.zeros(nz), np.zeros((n, 3)), a, a, a, 16, np.ones(3), a, a, a,
                    np.ones((3, 3)), np.zeros(3))
    path = tmp_path / "response-0.json"
    cached_response(path, "0", lambda: resp)
    assert_documented("Caches", keys=json.loads(path.read_text()))


def test_batch_summary():
    from plenopiv.batch import BatchSummary, JobResult

    job = JobResult("p1", "failed", "out/p1_vectors.h5", 1.0, error_type="E", error="e",
                    traceback="t")
    summary = BatchSummary(("p0",), (), (("p1", "E: e"),), 2.0, (job,), recomputed=(("p0", "x"),))
    d = summary.to_dict(tracebacks=True)
    keys = set(d) | set(d["results"][0])
    assert_documented("Batch summary", keys=keys)
