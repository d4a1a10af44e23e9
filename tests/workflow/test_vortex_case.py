"""Whole chain on synthetic flows at the thesis geometry (50 mm lens, M = -1, Auburn optics) on the
41 x 61-lenslet CI camera: calibration images -> calibration -> pair -> volumes -> 3-D PIV ->
errors against the true displacement. The full study is docs/validation/vortex.md.

Targets (issues 7 and 13): rms <= 0.2 voxel lateral and <= 1 voxel in depth, in voxels of the
thesis's grid (the lenslet footprint, 0.125 mm); the depth component at its true size (gain,
the least-squares slope of measured on true w, 0.8-1.2); a uniform depth shift within 0.1
voxel. The flows here are rendered at 0.3 particles per lenslet with Poisson noise and a
Gaussian point spread of 0.5 px, reconstructed and correlated with the library's defaults
(footprint voxels, lateral subdivision 3, overlap-corrected peak fit).
"""

from __future__ import annotations

import numpy as np
import pytest

from plenopiv.camera.resolution import footprint
from plenopiv.workflow.vortex_case import VortexCase, case_camera, run_case

LATERAL, DEPTH = 0.2, 1.0
GAIN = (0.8, 1.2)
#: Share of the true errors within +-2 sigma (the held-out products bar).
COVERAGE = (0.85, 0.99)
#: The issue's renders: 0.3 particles per lenslet, Poisson noise, Gaussian PSF.
RENDER = dict(particles_per_lenslet=0.3, blur_px=0.5)


def _errors(tmp_path_factory, **kw) -> dict:
    case = VortexCase(**kw)
    s = run_case(case, tmp_path_factory.mktemp(kw["flow"]))
    e = s["errors"]
    k = case.lateral_oversampling
    # in footprints laterally (the thesis's voxel), in depth voxels along z
    e["rms_fp"] = [e["rms_vox"][0] / k, e["rms_vox"][1] / k, e["rms_vox"][2]]
    e["bias_fp"] = [e["bias_vox"][0] / k, e["bias_vox"][1] / k, e["bias_vox"][2]]
    e["products"] = s["products"]
    e["lateral_subdivision"] = s["lateral_subdivision"]
    return e


@pytest.fixture(scope="module")
def oseen(tmp_path_factory):
    return _errors(tmp_path_factory, flow="oseen", **RENDER)


@pytest.fixture(scope="module")
def hill(tmp_path_factory):
    return _errors(tmp_path_factory, flow="hill", **RENDER)


@pytest.fixture(scope="module")
def hill_correlated(tmp_path_factory):
    return _errors(tmp_path_factory, flow="hill", continuity=False, **RENDER)


def test_oseen_measures_w_at_its_size_within_the_rms_targets(oseen):
    """Lamb-Oseen, axis along y (particles move up to 2 voxels in depth), footprint voxels.

    Measured with w fitted to continuity (the default): w gain 0.96, u gain 1.01, rms 0.08,
    0.05, 0.15 voxel; as correlated and corrected by its tracks: w gain 0.79, rms w 0.48
    (0.16 with earlier defaults: footprint voxels reconstructed directly, plain 3-point peak
    fit). The CI camera's ±3 mm holds few vectors per band."""
    assert oseen["lateral_subdivision"] == [3, 3]
    assert oseen["valid_fraction"] > 0.85 and oseen["n_vectors"] > 100
    assert 0.65 <= oseen["gain"][2] <= GAIN[1]
    assert GAIN[0] <= oseen["gain"][0] <= GAIN[1]
    # farthest from focus, where every particle's depth is seen, w is at its size
    assert GAIN[0] <= oseen["by_depth"][-1]["gain"][2] <= GAIN[1]
    assert max(oseen["rms_fp"][:2]) <= LATERAL
    assert oseen["rms_fp"][2] <= DEPTH
    assert np.all(np.abs(oseen["bias_fp"]) <= [0.25 * LATERAL] * 2 + [0.25 * DEPTH])
    assert oseen["products"]["png_truth"].endswith(".png")


def test_oseen_w_gain_in_every_depth_band_on_the_ci_camera(oseen):
    """With w fitted to continuity (the default) the layers nearest focus, where a particle
    lights one lenslet, take the depth motion the lateral components imply: measured 0.96,
    0.97, 0.93 by |Z| band (0.70, 0.79, 0.97 without the fit). The vectors product says the
    fit was made."""
    import json

    import h5py

    assert all(GAIN[0] <= b["gain"][2] <= GAIN[1] for b in oseen["by_depth"])
    with h5py.File(oseen["products"]["vectors"]) as fh:
        record = json.loads(fh.attrs["continuity"])
    assert record["applied"] and record["chi2_per_vector"] <= record["max_chi2_per_vector"]


