"""The correlation field corrected by the pair's tracks (plenopiv.tracking.correction)."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from plenopiv.camera.grid import VolumeGrid
from plenopiv.products.vectors import VectorResult
from plenopiv.tracking.correction import (
    KERNEL_FRACTION,
    KERNEL_REACH,
    correct_with_tracks,
    residual_weights,
)
from plenopiv.tracking.settings import TrackingSettings
from plenopiv.tracking.tracks import TrackResult

VOXEL = 1e-4                      # metres
WINDOW = (12, 12, 12)             # voxels (z, y, x)
SPACING = 6 * VOXEL               # 50 % overlap


def _field(fn, shape=(6, 7, 8)):
    """A VectorResult on a regular grid with displacement ``fn(x, y, z) -> (u, v, w)``."""
    nz, ny, nx = shape
    x, y, z = (SPACING * np.arange(n) for n in (nx, ny, nz))
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    u, v, w = fn(X, Y, Z)
    grid = VolumeGrid(origin=(0.0, 0.0, 0.0), voxel=(VOXEL, VOXEL, VOXEL),
                      shape=(6 * nz, 6 * ny, 6 * nx))
    return VectorResult(x, y, z, u, v, w, np.ones(shape, bool), np.ones(shape), grid=grid,
                        window_vox=WINDOW)


def _tracks(mid, disp):
    n = len(mid)
    z, i = np.zeros(n), np.arange(n)
    return TrackResult(mid - 0.5 * disp, mid + 0.5 * disp, np.zeros((n, 3)), np.zeros((n, 3)),
                       z, z, i, i, np.full(n, 9), np.full(n, 9))


def _shear(gain_w):
    """A shear flow whose w the 'correlation' measures with ``gain_w``."""
    def fn(X, Y, Z):
        return 1e-5 * np.ones_like(X), np.zeros_like(X), gain_w * 4e-5 * np.sin(X / 1e-3)
    return fn


def _shear_tracks(n, rng, extent):
    """``n`` tracks of the true shear, mid-points uniform in ``[0, extent]`` (x, y, z)."""
    mid = rng.uniform(0, 1, (n, 3)) * np.asarray(extent, float)
    return mid, np.stack(_shear(1.0)(mid[:, 0], mid[:, 1], mid[:, 2]), axis=1)


def test_sparse_kernel_matches_its_dense_numpy_twin():
    rng = np.random.default_rng(3)
    nodes, points = rng.uniform(0, 5, (40, 3)), rng.uniform(0, 5, (25, 3))
    points[0] = nodes[7]                       # a track on a vector: distance zero
    sigma = np.array([0.7, 1.1, 1.6])
    d = (nodes[:, None, :] - points[None, :, :]) / sigma
    r2 = (d ** 2).sum(-1)
    dense = np.where(r2 <= KERNEL_REACH ** 2, np.exp(-0.5 * r2), 0.0)
    k = residual_weights(nodes, points, sigma).toarray()
    assert np.allclose(k, dense, rtol=1e-12, atol=0)
    assert k[7, 0] == 1.0


def test_tracks_that_agree_with_the_field_change_nothing():
    vec = _field(_shear(1.0))
    mid, true = _shear_tracks(200, np.random.default_rng(1), [5 * SPACING] * 3)
    # the field is linear between vectors only approximately: the residual is the
    # interpolation's error, a sine over 10 vector spacings sampled at 1/6 of a period
    out, info = correct_with_tracks(vec, _tracks(mid, true), prior_tracks=1.0)
    assert info.tracks == 200
    assert np.max(np.abs(out.w - vec.w)) < 0.05 * 4e-5
    assert np.array_equal(out.u, vec.u) or np.max(np.abs(out.u - vec.u)) < 1e-12


def test_no_track_leaves_the_field_as_it_is():
    vec = _field(_shear(0.8))
    out, info = correct_with_tracks(vec, _tracks(np.zeros((0, 3)), np.zeros((0, 3))),
                                    prior_tracks=1.0)
    assert info.tracks == 0
    for c in "uvw":
        assert np.array_equal(getattr(out, c), getattr(vec, c))


def test_a_track_on_a_vector_moves_it_by_the_prior_share_of_its_residual():
    vec = _field(lambda X, Y, Z: (0 * X, 0 * X, 0 * X))
    node = np.array([[vec.x[3], vec.y[3], vec.z[2]]])
    for prior in (0.5, 1.0, 4.0):
        out, _ = correct_with_tracks(vec, _tracks(node, np.array([[0.0, 0.0, 3e-5]])),
                                     prior_tracks=prior)
        assert out.w[2, 3, 3] == pytest.approx(3e-5 / (1.0 + prior), rel=1e-12)
        # a vector two kernel widths away takes exp(-2) of the weight
        sigma = KERNEL_FRACTION * WINDOW[2] * VOXEL
        far = np.argmin(np.abs(vec.x - (vec.x[3] + 2 * sigma)))
        k = np.exp(-0.5 * ((vec.x[far] - vec.x[3]) / sigma) ** 2)
        assert out.w[2, 3, far] == pytest.approx(3e-5 * k / (k + prior), rel=1e-9)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_biased_depth_component_is_brought_toward_the_truth(seed):
    # the correlation measures w at 0.7 of the flow; unbiased tracks, 2.4 per vector cell,
    # with noise of a fifth of the amplitude. Inside, a vector sums about 11 tracks' kernel
    # weight (2.4 (2 pi)^1.5 (2/3)^3), so it takes 11/12 of their mean residual, which the
    # kernel smooths by exp(-(sigma/1 mm)^2 / 2) = 0.92: about 85 % of the bias goes, and the
    # noise left is 0.2/sqrt(11) of the amplitude. Expected: the rms w error falls to about a
    # third, the gain to 0.7 + 0.3 * 0.85 = 0.95
    truth, seen = _field(_shear(1.0)), _field(_shear(0.7))
    rng = np.random.default_rng(seed)
    extent = np.array([seen.x[-1], seen.y[-1], seen.z[-1]])
    mid, disp = _shear_tracks(int(2.4 * np.prod(extent / SPACING)), rng, extent)
    disp[:, 2] += rng.normal(0, 0.2 * 4e-5, len(mid))
    out, _ = correct_with_tracks(seen, _tracks(mid, disp), prior_tracks=1.0)
    inner = (slice(1, -1),) * 3          # a vector on the edge has half its tracks
    err_before = np.sqrt(np.mean((seen.w - truth.w)[inner] ** 2))
    err_after = np.sqrt(np.mean((out.w - truth.w)[inner] ** 2))
    gain = np.polyfit(truth.w[inner].ravel(), out.w[inner].ravel(), 1)[0]
    assert err_after < 0.5 * err_before
    assert 0.88 < gain < 1.02


def test_the_field_moved_is_corrected_alike():
    # invariance: the same flow and tracks shifted by an arbitrary offset give the same
    # correction (the kernel depends on distances only)
    vec = _field(_shear(0.7))
    mid, disp = _shear_tracks(150, np.random.default_rng(5), [5 * SPACING] * 3)
    base, _ = correct_with_tracks(vec, _tracks(mid, disp), prior_tracks=1.0)
    shift = np.array([0.37e-3, -1.21e-3, 2.05e-3])
    moved = VectorResult(vec.x + shift[0], vec.y + shift[1], vec.z + shift[2], vec.u, vec.v,
                         vec.w, vec.valid, vec.snr, grid=vec.grid, window_vox=WINDOW)
    out, _ = correct_with_tracks(moved, _tracks(mid + shift, disp), prior_tracks=1.0)
    assert np.allclose(out.w, base.w, rtol=0, atol=1e-12)


def test_a_field_without_its_window_is_refused_by_name():
    vec = _field(_shear(1.0))
    bare = VectorResult(vec.x, vec.y, vec.z, vec.u, vec.v, vec.w, vec.valid, vec.snr)
    with pytest.raises(ValueError, match="window_vox"):
        correct_with_tracks(bare, _tracks(np.zeros((1, 3)), np.zeros((1, 3))),
                            prior_tracks=1.0)


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), "one"])
def test_prior_tracks_must_be_a_positive_number(bad):
    with pytest.raises(ValidationError, match="prior_tracks"):
        TrackingSettings(prior_tracks=bad)


def test_masked_vectors_stay_masked_and_their_tracks_are_left_out():
    # NaN vectors (a [mask] box, unreplaced rejections) stay NaN; a track whose mid-point
    # interpolates a NaN is not used; the finite vectors are corrected by the others
    vec = _field(_shear(0.7))
    w = vec.w.copy()
    w[:, :, :2] = np.nan
    masked = VectorResult(vec.x, vec.y, vec.z, vec.u, vec.v, w, vec.valid, vec.snr,
                          grid=vec.grid, window_vox=WINDOW)
    mid, disp = _shear_tracks(400, np.random.default_rng(2), [vec.x[-1], vec.y[-1], vec.z[-1]])
    out, info = correct_with_tracks(masked, _tracks(mid, disp), prior_tracks=1.0)
    assert np.all(np.isnan(out.w[:, :, :2]))
    assert np.all(np.isfinite(out.w[:, :, 2:]))
    assert info.tracks == int(np.sum(mid[:, 0] > vec.x[2]))
