"""Reconstruction quality of particle fields (pipelines.studies.field_quality).

A 41 × 61-lenslet patch of the 50 mm / M = -1 camera, particles in |Z| <= 3 mm, seeded at a
sparse (0.05 ppl) and a dense (0.3 ppl) density, reconstructed on voxels of half a lenslet
footprint laterally (a footprint-wide voxel is wider than the image of a point particle, and
the soft line-of-sight mask then removes particles near a footprint corner: see the study).
The bounds follow from the resolution cell (lateral: one footprint b = 0.125 mm; depth:
ΔZ = b S_o/D = 0.55 mm), not from a past run.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipelines.studies import field_quality as fq
from plenopiv.calibration.model import Calibration
from plenopiv.reconstruction.settings import ReconstructionSettings

pytestmark = pytest.mark.study

DEPTH = 3e-3          # particles in |Z| <= 3 mm, grid ±3.5 mm: a small, fast volume
SPARSE, DENSE = 0.05, 0.3


def test_resolution_cell_of_the_50mm_lens():
    cam = fq.study_camera(11, 11)
    lateral, depth = fq.resolution_cell(cam)
    assert lateral == pytest.approx(125e-6)                       # p_m S_o/S_i at M = -1
    assert depth == pytest.approx(125e-6 * 0.1 / (0.05 / 2.2))    # b S_o / D = 0.55 mm
    assert fq.footprint(cam) == pytest.approx(lateral)


def test_match_particles_one_to_one_closest_first():
    tol = (1.0, 1.0, 4.0)
    true = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    found = np.array([[0.5, 0.0, 0.0], [0.1, 0.0, 1.0], [10.0, 0.0, 3.9], [20.0, 0.0, 0.0]])
    pairs = fq.match_particles(true, found, tol)
    # found 1 is closer to true 0 in units of the tolerance (0.25 against 0.5): it wins;
    # found 2 lies inside the ellipsoid of true 1 (3.9/4 < 1); found 0 and 3 stay unmatched
    assert sorted(map(tuple, pairs)) == [(0, 1), (1, 2)]
    assert len(fq.match_particles(true, [[0.0, 0.0, 4.1]], tol)) == 0
    assert fq.match_particles(true, np.zeros((0, 3)), tol).shape == (0, 2)


def test_q_against_the_true_brightness_is_one_for_the_true_volume():
    """A volume that holds each particle's blob as bright as the particle has Q = 1 against
    blobs weighted by brightness; against equal blobs its Q is E[b]/sqrt(E[b²]) for blobs
    of equal weight that do not overlap, exp(-σ²/2) for a log-normal spread σ."""
    from plenopiv.synthetic.truth import gaussian_truth_volume

    cam = fq.study_camera(41, 61)
    grid = fq.study_grid(cam, depth=DEPTH + 0.5e-3)
    pos = fq.isolated_field(grid, cam, np.random.default_rng(3), depth=DEPTH)
    sigma, sig = 0.3, fq.cell_sigma(grid, cam)
    bright = np.random.default_rng(4).lognormal(0.0, sigma, len(pos))
    true = gaussian_truth_volume(grid, pos, bright, sigma_vox=sig)
    assert fq.field_q(true, grid, pos, sig, intensities=bright) == pytest.approx(1.0, abs=1e-6)
    equal = fq.field_q(true, grid, pos, sig)
    # (to 0.005: a blob cut by the grid's depth ends weighs less than the others)
    assert equal == pytest.approx(bright.mean() / math.sqrt(np.mean(bright ** 2)), abs=5e-3)
    assert equal == pytest.approx(math.exp(-sigma ** 2 / 2), abs=0.03)   # sampling of N
    # lists of volumes take a list of intensities
    assert fq.field_q([true, true], grid, [pos, pos], sig,
                      intensities=[bright, bright]) == pytest.approx(1.0, abs=1e-6)


def test_isolated_particles_share_no_micro_image():
    cam = fq.study_camera(41, 61)
    grid = fq.study_grid(cam, depth=DEPTH + 0.5e-3)
    pos = fq.isolated_field(grid, cam, np.random.default_rng(3), depth=DEPTH)
    d = np.hypot(*(pos[:, None, :2] - pos[None, :, :2]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    # blur discs on the focal plane are at most 2 × interior_margin wide
    assert d.min() > 2 * fq.interior_margin(cam, DEPTH)
    assert np.all(np.abs(pos[:, 2]) <= DEPTH)
    assert fq.Region(grid, fq.interior_margin(cam, DEPTH)).contains(pos).all()


def test_seed_field_density(rng):
    cam = fq.study_camera(41, 61)
    grid = fq.study_grid(cam)
    pos = fq.seed_field(grid, cam, 0.2, rng, depth=DEPTH)
    assert len(pos) == round(0.2 * 41 * 61)          # the grid spans the lenslet footprints
    b = grid.bounds
    assert np.all((pos >= [b[0, 0], b[1, 0], -DEPTH]) & (pos <= [b[0, 1], b[1, 1], DEPTH]))


@pytest.fixture(scope="module")
def study():
    """Sparse and dense fields reconstructed with MLOS, SMART and row-action MART."""
    rng = np.random.default_rng(20261122)
    cam = fq.study_camera(41, 61)
    cal = Calibration.from_camera(cam)
    grid = fq.study_grid(cam, depth=DEPTH + 0.5e-3, subdivision=2)
    weights = fq.study_weights(cal, grid)
    lateral, depth = fq.resolution_cell(cam)
    region = fq.Region(grid, fq.interior_margin(cam, DEPTH))
    sigmas = {"cell": fq.cell_sigma(grid, cam)}
    cases = {"mlos": ReconstructionSettings(iterations=0),
             "smart": ReconstructionSettings(method="smart", iterations=5, relaxation=1.0),
             "mart": ReconstructionSettings(method="mart", iterations=5, relaxation=1.0),
             "mart_relaxed": ReconstructionSettings(method="mart", iterations=5,
                                                    relaxation=0.03)}
    out = {"camera": cam, "grid": grid}
    for k, density in enumerate((SPARSE, DENSE)):
        pos = fq.seed_field(grid, cam, density, rng, depth=DEPTH)
        img = fq.render(cam, pos, seed=k)
        for name, s in cases.items():
            row, _ = fq.reconstruct_and_score(cal, img, weights, pos, settings=s,
                                              particles=fq.particle_settings(grid, cam),
                                              tolerance=(lateral, lateral, depth),
                                              sigmas=sigmas, region=region)
            assert "error" not in row, row
            out[density, name] = row
    return out


def test_sparse_field_is_found(study):
    """At 0.05 ppl another particle lies in a given particle's resolution cell (π b² × 2ΔZ)
    with probability 0.05 × π × 2ΔZ / 6 mm ≈ 0.03, and three lines of sight from other
    particles meeting in one cell in every view are rarer still: ≥ 90 % of the particles are
    found, and ≤ 5 % of the detections are ghosts standing away from every true particle
    (second peaks of a real, depth-elongated particle are counted apart: ghost_near_rate)."""
    r = study[SPARSE, "smart"]
    assert r["n_true"] >= 60
    assert r["detection_rate"] >= 0.9
    assert r["ghost_rate"] - r["ghost_near_rate"] <= 0.05
    assert r["masked_rate"] <= 0.05


def test_position_errors_within_the_resolution_cell(study):
    """A particle found in its own footprint column has a lateral error of at most b/2, so an
    rms of at most b/√12 (uniform) even without sub-voxel information; in depth the matched
    errors must concentrate inside the ±ΔZ tolerance, below the ΔZ/√3 of a uniform spread."""
    lateral, depth = fq.resolution_cell(study["camera"])
    for density in (SPARSE, DENSE):
        r = study[density, "smart"]
        assert max(r["rms_m"][:2]) <= lateral / math.sqrt(12)
        assert r["rms_m"][2] <= depth / math.sqrt(3)
        # a plenoptic camera sees depth through a narrow aperture: elongated particles
        assert r["elongation"] >= 2.0


def test_iterations_remove_mlos_ghosts_at_high_density(study):
    """The MLOS first guess keeps voxels where lines of sight of different particles cross;
    at 0.3 ppl those intersections are a large part of its light. (Its dark pixels enter at the
    noise floor, plenopiv.reconstruction.sightline, which already removes part of them.) Iterations
    that
    enforce every view remove more: Q (cell-size truth) rises and the ghost rate falls."""
    mlos, smart = study[DENSE, "mlos"], study[DENSE, "smart"]
    assert smart["q"]["cell"] > mlos["q"]["cell"]
    assert smart["ghost_rate"] < mlos["ghost_rate"]


def test_quality_falls_with_density(study):
    """More particles, more crossing lines of sight: every method's detection rate falls from
    0.05 to 0.3 ppl, and the ghost rate of the MLOS guess and of SMART rises. (Q at the
    resolution cell need not fall: the floor-aware sub-cell MLOS, plenopiv.reconstruction.sightline,
    already empties most crossings, so Q of the guess is set by the depth elongation of each
    particle, which does not depend on density (measured 0.680 at 0.05 and 0.685 at 0.3 ppl); and Q
    weights voxels by E², so in a sparse field the iterations pile the light of particles near
    the focal plane into a few bright voxels; see docs/validation/field_quality.md.)"""
    for name in ("mlos", "smart"):
        assert study[DENSE, name]["ghost_rate"] > study[SPARSE, name]["ghost_rate"]
    for name in ("mlos", "smart", "mart_relaxed"):
        assert study[DENSE, name]["detection_rate"] < study[SPARSE, name]["detection_rate"]


def test_relaxed_row_action_mart_improves_on_mlos(study):
    """Each voxel is seen by ~200 pixels (about 50 times a 4-camera tomographic PIV set-up),
    so row-action MART needs μ of order 4/200 to take steps like μ = 1 there. Relaxed, it
    finds more particles than its MLOS first guess with fewer ghosts, and its Q stands well
    above that of μ = 1, which over-fits each pixel. (Row-action MART sees only the lit pixels:
    the dark pixels that enter the floor-aware MLOS guess and SMART as ceilings,
    plenopiv.reconstruction.sightline, do not constrain it, so it need not raise Q above that guess:
    measured 0.669 against 0.685; detection 0.88 against 0.79, ghosts 0.07 against 0.13.) The 0.05
    margin is over twice the binomial scatter of a detection rate of ~0.8 over the several
    hundred interior particles at 0.3 ppl (√(0.8·0.2/400) = 0.02)."""
    relaxed, guess = study[DENSE, "mart_relaxed"], study[DENSE, "mlos"]
    assert relaxed["detection_rate"] >= guess["detection_rate"] + 0.05
    assert relaxed["ghost_rate"] < guess["ghost_rate"]
    assert relaxed["q"]["cell"] >= study[DENSE, "mart"]["q"]["cell"] + 0.1


@pytest.mark.xfail(strict=True, reason="row-action MART at relaxation 1 over-fits each pixel "
                   "(each voxel is seen by ~200 pixels); see docs/validation/field_quality.md")
def test_row_action_mart_at_relaxation_1_improves_on_mlos(study):
    assert study[DENSE, "mart"]["q"]["cell"] >= study[DENSE, "mlos"]["q"]["cell"] + 0.1