def test_hill_depth_target_and_no_bias(hill_correlated):
    """Hill's vortex, axis along x, the field as correlated and corrected by its tracks
    (``[piv] continuity = false``): depth within target, w near its size, no bias."""
    hill = hill_correlated
    assert hill["valid_fraction"] > 0.75
    assert hill["rms_vox"][2] <= DEPTH
    assert hill["gain"][2] >= 0.7
    assert np.all(np.abs(hill["bias_vox"]) <= 0.1)


def test_hill_fitted_to_continuity_is_as_resolved_as_its_lateral_motion(hill, hill_correlated):
    """The default fits w to continuity, which the lateral components set. Hill's vortex at
    0.3 particles per lenslet is resolved by these windows at 0.69 of its axial u (its
    variation lies along the deep depth window): the fit's w follows that, at a w gain of at
    least 0.9 of the lateral components' lowest (measured 0.66 against u's 0.69; 0.88 as
    correlated), while its rms and bias fall (0.21 against 0.31 voxel; bias 0.01)."""
    assert hill["rms_vox"][2] < hill_correlated["rms_vox"][2]
    assert abs(hill["bias_vox"][2]) <= 0.1 and hill["rms_vox"][2] <= DEPTH
    lateral = min(hill["gain"][0], hill["gain"][1])
    assert hill["gain"][2] >= 0.9 * lateral
    assert hill["gain"][:2] == hill_correlated["gain"][:2]     # u and v are not changed


def test_uncertainty_coverage_in_the_band_on_the_ci_camera(oseen, hill):
    """Per-vector uncertainty (correlation statistics, the iteration's remainder, the chain's
    measured response, the windows' curvature bias, the range a rejected neighbour leaves
    open): 85-99 % of the true errors within +-2 sigma per component on both flows, the band
    of the products' held-out bar, where the correlation statistics alone leave 31-62 % of
    the depth errors outside (docs/validation/uncertainty.md). About 180 vectors per flow: a
    sigma exactly right puts 95.45 % inside with a binomial standard error of 1.6 points, so
    it leaves this band with a chance of about 0.3 % per component (the narrower 90-98 %
    with about 4 %, 22 % over the six components: a test that failed a right sigma), while
    a sigma 30 % too small (84 % inside) leaves it with a chance of 63 %. Measured on these
    renders: Oseen u, v, w = 97.2, 95.0, 92.8 %, Hill 97.1, 93.1, 89.1 %."""
    for e in (oseen, hill):
        cov = np.asarray(e["coverage_2sigma"])
        assert np.all((cov >= COVERAGE[0]) & (cov <= COVERAGE[1])), cov


@pytest.mark.slow
def test_uncertainty_coverage_in_the_band_with_the_vortex_turned(tmp_path_factory):
    """Hill's vortex with its axis along y, a case the uncertainty model was not developed on
    (0.15 particles per lenslet, Poisson noise): 85-99 % of the true errors within +-2 sigma
    per component. The response's test pairs move laterally along x alone or diagonally;
    fitted along x and y apart, w got no shared error from motion along y, and this case's w
    was covered at 80.4 % (now 89.6; u, v 94.5, 96.9; docs/validation/uncertainty_loo.md)."""
    e = _errors(tmp_path_factory, flow="hill", flow_axis="y")
    cov = np.asarray(e["coverage_2sigma"])
    assert np.all((cov >= COVERAGE[0]) & (cov <= COVERAGE[1])), cov


def test_the_vortex_axis_of_a_case_turns_the_flow():
    """``flow_axis`` turns the vortex: Oseen about y by default (no v), about x (no u), about
    z (no w); Hill about x by default; an unknown axis is refused."""
    from plenopiv.workflow.vortex_case import aligned_grid, case_flow

    grid = aligned_grid(case_camera(VortexCase()), VortexCase())
    pts = np.random.default_rng(0).uniform(-1e-3, 1e-3, (200, 3))
    for kw, still in ((dict(), 1), (dict(flow_axis="y"), 1), (dict(flow_axis="x"), 0),
                      (dict(flow_axis="z"), 2), (dict(flow="hill", flow_axis="z"), None)):
        vel = case_flow(VortexCase(**kw), grid)(pts)
        if still is not None:
            assert np.abs(vel[:, still]).max() < 1e-12 * np.abs(vel).max(), kw
    hill = case_flow(VortexCase(flow="hill"), grid)
    assert tuple(hill.axis) == (1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="flow_axis"):
        VortexCase(flow_axis="w")


