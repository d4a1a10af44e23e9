"""Tracking: ray-bundle positions, PIV-guided matching, the tracks product, ``plenopiv track``."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from pipelines.studies.depth import thesis_camera
from plenopiv.calibration.model import Calibration
from plenopiv.camera.resolution import resolution_cell
from plenopiv.cli import main
from plenopiv.lightfield import light_field
from plenopiv.particles.bundle import (
    BundleSettings,
    bundle_positions,
    closest_point,
    closest_points,
    lit_rays,
    ray_lines,
    ray_table,
)
from plenopiv.particles.forward import ForwardSettings, beam_fraction, near_focus, refine_positions
from plenopiv.products.tracks import TRACK_DATASETS, write_tracks
from plenopiv.products.vectors import load_vectors
from plenopiv.synthetic.images import particle_image
from plenopiv.tracking.matching import (
    MatchSettings,
    interpolate_displacement,
    match_particles,
    neighbour_median_test,
    predict_positions,
)
from plenopiv.tracking.tracks import TrackResult, bin_tracks

# ---- least-squares point of a ray bundle ----------------------------------------------------


def test_exact_rays_through_a_point_return_it(rng):
    p = rng.normal(size=3)
    d = rng.normal(size=(50, 3))
    a = p + d * rng.uniform(-5, 5, (50, 1))        # points on lines through p
    w = rng.uniform(0.1, 2.0, 50)
    np.testing.assert_allclose(closest_point(a, d, w), p, atol=1e-10)
    # several bundles at once, each with its own point
    q = rng.normal(size=(4, 3))
    g = np.repeat(np.arange(4), 10)
    dd = rng.normal(size=(40, 3))
    aa = q[g] + dd * rng.uniform(-3, 3, (40, 1))
    pts, _, ok = closest_points(g, aa, dd, np.ones(40), 4)
    assert ok.all()
    np.testing.assert_allclose(pts, q, atol=1e-10)


def test_least_squares_point_of_two_skew_lines_is_their_midpoint():
    # x axis and a line along y at z = 2: the nearest point is half-way, (0, 0, 1)
    p = closest_point([[0, 0, 0], [0, 0, 2]], [[1, 0, 0], [0, 1, 0]])
    np.testing.assert_allclose(p, [0, 0, 1], atol=1e-12)


def test_parallel_lines_have_no_point():
    with pytest.raises(ValueError, match="do not define a point"):
        closest_point([[0, 0, 0], [1, 0, 0]], [[0, 0, 1], [0, 0, 1]])


@pytest.fixture(scope="module")
def thesis_light_field():
    cam = thesis_camera(lenslets=25, sensor_px=430)
    cal = Calibration.from_camera(cam)
    return cam, cal, light_field(cal)


@pytest.mark.parametrize("engine", ["numba", "numpy"])
@pytest.mark.parametrize("depth", [-3e-3, 2.5e-3])
@pytest.mark.study
def test_bundle_position_of_a_rendered_particle(thesis_light_field, depth, engine):
    """One particle off focus, seeded half a depth cell and a third of a footprint away.

    Tolerances from the optics: the lateral position averages the rays of ~30 lenslets whose
    conjugates are placed to a footprint b (σ ≈ b/√12/√30 ≈ 0.05 b), so 0.15 b; in depth the
    parallax over the aperture (angle R/S_o = 0.11) turns that into σ_z ≈ 0.05 b/0.11 ≈ 0.5 b:
    1.5 b, a quarter of the depth resolution cell (b S_o/D = 4.4 b) that the centroid reaches.
    The reported uncertainty must cover the error (3 σ).
    """
    cam, cal, lf = thesis_light_field
    b = lf.footprint
    truth = np.array([0.23 * b, -0.31 * b, depth])
    img = particle_image(cam, [truth], rays_per_particle=20000, seed=3)
    cell = resolution_cell(cal.effective_camera)[1]
    seed = truth + np.array([0.3 * b, -0.3 * b, 0.5 * cell])
    res = bundle_positions(lf, img, seed[None], depth_cell=cell, engine=engine)
    err = res.position[0] - truth
    assert res.converged[0] and res.n_lenslets[0] > 10
    assert np.abs(err[:2]).max() < 0.15 * b
    assert abs(err[2]) < 1.5 * b
    assert np.all(np.abs(err) <= 3 * res.uncertainty[0])
    # the reported uncertainty is a fraction of the resolution cell, not a blanket figure
    assert res.uncertainty[0, 2] < 0.5 * cell


def seeded_particles(thesis_light_field, rng, n, *, rays, seed):
    """``n`` particles within ±4 footprints and ±3 mm, their image, seeds off by 0.2
    footprint laterally and 0.8 footprint in depth, and the depth resolution cell."""
    cam, cal, lf = thesis_light_field
    b = lf.footprint
    truth = np.column_stack([rng.uniform(-4, 4, (n, 2)) * b, rng.uniform(-3e-3, 3e-3, n)])
    img = particle_image(cam, truth, rays_per_particle=rays, seed=seed)
    seeds = truth + rng.normal(0, 0.2, (n, 3)) * [b, b, 4 * b]
    return truth, img, seeds, resolution_cell(cal.effective_camera)[1]


@pytest.mark.study
def test_numba_kernels_match_their_numpy_twin(thesis_light_field, rng):
    """Several overlapping particles (shared rays), seeded off: both engines agree."""
    _, _, lf = thesis_light_field
    truth, img, seeds, cell = seeded_particles(thesis_light_field, rng, 6, rays=4000, seed=5)
    res = {e: bundle_positions(lf, img, seeds, depth_cell=cell, engine=e,
                               brightness=np.linspace(1, 2, 6)) for e in ("numba", "numpy")}
    a, c = res["numba"], res["numpy"]
    np.testing.assert_allclose(a.position, c.position, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.covariance, c.covariance, rtol=1e-8,
                               atol=1e-12 * np.nanmax(np.abs(c.covariance)))
    np.testing.assert_array_equal(a.n_rays, c.n_rays)
    np.testing.assert_array_equal(a.n_lenslets, c.n_lenslets)
    with pytest.raises(ValueError, match="engine"):
        bundle_positions(lf, img, seeds, engine="cuda")


@pytest.mark.study
def test_ray_selection_matches_its_numpy_twin(thesis_light_field, rng):
    """The rays one solve selects once (numba, threads over blocks of particles) are those
    of the NumPy selection that carry weight, with the same cone shares, particle by
    particle."""
    from plenopiv.particles.bundle import _engine_inputs, _select_rays, ray_selection, ray_table

    _, _, lf = thesis_light_field
    b = lf.footprint
    table = ray_table(lf)
    centre = np.column_stack([rng.uniform(-4, 4, (9, 2)) * b, rng.uniform(-3e-3, 3e-3, 9)])
    radius = rng.uniform(0.5, 2.0, 9) * b
    weight = np.where(rng.uniform(0, 1, lf.n_rays) < 0.3, 0.0, 1.0)
    rays = _engine_inputs(lf, table, weight, "numba")[0]
    sel = ray_selection(lf, table[:4], rays, centre, radius)
    pid, ray, miss = _select_rays(lf, *table[:4], centre, radius)
    keep = weight[ray] > 0
    pid, ray, share = pid[keep], ray[keep], 1.0 - miss[keep] / radius[pid[keep]]
    sptr = sel.particle_ptr
    got_ray = table.order[sel.ray]
    assert len(got_ray) == len(ray) > 50
    for p in range(len(centre)):
        mine = np.argsort(got_ray[sptr[p]:sptr[p + 1]])
        twin = np.argsort(ray[pid == p])
        np.testing.assert_array_equal(got_ray[sptr[p]:sptr[p + 1]][mine], ray[pid == p][twin])
        np.testing.assert_allclose(sel.share[sptr[p]:sptr[p + 1]][mine],
                                   np.maximum(share[pid == p][twin], 0.0), rtol=0, atol=1e-12)


@pytest.mark.study
def test_bundle_positions_do_not_depend_on_the_particles_order(thesis_light_field, rng):
    """The kernels take the particles in spatial order: given in another order, each
    particle gets the same fit (to rounding: the rays' shared sums add in another order)."""
    from plenopiv.particles.bundle import spatial_order

    _, _, lf = thesis_light_field
    _, img, seeds, cell = seeded_particles(thesis_light_field, rng, 7, rays=3000, seed=8)
    order = spatial_order(lf, seeds)
    np.testing.assert_array_equal(np.sort(order), np.arange(7))
    bright = np.linspace(1, 2, 7)
    a = bundle_positions(lf, img, seeds, depth_cell=cell, brightness=bright)
    perm = rng.permutation(7)
    c = bundle_positions(lf, img, seeds[perm], depth_cell=cell, brightness=bright[perm])
    np.testing.assert_allclose(c.position, a.position[perm], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(c.n_rays, a.n_rays[perm])
    np.testing.assert_array_equal(c.n_lenslets, a.n_lenslets[perm])


@pytest.mark.parametrize("engine", ["numba", "numpy"])
@pytest.mark.study
def test_bundle_on_the_lit_rays_alone_is_the_same_fit(thesis_light_field, rng, engine):
    """Rays at or below the floor carry no weight: a light field of the lit rays only
    (``LightField.subset``, what the particle table fits on) gives the same positions, with
    the particle table's margin too."""
    from plenopiv.particles.bundle import PARTICLE_BUNDLE

    _, _, lf = thesis_light_field
    _, img, seeds, cell = seeded_particles(thesis_light_field, rng, 5, rays=3000, seed=9)
    values = lf.values(img)
    keep = values > PARTICLE_BUNDLE.floor * values.max()
    lit = lf.subset(keep)
    assert lit.n_rays < 0.5 * lf.n_rays
    # the same rays in the fit's lenslet order: the ray table lends their arrays, no copies
    ordered = lit_rays(lf, img, PARTICLE_BUNDLE.floor)
    assert np.array_equal(np.sort(ordered.pixel), np.sort(lit.pixel))
    table = ray_table(ordered)
    assert np.shares_memory(table.u, ordered.u)
    for settings in (BundleSettings(), PARTICLE_BUNDLE):
        full = bundle_positions(lf, img, seeds, settings=settings, depth_cell=cell,
                                engine=engine)
        for part_lf in (lit, ordered):
            part = bundle_positions(part_lf, img, seeds, settings=settings, depth_cell=cell,
                                    engine=engine)
            np.testing.assert_allclose(part.position, full.position, rtol=0, atol=1e-12)
            np.testing.assert_array_equal(part.n_rays, full.n_rays)
    with pytest.raises(ValueError, match="keep"):
        lf.subset(np.ones(3, bool))
    with pytest.raises(ValueError, match="keep"):
        lf.subset(np.ones(3))


@pytest.mark.study
def test_bundle_light_is_the_rays_weight_each_particle_gathered(thesis_light_field, rng):
    """``BundlePositions.light``: the same on both engines, in proportion to the image, and
    no more than the light above the floor (the particles share each ray)."""
    from plenopiv.particles.bundle import PARTICLE_BUNDLE

    _, _, lf = thesis_light_field
    _, img, seeds, cell = seeded_particles(thesis_light_field, rng, 5, rays=3000, seed=9)
    fits = [bundle_positions(lf, k * img, seeds, settings=PARTICLE_BUNDLE, depth_cell=cell,
                             engine=engine) for k, engine in ((1, "numba"), (1, "numpy"),
                                                              (3, "numba"))]
    np.testing.assert_allclose(fits[1].light, fits[0].light, rtol=1e-9)
    np.testing.assert_allclose(fits[2].light, 3 * fits[0].light, rtol=1e-9)
    values = lf.values(img)
    above = np.maximum(values - PARTICLE_BUNDLE.floor * values.max(), 0).sum()
    assert np.all(fits[0].light > 0) and fits[0].light.sum() <= above * (1 + 1e-9)
    # the lines of some rays are those rays' lines
    some = np.arange(0, lf.n_rays, 7)
    for part, whole in zip(ray_lines(lf, some), ray_lines(lf), strict=True):
        np.testing.assert_array_equal(part, whole[some])


@pytest.mark.study
def test_bundle_rejects_a_wrong_image_and_bad_settings(thesis_light_field):
    _, _, lf = thesis_light_field
    with pytest.raises(Exception, match="sensor"):
        bundle_positions(lf, np.zeros((3, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="radius"):
        BundleSettings(radius=0)
    with pytest.raises(ValueError, match="iterations"):
        BundleSettings(iterations=0)
    with pytest.raises(ValueError, match="margin"):
        BundleSettings(margin=-0.5)


@pytest.mark.parametrize("engine", ["numba", "numpy"])
@pytest.mark.study
def test_bundle_of_a_dark_image_does_not_converge(thesis_light_field, engine):
    _, _, lf = thesis_light_field
    res = bundle_positions(lf, np.zeros(lf.shape), np.array([[0.0, 0.0, 1e-3]]), engine=engine)
    assert not res.converged[0]
    np.testing.assert_allclose(res.position[0], [0.0, 0.0, 1e-3])


# ---- forward-model refinement ----------------------------------------------------------------


def test_beam_fraction_is_the_share_of_lines_through_the_aperture_cell(rng):
    """Against a Monte-Carlo of the lines from the pixel's aperture cell through the point.

    The fraction is that of the aperture cell (a c x c square around u on the lens plane)
    whose lines through the particle cross the focal plane inside the lenslet's footprint (a
    b x b square around X_f); 20000 samples give a binomial σ <= 0.0035, so 0.015 (4 σ).
    """
    so, c, b = 0.1, 1.48e-3, 0.125e-3
    n = 20000
    for _ in range(12):
        p = np.array([*rng.uniform(-b, b, 2), rng.uniform(-3e-3, 3e-3)])
        t = (so + p[2]) / so
        u = rng.uniform(-8e-3, 8e-3, 2)
        # a lenslet whose chief ray passes near the beam's edge, where the fraction is partial
        half = 0.5 * (b * abs(t) + c * abs(1 - t))
        miss = rng.uniform(-1.2, 1.2, 2) * half
        xf = (p[:2] + miss - u * (1 - t)) / t
        a = u + rng.uniform(-0.5, 0.5, (n, 2)) * c
        cross = (p[:2] + a * (t - 1)) / t          # line a -> p on the plane Z = 0
        mc = np.mean(np.all(np.abs(cross - xf) <= b / 2, axis=1))
        f = beam_fraction(u[None], xf[None], p, object_distance=so, cell=c, footprint=b)[0]
        assert abs(f - mc) < 0.015, (p, f, mc)


@pytest.mark.study
def test_a_particle_seen_through_two_by_two_lenslets_has_no_depth_in_the_image(
        thesis_light_field):
    """The reason for ``[tracking] min_lenslets = 6``.

    Near focus a particle's light falls in the 2 x 2 lenslets around a footprint corner X_c;
    the edge of its lit patch in a micro-image is the aperture point u = X_c - s S_o, s the
    slope (x - X_c)/Z of the line from the corner to the particle. Every point of that line
    lights the same pixels to the same fractions: two depths 0.2 mm apart (1.6 footprints)
    predict the same image to rounding. Off focus (the particle seen through ~20 lenslets,
    each with two edges) the same depth step changes the prediction by most of a pixel.
    """
    _, _, lf = thesis_light_field
    b, so = lf.footprint, lf.object_distance
    xf = lf.focal_plane_position
    corner = xf[np.argmin(np.hypot(*xf.T))] + 0.5 * b
    slope = np.array([0.03, -0.02])     # within the aperture's R/S_o = 0.11
    geom = dict(object_distance=so, cell=lf.cell, footprint=b)

    def fraction(z):
        return beam_fraction(lf.u, xf, np.array([*(corner + slope * z), z]), **geom)

    for z1, z2 in ((0.15e-3, 0.35e-3), (-0.15e-3, -0.35e-3)):
        f1, f2 = fraction(z1), fraction(z2)
        assert len(np.unique(lf.lenslet[f1 > 0])) == len(np.unique(lf.lenslet[f2 > 0])) == 4
        np.testing.assert_allclose(f1, f2, rtol=0, atol=1e-9)
    f1, f2 = fraction(2e-3), fraction(2.2e-3)
    assert len(np.unique(lf.lenslet[f1 > 0])) > 6
    assert np.abs(f1 - f2).max() > 0.5


@pytest.mark.parametrize(("neighbour_offset_b", "neighbour_dz"), [(1.0, -2e-3), (1.0, 1e-3)])
@pytest.mark.study
def test_refined_position_is_not_pulled_by_a_missed_neighbour(thesis_light_field,
                                                              neighbour_offset_b, neighbour_dz):
    """A neighbour the reconstruction missed, one footprint aside, its rays crossing the beam.

    Only the particle is seeded, so every lit pixel of the neighbour is light the bundle
    cannot share out. The refined position must still meet the tolerances of an isolated
    particle (test_bundle_position_of_a_rendered_particle: 0.15 b laterally, 1.5 b in depth,
    from the lenslet quantisation b/sqrt(12) over ~20 lenslets and the parallax R/S_o).
    """
    cam, cal, lf = thesis_light_field
    b = lf.footprint
    truth = np.array([0.2 * b, 0.1 * b, 2e-3])
    other = truth + np.array([neighbour_offset_b * b, 0.0, neighbour_dz])
    img = particle_image(cam, [truth, other], rays_per_particle=20000, seed=12)
    cell = resolution_cell(cal.effective_camera)[1]
    start = bundle_positions(lf, img, truth[None], depth_cell=cell)
    assert start.converged[0] and start.n_lenslets[0] > 10
    pos, amp = refine_positions(lf, img, start.position, depth_cell=cell)
    err = pos[0] - truth
    assert np.abs(err[:2]).max() < 0.15 * b
    assert abs(err[2]) < 1.5 * b
    assert amp[0] > 0


@pytest.mark.parametrize(("depth", "near"), [(1e-3, np.inf), (-1.5e-3, np.inf),
                                             (-1.5e-3, 0.0), (2.5e-3, 0.0)])
@pytest.mark.study
def test_refined_position_of_an_isolated_particle(thesis_light_field, depth, near):
    """Started from a bundle seeded off (0.1 b, 0.1 b, 0.3 cell): the isolated tolerances,
    by the grid searches (``near_focus = inf``) and by the local steps (``0``)."""
    cam, cal, lf = thesis_light_field
    b = lf.footprint
    truth = np.array([0.3 * b, -0.2 * b, depth])
    img = particle_image(cam, [truth], rays_per_particle=20000, seed=11)
    cell = resolution_cell(cal.effective_camera)[1]
    start = bundle_positions(lf, img, (truth + [0.1 * b, 0.1 * b, 0.3 * cell])[None],
                             depth_cell=cell)
    pos, _ = refine_positions(lf, img, start.position, depth_cell=cell,
                              settings=ForwardSettings(near_focus=near))
    err = pos[0] - truth
    assert np.abs(err[:2]).max() < 0.15 * b
    assert abs(err[2]) < 1.5 * b


@pytest.mark.parametrize("near", ["grid", "local", "both"])
@pytest.mark.study
def test_refinement_kernel_matches_its_numpy_twin(thesis_light_field, rng, near):
    """Several particles with crossing beams, started off the truth: both engines agree,
    by the grid searches, the local steps and both (``near_focus`` between the starts)."""
    cam, cal, lf = thesis_light_field
    b = lf.footprint
    truth = np.column_stack([rng.uniform(-4, 4, (5, 2)) * b, rng.uniform(-3e-3, 3e-3, 5)])
    img = particle_image(cam, truth, rays_per_particle=4000, seed=6)
    start = truth + rng.normal(0, 0.1, (5, 3)) * [b, b, 2 * b]
    cell = resolution_cell(cal.effective_camera)[1]
    mid = float(np.median(np.abs(start[:, 2]))) / cell
    fs = ForwardSettings(near_focus={"grid": np.inf, "local": 0.0, "both": mid}[near])
    res = {e: refine_positions(lf, img, start, depth_cell=cell, engine=e, settings=fs)
           for e in ("numba", "numpy")}
    np.testing.assert_allclose(res["numba"][0], res["numpy"][0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(res["numba"][1], res["numpy"][1], rtol=1e-12)
    assert np.abs(res["numba"][0] - start).max() > 0        # the search moved something
    if near != "both":
        return
    assert near_focus(start[:, 2], depth_cell=cell, settings=fs).sum() == 3
    # the compiled pixel selection and its twin take the same pixels in the same order
    from plenopiv.particles.forward import _lenslet_index, _pixels
    index = _lenslet_index(lf)
    for eng_a, eng_b in zip(_pixels(lf, index, start, 1.5, 0.3e-3, "numba"),
                            _pixels(lf, index, start, 1.5, 0.3e-3, "numpy"), strict=True):
        np.testing.assert_array_equal(eng_a, eng_b)
    # one particle per run of pixels: each particle's search is its own
    one = refine_positions(lf, img, start, depth_cell=cell, chunk_pixels=1, settings=fs)
    np.testing.assert_array_equal(one[0], res["numba"][0])
    np.testing.assert_array_equal(one[1], res["numba"][1])
    with pytest.raises(ValueError, match="engine"):
        refine_positions(lf, img, start, depth_cell=cell, engine="cuda")


@pytest.mark.study
def test_misfit_gradient_is_the_derivative_of_the_misfit(thesis_light_field):
    """The local steps' Jacobian: 2 J^T r equals the central difference of the misfit.

    The misfit is piecewise quadratic (the trapezoids are piecewise linear in x, y, Z): over
    a step of 1e-4 footprints (1e-4 depth cells) few pixels cross a kink, so the difference
    quotient matches the analytic gradient to well within 1 %.
    """
    from plenopiv.particles.bundle import ray_table
    from plenopiv.particles.forward import _fractions, _misfit_sums, _pixels, _robust_amplitude

    cam, cal, lf = thesis_light_field
    b = lf.footprint
    cell = resolution_cell(cal.effective_camera)[1]
    truth = np.array([[0.2 * b, -0.1 * b, 2e-3]])
    img = particle_image(cam, truth, rays_per_particle=20000, seed=3)
    table = ray_table(lf)
    at = truth + [[0.05 * b, 0.03 * b, 0.1 * cell]]
    pid, ray = _pixels(lf, table, at, 1.5, 0.3 * cell, "numpy")
    v, u, xf = lf.values(img).astype(float)[ray], lf.u[ray], table.focal[ray]
    ptr = np.array([0, len(pid)])
    geom = dict(object_distance=lf.object_distance, cell=lf.cell, footprint=lf.footprint)
    amp = _robust_amplitude(ptr, pid, _fractions(ptr, pid, u, xf, truth, geom), v)
    scale = (b, cell)
    _, _, g = _misfit_sums(pid, 1, u, xf, v, amp, at, geom, 0.2, scale)
    for k, unit in enumerate((b, b, cell)):
        d = np.zeros((1, 3))
        d[0, k] = 1e-4 * unit
        up = _misfit_sums(pid, 1, u, xf, v, amp, at + d, geom, 0.2, scale)[0][0]
        down = _misfit_sums(pid, 1, u, xf, v, amp, at - d, geom, 0.2, scale)[0][0]
        numeric = (up - down) / 2e-4               # per scale unit, as g
        assert numeric == pytest.approx(2 * g[0, k], rel=1e-2, abs=1e-6 * abs(g).max())


@pytest.mark.study
def test_amplitude_kernel_matches_its_numpy_twin(thesis_light_field, rng):
    """Median of value / fraction over the half-lit pixels, per particle; none lit: 0."""
    from plenopiv.particles.bundle import ray_table
    from plenopiv.particles.forward import _amplitude_at, _amplitude_at_numba, _fractions, _pixels

    _, _, lf = thesis_light_field
    b = lf.footprint
    table = ray_table(lf)
    pos = np.column_stack([rng.uniform(-3, 3, (4, 2)) * b, rng.uniform(-3e-3, 3e-3, 4)])
    pid, ray = _pixels(lf, table, pos, 1.5, 0.3e-3, "numpy")
    # a fifth particle's pixels all seen from far off: it lights none of them half
    pid = np.concatenate([pid, np.full(5, 4)])
    ray = np.concatenate([ray, ray[:5]])
    pos = np.vstack([pos, [[0.05, 0.05, 0.0]]])
    ptr = np.concatenate([[0], np.cumsum(np.bincount(pid, minlength=5))]).astype(np.int64)
    v = rng.normal(2.0, 1.0, len(pid))
    u, xf = lf.u[ray], table.focal[ray]
    geom = dict(object_distance=lf.object_distance, cell=lf.cell, footprint=lf.footprint)
    got = _amplitude_at_numba(ptr, pid, u, xf, v, pos, geom)
    np.testing.assert_array_equal(got, _amplitude_at(ptr, pid, u, xf, v, pos, geom))
    f = _fractions(ptr, pid, u, xf, pos, geom)
    lit = (pid == 0) & (f >= 0.5)
    assert lit.sum() > 3
    ratio = np.sort(v[lit] / f[lit])
    assert got[0] == max(ratio[len(ratio) // 2], 0.0)
    assert got[4] == 0.0


def test_kth_smallest_by_quickselect_is_that_of_the_sorted_values(rng):
    """The amplitude's upper median: element k of the sorted values, ties included."""
    from plenopiv.particles._bundle_kernels import _select_kth

    for n in (1, 2, 3, 8, 31):
        for values in (rng.normal(size=n), rng.integers(0, 3, n).astype(float)):
            for k in range(n):
                buf = np.concatenate([values, [np.inf]])       # past n: never read
                assert _select_kth(buf, n, k) == np.sort(values)[k]


@pytest.mark.study
def test_gathered_pixels_are_those_of_the_selection(thesis_light_field, rng):
    """The selection's gathered values and rays are those of its rows (lenslet order)."""
    from plenopiv.particles.bundle import ray_table
    from plenopiv.particles.forward import _pixel_data, _pixels

    _, _, lf = thesis_light_field
    b = lf.footprint
    table = ray_table(lf)
    start = np.column_stack([rng.uniform(-3, 3, (4, 2)) * b, rng.uniform(-3e-3, 3e-3, 4)])
    values = rng.uniform(0, 1, lf.n_rays)[table.order]
    pid, row = _pixels(lf, table, start, 1.5, 0.3e-3, "numba", lenslet_order=True)
    pid2, (v, u, xf) = _pixel_data(lf, table, values, start, 1.5, 0.3e-3)
    np.testing.assert_array_equal(pid, pid2)
    np.testing.assert_array_equal(v, values[row])
    np.testing.assert_array_equal(u, table.u[row])
    np.testing.assert_array_equal(xf, table.focal_sorted[row])


@pytest.mark.study
def test_refinement_of_a_dark_image_keeps_the_start(thesis_light_field):
    _, _, lf = thesis_light_field
    start = np.array([[0.0, 0.0, 1e-3], [1e-4, 0.0, -2e-3]])
    pos, amp = refine_positions(lf, np.zeros(lf.shape), start, depth_cell=0.55e-3)
    np.testing.assert_array_equal(pos, start)
    np.testing.assert_array_equal(amp, 0.0)


def test_forward_settings_name_the_bad_value():
    for kw, name in (({"depth_range": 0}, "depth_range"), ({"depth_steps": 4}, "depth_steps"),
                     ({"excess": -1}, "excess"), ({"rounds": 0}, "rounds"),
                     ({"round_depth_steps": 6}, "round_depth_steps"),
                     ({"margin": 0.5}, "margin"), ({"near_focus": -1}, "near_focus"),
                     ({"local_iterations": 0}, "local_iterations"),
                     ({"local_rounds": 1.5}, "local_rounds"),
                     ({"local_starts": 2}, "local_starts"),
                     ({"local_starts_within": -1.0}, "local_starts_within")):
        with pytest.raises(ValueError, match=name):
            ForwardSettings(**kw)


# ---- matching --------------------------------------------------------------------------------

CELL = np.array([0.125e-3, 0.125e-3, 0.55e-3])


def _field(fn, lo=-3e-3, hi=3e-3, n=13):
    """A displacement field sampled on a grid (the shape of a VectorResult)."""
    x = y = z = np.linspace(lo, hi, n)
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    d = fn(np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)).reshape(Z.shape + (3,))
    return SimpleNamespace(x=x, y=y, z=z, u=d[..., 0], v=d[..., 1], w=d[..., 2])


def test_matching_recovers_a_shift_with_no_wrong_match(rng):
    n = 400
    pa = rng.uniform(-2.5e-3, 2.5e-3, (n, 3))
    shift = np.array([0.3e-3, -0.2e-3, 0.4e-3])
    pb = pa + shift + rng.normal(0, 0.02, (n, 3)) * CELL      # position noise 0.02 cell
    # 10 % of the particles are lost in B, and B has 10 % of unrelated particles (ghosts)
    lost = rng.random(n) < 0.1
    ghosts = rng.uniform(-2.5e-3, 2.5e-3, (n // 10, 3))
    b_all = np.concatenate([pb[~lost], ghosts])
    perm = rng.permutation(len(b_all))
    b_all = b_all[perm]
    owner = np.concatenate([np.flatnonzero(~lost), np.full(len(ghosts), -1)])[perm]
    # the correlation field predicts the shift to 0.1 cell
    vec = _field(lambda p: np.broadcast_to(shift + 0.1 * CELL * np.array([1, -1, 1]), p.shape))
    m = match_particles(pa, b_all, predict_positions(vec, pa), CELL)
    assert len(m) > 0.8 * (~lost).sum()
    assert np.all(owner[m.index_b] == m.index_a)        # zero wrong matches
    d = b_all[m.index_b] - pa[m.index_a]
    np.testing.assert_allclose(np.median(d, axis=0), shift, atol=0.01 * CELL.min())


def test_matching_follows_a_known_rotation(rng):
    """Solid-body rotation about the y axis (particles move in depth), 2° between exposures."""
    n = 300
    pa = rng.uniform(-2.5e-3, 2.5e-3, (n, 3))
    ang = np.deg2rad(2.0)
    rot = np.array([[np.cos(ang), 0, np.sin(ang)], [0, 1, 0], [-np.sin(ang), 0, np.cos(ang)]])
    pb = pa @ rot.T
    perm = rng.permutation(n)
    vec = _field(lambda p: p @ rot.T - p)     # the rotation's displacement field
    m = match_particles(pa, pb[perm], predict_positions(vec, pa), CELL)
    assert len(m) == n
    assert np.all(perm[m.index_b] == m.index_a)
    np.testing.assert_allclose(pb[perm][m.index_b] - pa[m.index_a], (pa @ rot.T - pa)[m.index_a],
                               atol=1e-15)


def test_two_way_check_rejects_a_contested_particle():
    # two A particles predicted onto the same single B particle: only the nearer one keeps it
    pa = np.array([[0.0, 0, 0], [0.05e-3, 0, 0]])
    pred = np.array([[1e-6, 0, 0], [0.05e-3, 0, 0]])
    m = match_particles(pa, np.array([[0.0, 0, 0]]), pred, CELL,
                        settings=MatchSettings(search_radius_cells=1.0))
    assert list(m.index_a) == [0] and m.rejected_mutual == 1


def test_neighbour_median_test_flags_an_inconsistent_track(rng):
    p = rng.uniform(0, 10, (200, 3))
    d = np.tile([1.0, 0.5, -0.2], (200, 1)) + rng.normal(0, 0.02, (200, 3))
    d[17] += [0.0, 0.0, 1.0]
    bad = neighbour_median_test(p, d, threshold=3.0, epsilon=0.1, radius=5.0)
    assert bad[17] and bad.sum() == 1


def test_interpolation_is_exact_for_a_linear_field(rng):
    vec = _field(lambda p: p @ np.array([[0.1, 0.2, 0.0], [0.0, -0.1, 0.3], [0.05, 0, 0]]))
    p = rng.uniform(-2e-3, 2e-3, (20, 3))
    d = interpolate_displacement(vec.x, vec.y, vec.z, vec.u, vec.v, vec.w, p)
    np.testing.assert_allclose(d, p @ np.array([[0.1, 0.2, 0.0], [0.0, -0.1, 0.3],
                                                 [0.05, 0, 0]]), atol=1e-15)


def test_match_settings_name_the_bad_value():
    with pytest.raises(ValueError, match="search_radius_cells"):
        MatchSettings(search_radius_cells=-1)
    with pytest.raises(ValueError, match="neighbours"):
        MatchSettings(neighbours=2)


# ---- products --------------------------------------------------------------------------------


def _tracks(rng, n=25, dt=1e-3):
    pa = rng.uniform(-1e-3, 1e-3, (n, 3))
    pb = pa + [1e-4, 0, -2e-4]
    s = np.full((n, 3), 1e-5)
    return TrackResult(pa, pb, s, s, np.ones(n), np.zeros(n), np.arange(n), np.arange(n),
                       np.full(n, 5), np.full(n, 6), dt, {"tracks": n})


def test_tracks_product_has_the_documented_datasets(tmp_path, rng):
    t = _tracks(rng)
    files = write_tracks(tmp_path / "t.h5", t, config={"x": 1})
    with h5py.File(files[0], "r") as fh:
        for name in TRACK_DATASETS + ("/velocity_m_s",):
            assert name in fh, name
        assert fh["/displacement_m"].shape == (25, 3)
        assert fh["/position_a_m"].attrs["units"] == "m"
        assert fh["/velocity_m_s"].attrs["units"] == "m s-1"
        np.testing.assert_allclose(fh["/velocity_m_s"][0], [0.1, 0, -0.2])
        assert fh.attrs["product"] == "tracks" and fh.attrs["n_tracks"] == 25
    root = ET.parse(files[1]).getroot()
    piece = root.find("PolyData/Piece")
    assert piece.get("NumberOfLines") == "25" and piece.get("NumberOfPoints") == "50"
    # without dt there is no velocity
    files = write_tracks(tmp_path / "n.h5", _tracks(rng, dt=None), vtk=False)
    with h5py.File(files[0], "r") as fh:
        assert "/velocity_m_s" not in fh and np.isnan(fh.attrs["dt_s"])


def test_binned_tracks_average_in_their_cell(rng):
    t = _tracks(rng, n=200)
    vec = _field(lambda p: np.zeros(p.shape), lo=-1e-3, hi=1e-3, n=5)
    vec = SimpleNamespace(**vars(vec), dt=1e-3)
    b = bin_tracks(t, vec)
    assert b.valid.any() and b.snr[b.valid].sum() <= 200
    np.testing.assert_allclose(b.u[b.valid], 1e-4)
    np.testing.assert_allclose(b.w[b.valid], -2e-4)


# ---- the command -----------------------------------------------------------------------------


def test_track_command_end_to_end(tmp_path, capsys):
    """`plenopiv track` on the CI camera: a uniform shift of 1.5 footprints along x."""
    from plenopiv.camera.model import load_camera

    cam = load_camera("small_m1")
    Calibration.from_camera(cam).save(tmp_path / "cal.h5")
    pair = tmp_path / "pair.h5"
    assert main(["simulate", "pair", "small_m1", "--n-particles", "40", "--flow", "uniform",
                 "--max-displacement-mm", "0.1875", "--rays-per-particle", "1024",
                 "--depth-mm", "-1.5", "1.5", "--fill", "0.4", "--seed", "4", "--no-tiff",
                 "--quiet", "--out", str(pair)]) == 0
    (tmp_path / "exp.toml").write_text(
        'camera = "small_m1"\n[volume]\nx_mm = [-1.6875, 1.6875]\ny_mm = [-1.1875, 1.1875]\n'
        'z_mm = [-2.0, 2.0]\nvoxel_mm = 0.125\n[piv]\nwindows = [[16, 12, 12]]\npasses = 2\n'
        '[images]\ndt_s = 1e-3\n[output]\npng = false\n[tracking]\nenabled = true\n')
    capsys.readouterr()
    out = tmp_path / "tracks.h5"
    code = main(["track", str(tmp_path / "cal.h5"), f"{pair}:/image_a", f"{pair}:/image_b",
                 "--config", str(tmp_path / "exp.toml"), "--out", str(out), "--json"])
    s = json.loads(capsys.readouterr().out)
    assert code == 0 and s["command"] == "track"
    with h5py.File(pair, "r") as fh:
        truth = fh["/truth/displacement_m"][()]
    assert s["n_tracks"] >= 0.3 * len(truth)
    with h5py.File(out, "r") as fh:
        d = fh["/displacement_m"][()]
        v = fh["/velocity_m_s"][()]
        sig = fh["/uncertainty_m"][()]
        sharp = (fh["/n_lenslets_a"][()] > 1) & (fh["/n_lenslets_b"][()] > 1)
    # every track within 3 of its reported uncertainties of the flow (1.5 footprints along x);
    # off focus (seen through several lenslets) the median within 0.1 voxel laterally and
    # 0.5 voxel in depth (one track's depth error is ~1 voxel rms, docs/validation/tracking.md)
    assert np.all(np.abs(d - truth[0]) <= 3 * sig)
    assert sharp.sum() >= 5
    assert np.all(np.abs(np.median(d[sharp], axis=0) - truth[0])
                  <= np.array([0.1, 0.1, 0.5]) * 0.125e-3)
    np.testing.assert_allclose(v, d / 1e-3)
    assert out.with_suffix(".vtp").exists()
    with h5py.File(out, "r") as fh:
        assert json.loads(fh.attrs["judgement"]) == s["judgement"]
    binned = load_vectors(s["files"]["binned"])
    assert binned.u.shape == (len(binned.z), len(binned.y), len(binned.x))
    assert binned.valid.any()
    # reusing the volumes and vectors of a pair gives the same tracks
    code = main(["track", str(tmp_path / "cal.h5"), f"{pair}:/image_a", f"{pair}:/image_b",
                 "--config", str(tmp_path / "exp.toml"), "--out", str(tmp_path / "t2.h5"),
                 "--vectors", s["files"]["binned"], "--json"])
    assert code == 0 and json.loads(capsys.readouterr().out)["n_tracks"] > 0


def test_tracking_in_a_batch_pair_and_its_config(tmp_path):
    """`[tracking] enabled = true`: the per-pair work of `plenopiv run` writes NAME_tracks.h5."""
    from plenopiv.batch.jobs import PairJob
    from plenopiv.camera.model import load_camera
    from plenopiv.config.experiment import load_experiment
    from plenopiv.errors import ConfigError
    from plenopiv.workflow.worker import ExperimentPairProcess

    cam = load_camera("small_m1")
    Calibration.from_camera(cam).save(tmp_path / "cal.h5")
    pair = tmp_path / "p1.h5"
    assert main(["simulate", "pair", "small_m1", "--n-particles", "30", "--rays-per-particle",
                 "512", "--depth-mm", "-1.5", "1.5", "--fill", "0.4", "--seed", "2",
                 "--no-tiff", "--quiet", "--out", str(pair)]) == 0
    text = ('camera = "small_m1"\n[volume]\nx_mm = [-1.6875, 1.6875]\n'
            'y_mm = [-1.1875, 1.1875]\nz_mm = [-2.0, 2.0]\nvoxel_mm = 0.125\n'
            '[piv]\nwindows = [[16, 12, 12]]\npasses = 2\n[images]\ndt_s = 1e-3\n'
            '[output]\npng = false\nvtk = false\nweights_cache = ""\n'
            '[tracking]\nenabled = true\nsearch_radius_cells = 1.5\n')
    (tmp_path / "exp.toml").write_text(text)
    assert load_experiment(tmp_path / "exp.toml").tracking.search_radius_cells == 1.5
    job = PairJob("p1", f"{pair}:/image_a", f"{pair}:/image_b", tmp_path / "p1_vectors.h5")
    s = ExperimentPairProcess(str(tmp_path / "exp.toml"), str(tmp_path / "cal.h5"),
                              str(tmp_path))(job)
    assert s["n_tracks"] > 0 and (tmp_path / "p1_tracks.h5").exists()
    with h5py.File(tmp_path / "p1_tracks.h5", "r") as fh:
        assert fh["/displacement_m"].shape == (s["n_tracks"], 3)
        assert json.loads(fh.attrs["config"])["tracking"]["enabled"] is True
        # the default min_lenslets = 6: no kept end was seen through 2 x 2 lenslets or fewer
        assert fh["/n_lenslets_a"][()].min() >= 6 and fh["/n_lenslets_b"][()].min() >= 6
        assert fh.attrs["count_rejected_few_lenslets"] >= 0
        assert fh.attrs["count_tracks"] == s["n_tracks"]
        # the judgement of the settings and of the seeding, as `plenopiv track` records it
        judged = json.loads(fh.attrs["judgement"])
    with h5py.File(tmp_path / "p1_vectors.h5", "r") as fh:
        assert set(judged) == set(json.loads(fh.attrs["judgement"]))
    assert judged["n_particles"] > 0 and judged["particles_per_lenslet"] > 0
    (tmp_path / "bad.toml").write_text(text + "search_radius = 2\n")
    with pytest.raises(ConfigError, match="search_radius"):
        load_experiment(tmp_path / "bad.toml")
    (tmp_path / "bad.toml").write_text(text + "min_lenslets = 0\n")
    with pytest.raises(ConfigError, match="min_lenslets"):
        load_experiment(tmp_path / "bad.toml")
    (tmp_path / "off.toml").write_text(text + "forward_refine = false\nmin_lenslets = 1\n")
    off = load_experiment(tmp_path / "off.toml").tracking
    assert off.forward_refine is False and off.min_lenslets == 1



@pytest.mark.study
def test_bundle_does_not_depend_on_the_order_of_the_light_fields_rays(thesis_light_field, rng):
    """The kernels find a lenslet's first candidate ray by bisection on aperture y: a light
    field whose rays come in another order (pixels shuffled) is grouped with each lenslet's
    rays running down in u_y, and gives the same bundle (to rounding of the sums' order)."""
    import dataclasses

    from plenopiv.particles.bundle import lenslet_table

    cam, cal, lf = thesis_light_field
    perm = rng.permutation(lf.n_rays)
    per_ray = {f.name: getattr(lf, f.name)[perm] for f in dataclasses.fields(lf)
               if isinstance(getattr(lf, f.name), np.ndarray)
               and getattr(lf, f.name).shape[:1] == (lf.n_rays,)}
    shuffled = dataclasses.replace(lf, **per_ray)
    for field in (lf, shuffled):
        order, _, _, _ = lenslet_table(field)
        lens = field.lenslet[order]
        assert np.all(np.diff(lens) >= 0)
        assert np.all(np.diff(field.u[order, 1])[lens[1:] == lens[:-1]] <= 0.0)
    b = lf.footprint
    truth = np.column_stack([rng.uniform(-4, 4, (5, 2)) * b, rng.uniform(-3e-3, 3e-3, 5)])
    img = particle_image(cam, truth, rays_per_particle=3000, seed=9)
    seeds = truth + rng.normal(0, 0.2, (5, 3)) * [b, b, 4 * b]
    cell = resolution_cell(cal.effective_camera)[1]
    a = bundle_positions(lf, img, seeds, depth_cell=cell)
    c = bundle_positions(shuffled, img, seeds, depth_cell=cell)
    np.testing.assert_allclose(c.position, a.position, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(c.n_rays, a.n_rays)
