"""``plenopiv compare``: a vectors product against a known field, another product or a pair."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest

from plenopiv.camera.grid import VolumeGrid
from plenopiv.cli import main
from plenopiv.products.vectors import VectorResult, load_vectors
from plenopiv.workflow.compare import field_accuracy, window_mean_displacement

#: The grid of the known fields: 16 x 16 x 12 voxels (x, y, z), voxels of 0.1, 0.1, 0.2 mm.
GRID = VolumeGrid((-0.75e-3, -0.75e-3, -1.1e-3), (0.1e-3, 0.1e-3, 0.2e-3), (12, 16, 16))
WINDOW = (4, 8, 8)                      # (z, y, x) voxels; vectors every half window


def strict_loads(text: str):
    """JSON as strict parsers read it: the bare NaN and Infinity tokens are refused."""
    return json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))


def _axis(a: int) -> np.ndarray:
    """Window centres along axis a (0: x, 1: y, 2: z) of windows tiling GRID, and one more
    vector beyond its edge (its window sticks out of the volume)."""
    w = WINDOW[2 - a]
    n = 2 * GRID.shape[2 - a] // w          # one more than the windows that fit
    return GRID.origin[a] + GRID.voxel[a] * ((w - 1) / 2 + w / 2 * np.arange(n))


X, Y, Z = (_axis(a) for a in range(3))
ZZ, YY, XX = np.meshgrid(Z, Y, X, indexing="ij")
#: A vortex about y: u and w vary, v is 0 everywhere (no gain).
U = 2e-4 * ZZ / 1e-3
V = np.zeros_like(U)
W = -2e-4 * XX / 1e-3


def vectors(path, scale=1.0, bias=(0.0, 0.0, 0.0), *, valid=None, dt=None, grid=GRID,
            window=WINDOW, x=X, config=None):
    valid = np.ones(U.shape, bool) if valid is None else valid
    # displacements in metres; a product with dt stores them as velocities
    vec = VectorResult(x, Y, Z, scale * U + bias[0], scale * V + bias[1], scale * W + bias[2],
                       valid, np.full(U.shape, 3.0), dt=dt, grid=grid, window_vox=window)
    vec.save(path, config=config)
    return path


def compare(capsys, *argv):
    code = main(["compare", *map(str, argv), "--json"])
    out, err = capsys.readouterr()
    return code, strict_loads(out), err


@pytest.fixture
def truth(tmp_path):
    return vectors(tmp_path / "truth.h5")


def test_identical_fields_gain_1_bias_0_rms_0(tmp_path, truth, capsys):
    code, s, _ = compare(capsys, truth, truth)
    assert code == 0
    assert set(s) == {"command", "vectors", "truth", "truth_kind", "truth_at_vectors",
                      "n_vectors", "unit", "voxel_m", "overall", "bands", "notes"}
    assert s["command"] == "compare" and s["truth_kind"] == "vectors"
    assert s["unit"] == "voxel" and s["voxel_m"] == pytest.approx(GRID.voxel)
    inner = (len(X) - 1) * (len(Y) - 1) * (len(Z) - 1)     # the last sticks out
    assert s["n_vectors"] == inner
    for c in "uw":
        f = s["overall"][c]
        assert set(f) >= {"gain", "bias", "rms", "correlation", "true_rms", "n"}
        assert f["gain"] == pytest.approx(1.0, abs=1e-6)
        assert f["correlation"] == pytest.approx(1.0, abs=1e-6)
        assert f["bias"] == 0 and f["rms"] == 0 and f["n"] == inner
        assert f["true_rms"] > 0.3
    assert s["overall"]["v"]["gain"] is None and s["overall"]["v"]["correlation"] is None
    assert "v: no gain, the true v does not vary (rms 0.000 voxel)" in s["notes"]


def test_half_size_field_has_gain_one_half(tmp_path, truth, capsys):
    half = vectors(tmp_path / "half.h5", scale=0.5)
    code, s, _ = compare(capsys, half, truth)
    assert code == 0
    for c in "uw":
        assert s["overall"][c]["gain"] == pytest.approx(0.5, abs=1e-6)
        assert s["overall"][c]["bias"] == pytest.approx(0.0, abs=1e-6)
        # the error is half the field: rms error = true rms / 2
        assert s["overall"][c]["rms"] == pytest.approx(0.5 * s["overall"][c]["true_rms"],
                                                       rel=1e-5)
        for band in s["bands"]:
            assert band[c]["gain"] is None or band[c]["gain"] == pytest.approx(0.5, abs=1e-5)


def test_known_bias_in_voxels_and_metres(tmp_path, truth, capsys):
    biased = vectors(tmp_path / "bias.h5", bias=(0.05e-3, -0.02e-3, 0.1e-3))
    code, s, _ = compare(capsys, biased, truth)
    assert code == 0
    expected = {"u": 0.5, "v": -0.2, "w": 0.5}          # 0.05 mm / 0.1 mm, ... 0.1 / 0.2
    for c, b in expected.items():
        f = s["overall"][c]
        assert f["bias"] == pytest.approx(b, abs=1e-5)
        assert f["rms"] == pytest.approx(abs(b), abs=1e-5)
        assert f["bias_m"] == pytest.approx(b * GRID.voxel["uvw".index(c)], abs=1e-9)
    assert s["overall"]["u"]["gain"] == pytest.approx(1.0, abs=1e-5)


def test_depth_bands_split_the_vectors_used(tmp_path, truth, capsys):
    code, s, _ = compare(capsys, truth, truth, "--bands", "2")
    assert code == 0 and len(s["bands"]) == 2
    assert sum(b["n_vectors"] for b in s["bands"]) == s["n_vectors"]
    lo, hi = s["bands"][0]["z_m"][0], s["bands"][-1]["z_m"][1]
    used_z = Z[:-1]
    assert lo == pytest.approx(used_z.min()) and hi == pytest.approx(used_z.max())
    assert s["bands"][0]["z_m"][1] == pytest.approx(s["bands"][1]["z_m"][0])


def test_rejected_vectors_and_velocities(tmp_path, truth, capsys):
    valid = np.ones(U.shape, bool)
    valid[2, 2, 2] = False
    velo = vectors(tmp_path / "velo.h5", valid=valid, dt=2e-3)
    code, s, _ = compare(capsys, velo, truth)
    assert code == 0
    assert s["n_vectors"] == (len(X) - 1) * (len(Y) - 1) * (len(Z) - 1) - 1
    assert s["overall"]["u"]["gain"] == pytest.approx(1.0, abs=1e-5)
    assert any("velocities (dt 0.002 s)" in n for n in s["notes"])


def test_human_output_is_a_table(tmp_path, truth, capsys):
    half = vectors(tmp_path / "half.h5", scale=0.5)
    assert main(["compare", str(half), str(truth)]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0] == f"vectors: {half}"
    assert "gain" in out and "bias vox" in out and "rms mm" in out
    row = next(ln for ln in lines if ln.strip().startswith("u "))
    assert row.split()[1] == "0.500"
    assert "v: no gain, the true v does not vary (rms 0.000 voxel)" in out
    assert "nan" not in out.lower()


def test_old_product_takes_its_grid_from_the_config(tmp_path):
    cfg = {"volume": GRID.to_dict(), "piv": {"windows": [[8, 8, 8], list(WINDOW)]}}
    p = vectors(tmp_path / "old.h5", grid=None, window=None, config=cfg)
    vec = load_vectors(p)
    assert vec.window_vox == WINDOW and vec.grid.shape == GRID.shape
    assert np.allclose(vec.grid.origin, GRID.origin) and np.allclose(vec.grid.voxel,
                                                                      GRID.voxel)


# ---- bad input ------------------------------------------------------------------------------

@pytest.fixture
def bad_inputs(tmp_path):
    from plenopiv.camera.corrections import DepthCorrection
    from plenopiv.products.hdf5 import write_h5
    from plenopiv.products.volume import VolumeResult

    d = tmp_path
    vectors(d / "truth.h5")
    vectors(d / "wider.h5", x=X + 0.1e-3)                # the same shape, shifted in x
    vectors(d / "nogrid.h5", grid=None, window=None)
    empty = np.zeros((0, 3))
    VolumeResult(np.zeros(GRID.shape, np.float32), GRID, DepthCorrection(), empty, empty,
                 np.zeros(0), empty).save(d / "volume.h5")
    write_h5(d / "notruth.h5", {"/image_a": np.zeros((4, 4))}, kind="synthetic pair")
    (d / "text.h5").write_text("not hdf5")
    return d


BAD = [
    ("vectors-missing", "{d}/none.h5 {d}/truth.h5", "VECTORS file '{d}/none.h5' not found"),
    ("truth-missing", "{d}/truth.h5 {d}/none.h5", "TRUTH file '{d}/none.h5' not found"),
    ("vectors-is-volume", "{d}/volume.h5 {d}/truth.h5",
     "VECTORS '{d}/volume.h5' is a plenopiv volume file: expected a vectors product"),
    ("vectors-not-hdf5", "{d}/text.h5 {d}/truth.h5", "VECTORS '{d}/text.h5' is not an HDF5"),
    ("truth-is-volume", "{d}/truth.h5 {d}/volume.h5",
     "TRUTH '{d}/volume.h5' is a plenopiv volume file: expected a synthetic pair"),
    ("pair-without-truth", "{d}/truth.h5 {d}/notruth.h5",
     "TRUTH '{d}/notruth.h5' is a synthetic pair without its truth (no /truth/position_a_m"),
    ("grids-differ", "{d}/truth.h5 {d}/wider.h5",
     "VECTORS '{d}/truth.h5' and TRUTH '{d}/wider.h5' are on different grids"),
    ("no-grid", "{d}/nogrid.h5 {d}/truth.h5", "VECTORS '{d}/nogrid.h5' holds no voxel grid"),
    ("bands-0", "{d}/truth.h5 {d}/truth.h5 --bands 0", "--bands 0"),
]


@pytest.mark.parametrize("case", BAD, ids=[c[0] for c in BAD])
def test_bad_input_is_one_clear_error(case, bad_inputs, capsys):
    _, argv, words = case
    d = str(bad_inputs)
    code = main(["compare", *argv.replace("{d}", d).split(), "--json"])
    out, err = capsys.readouterr()
    assert code == 2 and "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("error: ")]
    assert len(lines) == 1 and words.replace("{d}", d) in lines[0], err
    assert strict_loads(out)["exit_status"] == 2


def test_grids_error_names_both_grids(bad_inputs, capsys):
    main(["compare", str(bad_inputs / "truth.h5"), str(bad_inputs / "wider.h5")])
    err = capsys.readouterr().err
    assert "VECTORS: " in err and "TRUTH: " in err and "x -0.4 to " in err and "x -0.3 to " in err


# ---- the pieces ------------------------------------------------------------------------------

def test_window_mean_counts_particles_on_the_edges():
    class Centres:
        x = np.array([0.0, 1.0, 2.0])
        y = np.array([0.0])
        z = np.array([0.0, 1.0])

    pos = np.array([[1.0, 0.0, 0.0], [2.0, 0.0, 1.0], [0.5, 0.0, 0.5]])
    disp = np.array([[1.0, 2.0, 3.0], [3.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    mean, count = window_mean_displacement(Centres, pos, disp, (2.0, 2.0, 1.0))
    # (1, 0, 0) lies in the windows centred at x 0, 1, 2 (edges count), z 0 only;
    # (0.5, 0, 0.5) in those at x 0, 1 and z 0, 1; (2, 0, 1) at x 1, 2 and z 1
    assert count[0].tolist() == [[2, 2, 1]] and count[1].tolist() == [[1, 2, 1]]
    assert mean[0, 0, 0, 0] == pytest.approx(3.0) and mean[1, 0, 0, 0] == pytest.approx(1.0)
    assert mean[0, 1, 0, 2] == pytest.approx(3.0)


def test_field_accuracy_without_vectors_says_so():
    acc = field_accuracy(np.zeros((3, 4)), np.zeros((3, 4)), np.zeros(4), (1, 1, 1),
                         mask=np.zeros(4, bool))
    assert acc["n_vectors"] == 0 and acc["bands"] == []
    assert np.isnan(acc["overall"]["u"]["gain"]) and "no vector to compare" in acc["notes"][0]
    with pytest.raises(ValueError, match="bands"):
        field_accuracy(np.zeros((3, 4)), np.zeros((3, 4)), np.zeros(4), (1, 1, 1), bands=0)


# ---- against a simulated pair: the small chain once ------------------------------------------

EXPERIMENT = """camera = "small_m1"
[volume]
x_mm = [-1.9375, 1.9375]
y_mm = [-1.3125, 1.3125]
z_mm = [-2.0625, 2.0625]
voxel_mm = 0.125
[piv]
windows = [[12, 12, 12]]
passes = 2
uncertainty = "correlation"
[output]
png = false
vtk = false
weights_cache = ""
"""


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    """simulate pair -> reconstruct A and B -> piv, through the command, on small_m1."""
    from plenopiv.calibration.model import Calibration
    from plenopiv.camera.model import load_camera

    d = tmp_path_factory.mktemp("chain")
    (d / "exp.toml").write_text(EXPERIMENT)
    Calibration.from_camera(load_camera("small_m1")).save(d / "cal.h5")
    steps = [
        ["simulate", "pair", "small_m1", "--out", f"{d}/pair.h5", "--fill", "0.45",
         "--depth-mm", "-2", "2", "--particles-per-lenslet", "0.15", "--rays-per-particle",
         "1024", "--max-displacement-mm", "0.25", "--no-tiff", "--seed", "3"],
        ["reconstruct", f"{d}/cal.h5", f"{d}/pair.h5:/image_a", "--config", f"{d}/exp.toml",
         "--out", f"{d}/va.h5"],
        ["reconstruct", f"{d}/cal.h5", f"{d}/pair.h5:/image_b", "--config", f"{d}/exp.toml",
         "--out", f"{d}/vb.h5"],
        ["piv", f"{d}/va.h5", f"{d}/vb.h5", "--config", f"{d}/exp.toml", "--out",
         f"{d}/vectors.h5", "--no-png", "--no-vtk"],
    ]
    for argv in steps:
        assert main([*argv, "--json", "--quiet"]) == 0, argv
    return d


def test_against_the_simulated_pair_flow(chain, capsys):
    d = chain
    capsys.readouterr()
    code, s, _ = compare(capsys, d / "vectors.h5", d / "pair.h5")
    assert code == 0
    assert s["truth_kind"] == "simulated pair" and s["truth_at_vectors"] == "flow"
    assert s["voxel_m"] == pytest.approx([0.125e-3] * 3)
    assert s["n_vectors"] >= 10
    assert s["notes"][0].startswith("truth: the oseen flow recorded in pair.h5 (rebuilt")
    # the vortex about y: no true v; u and w measured in the right direction, at most at size
    assert s["overall"]["v"]["gain"] is None
    assert "v: no gain, the true v does not vary (rms 0.000 voxel)" in s["notes"]
    for c in "uw":
        assert 0.2 < s["overall"][c]["gain"] < 1.3
        assert s["overall"][c]["correlation"] > 0.7
        assert s["overall"][c]["rms"] < s["overall"][c]["true_rms"]


def test_window_mean_where_the_flow_cannot_be_rebuilt(chain, tmp_path, capsys):
    d = chain
    capsys.readouterr()
    pair = tmp_path / "pair.h5"
    shutil.copy(d / "pair.h5", pair)
    with h5py.File(pair, "r+") as fh:
        cfg = json.loads(fh.attrs["config"])
        cfg["flow"]["kind"] = "tornado"
        fh.attrs["config"] = json.dumps(cfg)
    code, s, _ = compare(capsys, d / "vectors.h5", pair)
    assert code == 0 and s["truth_at_vectors"] == "window mean"
    assert "not the recorded flow: its flow 'tornado' is not one of" in s["notes"][0]
    assert s["overall"]["v"]["gain"] is None
    _, by_flow, _ = compare(capsys, d / "vectors.h5", d / "pair.h5")
    for c in "uw":
        # the window mean is the vortex smoothed over 1.5 mm windows: smaller than the flow at
        # the centres (0.75 against 0.98 voxel here), and nearer what PIV measures, a window
        # average too (gain 0.97 and 0.69 against 0.73 and 0.51)
        win, flow = s["overall"][c], by_flow["overall"][c]
        assert 0.5 * flow["true_rms"] < win["true_rms"] < flow["true_rms"]
        assert flow["gain"] < win["gain"] < 1.3 and win["correlation"] > 0.7
