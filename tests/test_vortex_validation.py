"""Whole chain on synthetic flows at the thesis geometry (50 mm lens, M = -1, Auburn optics) on the
41 x 61-lenslet CI camera: calibration images -> calibration -> pair -> volumes -> 3-D PIV ->
errors against the true displacement. The full study is docs/validation/vortex.md.

Targets (issue): rms <= 0.2 voxel lateral and <= 1 voxel in depth, in voxels of the thesis's
grid (the lenslet footprint, 0.125 mm).
"""

from __future__ import annotations

import numpy as np
import pytest

from plenopiv.pipeline import footprint
from plenopiv.validation.vortex import VortexCase, case_camera, run_case

LATERAL, DEPTH = 0.2, 1.0


def _errors(tmp_path_factory, **kw) -> dict:
    case = VortexCase(**kw)
    s = run_case(case, tmp_path_factory.mktemp(kw["flow"]))
    e = s["errors"]
    k = case.lateral_oversampling
    # in footprints laterally (the thesis's voxel), in depth voxels along z
    e["rms_fp"] = [e["rms_vox"][0] / k, e["rms_vox"][1] / k, e["rms_vox"][2]]
    e["bias_fp"] = [e["bias_vox"][0] / k, e["bias_vox"][1] / k, e["bias_vox"][2]]
    e["products"] = s["products"]
    return e


@pytest.fixture(scope="module")
def oseen(tmp_path_factory):
    return _errors(tmp_path_factory, flow="oseen", lateral_oversampling=2)


@pytest.fixture(scope="module")
def hill(tmp_path_factory):
    return _errors(tmp_path_factory, flow="hill")


def test_oseen_meets_the_targets_with_half_footprint_voxels(oseen):
    """Lamb-Oseen, axis along y (particles move up to 2 voxels in depth)."""
    assert oseen["valid_fraction"] > 0.85 and oseen["n_vectors"] > 100
    assert max(oseen["rms_fp"][:2]) <= LATERAL
    assert oseen["rms_fp"][2] <= DEPTH
    # the mean error stays well inside the rms targets: no systematic drift of the chain
    assert np.all(np.abs(oseen["bias_fp"]) <= [0.25 * LATERAL] * 2 + [0.25 * DEPTH])
    assert oseen["products"]["png_truth"].endswith(".png")


def test_hill_depth_target_and_no_bias(hill):
    """Hill's vortex, axis along x: depth within target, every component unbiased."""
    assert hill["valid_fraction"] > 0.75
    assert hill["rms_vox"][2] <= DEPTH
    assert np.all(np.abs(hill["bias_vox"]) <= 0.1)


def test_uncertainty_covers_the_true_errors(oseen, hill):
    """Per-vector uncertainty (correlation statistics + last correction + the chain's measured
    response): most true errors within +-2 sigma in every component, where the correlation
    statistics alone leave 31-62 % of the depth errors outside (docs/validation/uncertainty.md).
    """
    for e in (oseen, hill):
        cov = np.asarray(e["coverage_2sigma"])
        assert np.all(cov >= 0.8) and np.all(cov <= 1.0), cov
        assert np.mean(cov) >= 0.9


@pytest.mark.xfail(strict=True, reason=(
    "measured on the CI camera: Oseen (half-footprint voxels) u, v, w = 94, 100, 85 %; Hill "
    "(footprint voxels) 88, 99, 100 %. The v of Oseen (no motion along y) is over-covered, "
    "the near-focus depth error of Oseen and the lateral error of the under-resolved Hill "
    "vortex are under-covered; docs/validation/uncertainty.md has all ten cases"))
def test_uncertainty_coverage_in_the_band_on_the_ci_camera(oseen, hill):
    for e in (oseen, hill):
        cov = np.asarray(e["coverage_2sigma"])
        assert np.all((cov >= 0.90) & (cov <= 0.98)), cov


@pytest.mark.xfail(strict=True, reason=(
    "measured 0.45 voxel in x: on the CI camera the sphere (radius 1.7 mm) spans about two "
    "12-voxel windows, and PIV of the exact particle volumes already errs by 0.28 voxel; "
    "the error falls with the vortex size, to 0.16 footprint on an 81 x 121-lenslet patch "
    "with half-footprint voxels (docs/validation/vortex.md)"))
def test_hill_lateral_target_on_the_ci_camera(hill):
    assert max(hill["rms_vox"][:2]) <= LATERAL


def test_footprint_voxels_lock_sub_voxel_shifts_and_half_footprints_do_not(tmp_path_factory):
    """A uniform shift of 1.25 lenslet footprints along x.

    In focus, the position of a particle inside a lenslet footprint does not change the
    image, so footprint-sized voxels pull displacements towards whole footprints (peak
    locking); halving the voxel lets the out-of-focus views place the particle.

    The locked part of the error is the mean (the bias); what remains about it, the scatter
    √(rms² - bias²), comes from reconstructing two differently sampled particle images, which
    a finer grid shares and cannot add to (at whole-footprint shifts, where the two images
    agree, both grids scatter by ≲ 0.05 footprint; docs/validation/vortex.md). So with
    half-footprint voxels the bias vanishes and the whole rms stays within the footprint
    voxels' scatter. (Measured: footprint voxels bias -0.119, rms 0.171, scatter 0.123; half
    footprints bias +0.005, rms 0.094. A ratio of the two rms is no physical bound: the
    scatter, not the lock, sets the half-footprint rms.)
    """
    shift = 1.25 * footprint(case_camera(VortexCase()))     # the CI camera's footprint
    coarse = _errors(tmp_path_factory, flow="uniform", max_displacement=shift)
    fine = _errors(tmp_path_factory, flow="uniform", max_displacement=shift,
                   lateral_oversampling=2)
    assert coarse["bias_fp"][0] < -0.05            # locked towards 1 footprint
    assert abs(fine["bias_fp"][0]) < 0.02
    scatter = np.sqrt(coarse["rms_fp"][0] ** 2 - coarse["bias_fp"][0] ** 2)
    assert fine["rms_fp"][0] < scatter
    assert fine["rms_fp"][0] <= LATERAL and fine["rms_fp"][2] <= DEPTH