@pytest.mark.xfail(strict=True, reason=(
    "measured 0.24 voxel in x: on the CI camera the sphere (radius 1.7 mm) spans about two "
    "12-voxel windows, which average its gradients away (u gain 0.66); on the 61 x 91-lenslet "
    "patch the same chain measures 0.15 (docs/validation/vortex.md)"))
def test_hill_lateral_target_on_the_ci_camera(hill):
    assert max(hill["rms_vox"][:2]) <= LATERAL


def test_uniform_depth_shift_is_measured_within_a_tenth_of_a_voxel(tmp_path_factory):
    """Every particle moves one depth voxel (0.125 mm) along z.

    Before issue 13 the chain measured 0.5 of it (reconstructed particles 10-20 voxels long
    that moved by a third of the shift, and a peak fit pulled towards zero by the window
    border); the docs give 0.5, 1, 1.5 and 2 voxels."""
    shift = 1.0 * footprint(case_camera(VortexCase()))     # depth voxel = footprint here
    e = _errors(tmp_path_factory, flow="uniform", uniform_axis="z", max_displacement=shift,
                **RENDER)
    assert e["valid_fraction"] > 0.85
    assert abs(e["bias_vox"][2]) <= 0.1
    assert abs(e["by_depth"][-1]["bias_vox"][2]) <= 0.05     # away from focus
    assert np.all(np.abs(e["bias_vox"][:2]) <= 0.02)          # no lateral motion made up
    assert e["rms_vox"][2] <= 0.4


def test_sub_voxel_lateral_shift_footprint_and_half_footprint_voxels(tmp_path_factory):
    """A uniform shift of 1.25 lenslet footprints along x (0.15 particles per lenslet).

    In focus, the position of a particle inside a lenslet footprint does not change the
    image, so footprint-sized voxels pull displacements towards whole footprints (peak
    locking: -0.097 footprint before the subdivided reconstruction and its Gaussian merge,
    -0.039 with them); halving the voxel lets the out-of-focus views place the particle.
    """
    shift = 1.25 * footprint(case_camera(VortexCase()))     # the CI camera's footprint
    coarse = _errors(tmp_path_factory, flow="uniform", max_displacement=shift)
    fine = _errors(tmp_path_factory, flow="uniform", max_displacement=shift,
                   lateral_oversampling=2)
    assert -0.1 < coarse["bias_fp"][0] < 0.0               # still locked towards 1 footprint
    assert abs(fine["bias_fp"][0]) < 0.02
    assert fine["rms_fp"][0] <= LATERAL and coarse["rms_fp"][0] <= LATERAL
    assert fine["rms_fp"][2] <= DEPTH and coarse["rms_fp"][2] <= DEPTH


def test_a_window_touching_the_volume_s_face_counts_as_inside_wherever_the_grid_lies():
    """The vectors of windows that tile a grid from its first voxel have their centres exactly
    half a window from the faces; they count as inside for grids whose origins differ by a
    random fraction of a voxel (float rounding must not drop a layer), and a vector a tenth
    of a voxel nearer a face does not."""
    from types import SimpleNamespace

    from plenopiv.camera.grid import VolumeGrid
    from plenopiv.workflow.compare import inner_vectors

    rng = np.random.default_rng(11)
    window = (12, 24, 24)                                  # (z, y, x) voxels
    for _ in range(50):
        voxel = rng.uniform(0.03e-3, 0.2e-3, 3)
        shape = (rng.integers(3, 6) * 12, rng.integers(3, 6) * 24, rng.integers(3, 6) * 24)
        origin = rng.uniform(-5e-3, 5e-3, 3) + rng.uniform(0.0, 1.0, 3) * voxel
        grid = VolumeGrid(tuple(origin), tuple(voxel), tuple(int(n) for n in shape))
        centres = [grid.origin[a] + grid.voxel[a] * (
            (window[2 - a] - 1) / 2 + window[2 - a] / 2 * np.arange(2 * grid.shape[2 - a]
                                                                   // window[2 - a] - 1))
            for a in range(3)]
        vectors = SimpleNamespace(x=centres[0], y=centres[1], z=centres[2])
        assert inner_vectors(vectors, grid, window).all()
        nearer = SimpleNamespace(x=centres[0] - 0.1 * voxel[0], y=centres[1], z=centres[2])
        inside = inner_vectors(nearer, grid, window)
        assert not inside[:, :, 0].any() and inside[:, :, 1:].all()
