"""The invariance study's parts: its variations, the particle scorer, the single-lenslet depth
and the page (:mod:`pipelines.studies.invariance`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipelines.studies.invariance import (
    FOCUS_VARIATIONS,
    REFERENCE,
    VARIATIONS,
    base_case,
    focus_profile,
    markdown,
    particle_errors,
    single_lenslet_depth,
    summarise,
)
from plenopiv.workflow.vortex_case import VortexCase, case_camera

pytestmark = pytest.mark.study


@pytest.mark.parametrize("name", list(VARIATIONS))
def test_every_variation_is_a_valid_case_that_changes_something(name):
    case = dataclasses.replace(base_case(), **VARIATIONS[name])
    assert case.uncertainty == "correlation"
    assert case != base_case() or name == "axis y (preset)"
    case_camera(case)                          # the camera it varies can be built


def test_the_reference_and_the_focus_variations_are_variations():
    assert REFERENCE in VARIATIONS
    assert set(FOCUS_VARIATIONS) <= set(VARIATIONS)


def test_particle_errors_return_a_known_shift_and_scale(rng):
    true = rng.uniform(-2e-3, 2e-3, (200, 3))
    voxel = np.array([1e-4, 1e-4, 1e-4])
    found = true + np.array([1e-5, -2e-5, 0.0])
    found[:, 0] += 2e-3 * true[:, 0]
    out = particle_errors(found, true, voxel, (3e-4, 3e-4, 3e-4))
    assert out["n_matched"] == 200
    np.testing.assert_allclose(out["scale_error"], [2e-3, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(out["bias_vox"][1:], [-0.2, 0.0], atol=1e-9)


def test_single_lenslet_depth_of_the_preset():
    # p·S_i·N / (f·M²) = 0.125 mm · 100 mm · 2.2 / 50 mm at M = -1
    cam = case_camera(VortexCase())
    assert single_lenslet_depth(cam) == pytest.approx(0.55e-3, rel=1e-6)
    # a smaller stop widens the band in proportion
    wide = case_camera(VortexCase(f_number=2.8))
    assert single_lenslet_depth(wide) / single_lenslet_depth(cam) == pytest.approx(2.8 / 2.2)


@pytest.mark.slow
def test_a_particle_at_focus_loses_its_place_in_the_footprint():
    p = focus_profile("axis y (preset)", depths=(0.0, 1e-3))
    at_focus, off = (np.sqrt(np.mean(np.square(r["rms_vox"]))) for r in p["depths"])
    # uniform over a footprint: 1/sqrt(12) = 0.29 voxel; off focus a tenth of it
    assert 0.2 < at_focus < 0.4 and off < 0.06


def test_the_page_lists_every_variation_and_seed():
    rows = [{"variation": n, "seed": s, "gain": [np.nan, 1.0, 0.9],
             "bias_vox": [0.0, 0.01, -0.02], "rms_vox": [0.05, 0.15, 0.4],
             "true_rms_vox": [0.0, 1.4, 1.0], "voxel_mm": [0.125, 0.125, 0.125],
             "by_depth": [{"rms_vox": [0.05, r, 0.4]} for r in (0.2, 0.1, 0.05)],
             "particles": {"rms_vox": [0.1, 0.1, 0.9], "scale_error": [0.0, 1e-3, -4e-3]},
             "calibration": {"image_distance_error_mm": 0.003}}
            for n in (REFERENCE, "rotated 1.5 mrad") for s in (1, 2)]
    result = {"summary": summarise(rows), "seconds": 1.0}
    text = markdown(result, "python pipelines/validate_invariance.py")
    assert "| rotated 1.5 mrad | 1,2 |" in text and REFERENCE in text
    assert "| rotated 1.5 mrad | v | 0.200 | 0.100 | 0.050 | 18.8 | 125.0 |" in text
