"""The particle-noise study's pieces on one small case: blobs, scores, pooling, the page."""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.studies.particle_noise import (
    ESTIMATORS,
    NOISE_LEVELS,
    blob_volume,
    cell_options,
    markdown,
    score,
    summary,
)

pytestmark = pytest.mark.study


def test_blobs_peak_at_their_truth(rng):
    """Noise-free blobs: each one's brightest voxel is the one holding its centre, a blob
    centred on a voxel has 1 there, and every estimator finds every blob, within 0.25 voxel
    and 0.1 rms (laterally the blobs are half a voxel wide: the voxel integral is no sampled
    Gaussian, and the centroid's ±1-voxel box takes in a neighbour's tail)."""
    sigma = (1.9, 0.5, 0.5)
    vol, centres, peaks = blob_volume(sigma, rng, shape=(40, 24, 24))
    assert len(centres) > 10 and np.all(peaks <= 1.0 + 1e-12) and np.all(peaks > 0.3)
    nearest = np.round(centres).astype(int)
    # the neighbours' tails: a lattice node 3 voxels away, jittered to 2 (4 sigma), adds
    # Q(3) = 1.3e-3 of its peak
    np.testing.assert_allclose(vol[tuple(nearest.T)], peaks, rtol=3e-3)
    opts = cell_options(sigma)
    assert opts["box_vox"] == (4, 1, 1)
    found = score(vol, centres, opts, 0.1)
    assert found["n_matched"] == found["n_found"] == len(centres)
    for err in found["errors"].values():
        assert np.abs(err).max() < 0.25 and np.sqrt(np.mean(err**2)) < 0.1
    one = blob_volume(sigma, np.random.default_rng(0), shape=(14, 6, 6))
    assert len(one[1]) == 1


def test_summary_and_page(rng):
    sigma = (3.8, 1.0, 1.0)
    vol, centres, peaks = blob_volume(sigma, rng, shape=(48, 30, 30))
    noisy = vol + rng.normal(0.0, 0.03, vol.shape)
    parts = [score(noisy, centres, cell_options(sigma), 0.2, noise_sigma=0.03, peaks=peaks)]
    s = summary(parts * 2)
    assert s["n_true"] == 2 * len(centres) and s["spurious"] == 0.0
    assert set(s["estimators"]) == set(ESTIMATORS)
    for e in s["estimators"].values():
        assert max(e["rms_vox"]) < 0.5 and max(np.abs(e["bias_vox"])) < 0.2
    row = {"blob": "b", "sigma_vox": list(sigma), "noise": 0.03, "clipped": False,
           "sigma_ratio": 1.0, "relative": s, "default": s}
    rec = {"density_ppl": 0.05, "noise": 0.0, "relative": s,
           "default": {**s, "noise_over_relative": 0.1}}
    page = markdown({"synthetic": [row], "reconstructed": [rec], "seconds": 1.0,
                     "noise_only": [{"noise": n, "peaks_per_voxel": {"0": 1e-3, "5": 1e-4}}
                                    for n in NOISE_LEVELS[1:]],
                     "noise_sigmas": 5.0, "default_method": "gaussian"})
    assert page.count("| b | 0.03 |") == 1 + len(ESTIMATORS)
