"""The per-lenslet matrix-free projector (plenopiv.reconstruction.real_lattice) against the explicit
weights.

Rotated (up to 10 mrad, with an offset), hexagonal and jittered lattices. With the same ray
model (cell-centre rays for edge pixels, no weight dropped) the projector is the explicit W
computed in another order, so projections agree to float32 summation error: |Δ| ≤ 1e-5 of
the largest value (sums of a few hundred float32 terms, each rounded at 6e-8), and
<A x, y> = <x, Aᵀ y> to the same relative error. With the pipeline's default ray model (edge
pixels through the centroid of their lit part) the reconstructions differ only at the
micro-images' rims: Q ≥ 0.99 between them.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.cli import main
from plenopiv.errors import ReconstructionError
from plenopiv.lightfield import light_field
from plenopiv.reconstruction import real_lattice as rl
from plenopiv.reconstruction._kernels import real_lattice as rk
from plenopiv.reconstruction.build import cached_weights
from plenopiv.reconstruction.choose import choose_projector
from plenopiv.reconstruction.geometry import separable_axes
from plenopiv.reconstruction.mart import reconstruction_quality
from plenopiv.reconstruction.real_lattice import (
    LensletProjector,
    compile_ahead,
    estimate_lenslet_gb,
    kernel_signatures,
    lenslet_weights_reference,
    matrix_free_projector,
)
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.weights import build_weights
from plenopiv.synthetic.images import particle_image
from plenopiv.workflow.volume import reconstruct_volume

RTOL = 1e-5

GEOMETRIES = {
    "rotated_10mrad": {"rotation": 10e-3, "offset": (3e-6, -2e-6)},
    "rotated_-2mrad": {"rotation": -2e-3, "offset": (-4e-6, 1e-6)},
    "hexagonal": {"grid": "hexagonal", "rotation": 1e-3},
}


def camera_of(base, geometry: str, lenslets=(15, 19)):
    mla = dataclasses.replace(base.microlens_array, **GEOMETRIES[geometry])
    return base.replace(microlens_array=mla).patch(*lenslets, margin_px=12)


def jittered(cal: Calibration, rng, centre_px=0.4, spot_px=0.05) -> Calibration:
    """Per-lens centres moved by ``centre_px`` pixels rms (3 µm here) and focal spots by
    ``spot_px`` (the spot-fit noise; more would make neighbouring micro-images, which here
    nearly touch, claim the same pixels)."""
    return dataclasses.replace(
        cal, centre_px=cal.centre_px + rng.normal(0.0, centre_px, cal.centre_px.shape),
        focal_spot_px=cal.focal_spot_px + rng.normal(0.0, spot_px, cal.centre_px.shape))


def small_grid(lf, nx=22, ny=18, nz=12, lateral=0.75, depth=1.7, shift=(0.37, 0.21)):
    b = lf.footprint
    vx, vz = b * lateral, b * depth
    ox, oy = shift[0] * vx, shift[1] * vx
    return VolumeGrid.from_bounds((-nx / 2 * vx + ox, nx / 2 * vx + ox),
                                  (-ny / 2 * vx + oy, ny / 2 * vx + oy),
                                  (-nz / 2 * vz, nz / 2 * vz), voxel=(vx, vx, vz))


@pytest.fixture(scope="module", params=[*GEOMETRIES, "jittered"])
def case(request, small_camera):
    rng = np.random.default_rng(7)
    geometry = "rotated_-2mrad" if request.param == "jittered" else request.param
    cal = Calibration.from_camera(camera_of(small_camera, geometry))
    if request.param == "jittered":
        cal = jittered(cal, rng)
    lf = light_field(cal, edge_centroid=False)
    grid = small_grid(lf)
    return (request.param, lf, grid, build_weights(lf, grid, min_weight=0.0).projector,
            LensletProjector.from_light_field(lf, grid))


def test_the_lattices_are_not_separable(case):
    _, lf, _, _, _ = case
    assert separable_axes(lf) is None


def test_forward_back_row_max_equal_explicit_weights(case, rng):
    _, lf, grid, explicit, lens = case
    assert lens.n_pixels == explicit.n_pixels == lf.n_rays
    e = rng.random(grid.n_voxels).astype(np.float32)
    f0, f1 = explicit.forward(e), lens.forward(e)
    assert np.abs(f1 - f0).max() <= RTOL * np.abs(f0).max()
    i = rng.random(lf.n_rays).astype(np.float32)
    b0, b1 = explicit.back(i), lens.back(i)
    assert np.abs(b1 - b0).max() <= RTOL * np.abs(b0).max()
    r0, r1 = explicit.row_max(), lens.row_max()
    assert np.abs(r1 - r0).max() <= RTOL * r0.max()
    c0, c1 = explicit.column_sums(), lens.column_sums()
    assert np.abs(c1 - c0).max() <= RTOL * c0.max()
    s0, s1 = explicit.row_sums(), lens.row_sums()
    assert np.abs(s1 - s0).max() <= RTOL * s0.max()


def test_adjoint_and_row_views(case, rng):
    _, lf, grid, explicit, lens = case
    e = rng.random(grid.n_voxels).astype(np.float32)
    i = rng.random(lf.n_rays).astype(np.float32)
    lhs = float(np.dot(lens.forward(e).astype(np.float64), i))
    rhs = float(np.dot(e.astype(np.float64), lens.back(i)))
    assert lhs == pytest.approx(rhs, rel=RTOL)
    mask = rng.random(lf.n_rays) < 0.3
    factors = rng.uniform(0.5, 2.0, lf.n_rays).astype(np.float32)
    sub0 = explicit.scale_rows(factors).select_rows(mask)
    sub1 = lens.scale_rows(factors).select_rows(mask)
    assert sub1.n_pixels == int(mask.sum())
    f0, f1 = sub0.forward(e), sub1.forward(e)
    assert np.abs(f1 - f0).max() <= RTOL * np.abs(f0).max()
    j = rng.random(sub1.n_pixels).astype(np.float32)
    b0, b1 = sub0.back(j), sub1.back(j)
    assert np.abs(b1 - b0).max() <= RTOL * np.abs(b0).max()


def test_on_grid_equals_a_projector_built_for_that_grid(case, rng):
    """The refined line-of-sight slabs reuse the rays' tables on another grid."""
    _, lf, grid, _, lens = case
    other = small_grid(lf, nx=13, ny=11, nz=5, lateral=0.5, depth=1.0, shift=(0.1, -0.3))
    want = LensletProjector.from_light_field(lf, other)
    got = lens.on_grid(other)
    e = rng.random(other.n_voxels).astype(np.float32)
    np.testing.assert_array_equal(got.forward(e), want.forward(e))
    i = rng.random(lf.n_rays).astype(np.float32)
    np.testing.assert_array_equal(got.back(i), want.back(i))


def test_kernels_equal_their_numpy_twin(small_camera, rng):
    """The numba kernels against the dense W of the plain-NumPy twin, on a 3 × 4 patch."""
    cal = Calibration.from_camera(camera_of(small_camera, "hexagonal", (3, 4)))
    lf = light_field(cal)
    proj = LensletProjector.from_light_field(lf, small_grid(lf, nx=6, ny=5, nz=4))
    dense = lenslet_weights_reference(proj)
    e = rng.random(proj.n_voxels).astype(np.float32)
    i = rng.random(proj.n_pixels).astype(np.float32)
    want_f, want_b = dense @ e, dense.T @ i
    assert np.abs(proj.forward(e) - want_f).max() <= RTOL * np.abs(want_f).max()
    assert np.abs(proj.back(i) - want_b).max() <= RTOL * np.abs(want_b).max()
    np.testing.assert_allclose(proj.row_max(), dense.max(axis=1), rtol=RTOL, atol=0)
    np.testing.assert_allclose(proj.row_sums(), dense.sum(axis=1), rtol=RTOL, atol=0)
    assert dense.any(axis=1).all()      # every ray reaches the grid: the test covers them


def _patch_rows(proj) -> np.ndarray:
    """Voxel rows each lenslet's beams span on each slice (lenslets × slices), as `_span`."""
    le, sl, win, g = proj._lens, proj._slices, proj._window, proj.grid
    lens = np.arange(len(le["xf_y"]))
    first = le["u_row"][lens, win[:, 0]]
    last = le["u_row"][lens, np.maximum(win[:, 1] - 1, 0)]
    t, half = sl["t"][None, :], sl["half"][None, :]
    m0 = (1 - t) * first[:, None] + t * le["xf_y"][:, None]
    m1 = (1 - t) * last[:, None] + t * le["xf_y"][:, None]
    lo = np.floor((np.minimum(m0, m1) - half - g.origin[1]) / g.voxel[1] + 0.5)
    hi = np.floor((np.maximum(m0, m1) + half - g.origin[1]) / g.voxel[1] + 0.5) + 1
    return np.clip(hi, 0, g.shape[1]) - np.clip(lo, 0, g.shape[1])


@pytest.mark.parametrize("geometry", ["rotated_10mrad", "hexagonal"])
def test_back_projection_of_short_and_tall_patches_equals_explicit_weights(small_camera, rng,
                                                                            geometry):
    """On voxels a quarter of a footprint wide a lenslet's beams span a few rows near focus
    and many far from it: the back projection adds the short patches straight into the
    slice and the tall ones through the slice transposed; both equal the explicit weights."""
    cal = Calibration.from_camera(camera_of(small_camera, geometry, (9, 11)))
    lf = light_field(cal, edge_centroid=False)
    grid = small_grid(lf, nx=44, ny=40, nz=12, lateral=0.25, depth=1.7)
    lens = LensletProjector.from_light_field(lf, grid)
    rows = _patch_rows(lens)
    assert (rows < rk.TRANSPOSED_MIN_ROWS).any() and (rows >= rk.TRANSPOSED_MIN_ROWS).any()
    explicit = build_weights(lf, grid, min_weight=0.0).projector
    i = rng.random(lf.n_rays).astype(np.float32)
    b0, b1 = explicit.back(i), lens.back(i)
    assert np.abs(b1 - b0).max() <= RTOL * np.abs(b0).max()


def test_the_signatures_compiled_ahead_are_those_the_projector_calls(case, monkeypatch):
    """What :func:`compile_ahead` compiles is what the projector then calls: the forward and
    back projections (with and without ``out``, as SMART and the line of sight call them)
    and the row reduction, each with the argument types of its real call."""
    import numba

    _, _, _, _, lens = case
    want = {k.py_func.__name__: sig for k, sig in kernel_signatures().items()}
    seen = {}

    def recorder(name, kernel):
        def record(*args):
            seen.setdefault(name, set()).add(tuple(numba.typeof(a) for a in args))
            return kernel(*args)
        return record

    for name in want:
        monkeypatch.setattr(rk, name, recorder(name, getattr(rk, name)))
    lens.forward(np.ones(lens.n_voxels))
    lens.forward(np.ones(lens.n_voxels, np.float32), out=np.empty(lens.n_pixels, np.float32))
    lens.back(np.ones(lens.n_pixels))
    lens.back(np.ones(lens.n_pixels, np.float32), out=np.empty(lens.n_voxels, np.float32))
    lens.row_max()
    assert seen == {name: {sig} for name, sig in want.items()}


def test_compile_ahead_runs_once_per_process_and_compiles_every_kernel():
    first = compile_ahead()
    assert compile_ahead() is None          # once per process, however often it is asked
    assert first is not None or rl._AHEAD
    for thread in rl._AHEAD:
        thread.join(600)
    for kernel, sig in kernel_signatures().items():
        assert sig in {tuple(s) for s in kernel.signatures}, kernel.py_func.__name__


def test_back_projection_does_not_depend_on_the_order_of_its_slices(case, rng):
    """Each slice is summed by one thread alone: dealing the slices to the threads in
    another order gives the same volume to the bit."""
    import numba

    _, lf, grid, _, lens = case
    nz = grid.shape[0]
    for n in (1, 2, 3, 7):
        order = rk.interleaved_order(nz, n)
        np.testing.assert_array_equal(np.sort(order), np.arange(nz))
    i = rng.random(lf.n_rays).astype(np.float32)
    want = lens.back(i)
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        got = lens.back(i)
    finally:
        numba.set_num_threads(threads)
    np.testing.assert_array_equal(got, want)
    if threads > 1:
        assert not np.array_equal(rk.interleaved_order(nz, 1), rk.interleaved_order(nz, threads))


def test_smart_over_all_rows_equals_smart_over_the_rows_reaching_the_support(case, rng):
    """Rows whose beams miss the first guess's support change nothing: the solver may hand
    SMART every touching row instead of selecting the reaching ones by a forward projection.
    Their weights on the support are zero, so the sums are the same to the bit."""
    from plenopiv.reconstruction.mart import reconstruct

    _, lf, grid, _, lens = case
    first = (rng.random(grid.n_voxels) * (rng.random(grid.n_voxels) < 0.05)).astype(np.float32)
    reach = np.asarray(lens.forward((first > 0).astype(np.float32))) > 0
    assert 0.1 < reach.mean() < 0.9
    values = (np.asarray(lens.forward(first)) * rng.uniform(0.5, 2.0, lf.n_rays) + 1e-3
              ).astype(np.float32)
    ceiling = rng.random(lf.n_rays) < 0.3
    options = dict(method="smart", iterations=3, relaxation=2.0, pixel_threshold=0.0)
    want = reconstruct(values[reach], lens.select_rows(reach), initial=first,
                       ceiling=ceiling[reach], **options)
    got = reconstruct(values, lens, initial=first, ceiling=ceiling, **options)
    np.testing.assert_array_equal(got, want)
    assert not np.array_equal(got, first)


def test_the_smart_views_column_sums_are_kept_for_the_same_projector_and_rows(case, rng):
    _, lf, _, _, lens = case
    rows = rng.random(lf.n_rays) < 0.5
    first = lens.summed_row_view(rows)
    again = lens.summed_row_view(rows.copy())
    assert again is not first and again.n_pixels == int(rows.sum())
    assert again.column_sums() is first.column_sums()               # not summed again
    other = lens.summed_row_view(~rows)
    np.testing.assert_array_equal(other.column_sums(), lens.select_rows(~rows).column_sums())
    scaled = lens.scale_rows(np.full(lf.n_rays, 2.0)).summed_row_view(~rows)
    np.testing.assert_allclose(scaled.column_sums(), 2 * other.column_sums(), rtol=RTOL)
    # sums handed in for new rows are taken (and kept); for the kept rows they are not
    given = np.asarray(lens.select_rows(rows).column_sums()) + np.float32(1.0)
    taken = lens.summed_row_view(rows, column_sums=given)
    np.testing.assert_array_equal(taken.column_sums(), given)
    assert lens.summed_row_view(rows, column_sums=given * 0).column_sums() is taken.column_sums()


def test_line_of_sight_cell_sums_stand_for_the_coarse_back_projections(case, rng):
    """The line of sight's cells give the SMART view's column sums and "seen by a lit row".

    A voxel's weight is the mean of its cells' weights per unit area, so the used rows'
    coarse column sums are the pooled cell sums over kx·ky (float32 summation error, RTOL).
    Σ_used − Σ_dark on a cell is the lit rows' weight: no voxel that no lit row reaches is
    called lit (a zero-weight ray adds an exact zero), and a lit voxel is missed only where
    its lit weight is below float32 resolution of its dark weight.
    """
    from plenopiv.reconstruction import sightline
    from plenopiv.reconstruction.solve import touching_rows
    from plenopiv.reconstruction.weights import Weights

    name, lf, grid, _, lens = case
    w = Weights(lens, lf.pixel, grid, key=f"cell-sums-{name}")
    proj, _ = w.normalised
    volume = (rng.random(grid.n_voxels) * (rng.random(grid.n_voxels) < 0.02)).astype(np.float32)
    image = np.asarray(proj.forward(volume))
    touching = touching_rows(w)
    bright = touching & (image > 0.05 * image.max())
    used = touching & (np.asarray(proj.row_sums()) > 0)
    dark = touching & ~bright
    assert 0.05 < bright.sum() / touching.sum() < 0.95
    sl = sightline.subcell_sightline(w, lambda: lf, dark, rng.random(lf.n_rays), used,
                                     tolerance=0.5, footprint=lf.footprint)
    want = np.asarray(proj.back(used.astype(np.float32)))
    assert np.abs(sl.used_column_sums - want).max() <= RTOL * want.max()
    lit_weight = np.asarray(proj.back((used & ~dark).astype(np.float32)))
    dark_weight = np.asarray(proj.back(dark.astype(np.float32)))
    assert not (sl.seen_by_lit & (lit_weight <= 0)).any()
    missed = ~sl.seen_by_lit & (lit_weight > 0)
    assert (lit_weight[missed] <= RTOL * dark_weight[missed]).all()
    assert sl.seen_by_lit.sum() >= 0.999 * (lit_weight > 0).sum()
    # the cells' column sums: the used rows' back projection plus the others'
    kx, ky = sightline.subcell_factors(grid, lf.footprint)
    (z0, _), fine = sightline._refined_projectors(w, lambda: lf, kx, ky)[0]
    seen, _ = sightline._geometry_sums(fine, used.astype(np.float32), z0)
    ones = np.asarray(fine.column_sums())
    assert np.abs(seen - ones).max() <= RTOL * ones.max()


@pytest.mark.parametrize("geometry", ["rotated_10mrad", "hexagonal"])
def test_reconstruction_agrees_with_explicit_path(small_camera, geometry):
    """Same image, both projectors, the default ray model: the volumes agree (Q >= 0.99)."""
    cam = camera_of(small_camera, geometry, (21, 27))
    cal = Calibration.from_camera(cam)
    lf = light_field(cal)
    grid = small_grid(lf, nx=16, ny=12, nz=16, lateral=1.0, depth=3.0)
    rng = np.random.default_rng(5)
    half = np.array([8, 6, 24]) * lf.footprint * 0.8
    pos = rng.uniform(-half, half, (20, 3))
    img = particle_image(cam, pos, rays_per_particle=4000, seed=2)
    vols = {}
    for kind in ("sparse", "lattice"):
        s = ReconstructionSettings(projector=kind, iterations=5)
        vols[kind] = reconstruct_volume(cal, img, grid, settings=s).volume
    assert vols["sparse"].max() > 0
    assert reconstruction_quality(vols["lattice"], vols["sparse"]) >= 0.99


def test_auto_takes_the_lenslet_projector_when_weights_do_not_fit(small_camera):
    cal = Calibration.from_camera(camera_of(small_camera, "rotated_10mrad"))
    lf = light_field(cal)
    grid = small_grid(lf)
    assert choose_projector(lf, grid, max_weights_gb=1e3) == "sparse"
    budget = 1.01 * estimate_lenslet_gb(lf, grid)
    assert choose_projector(lf, grid, max_weights_gb=budget) == "lattice"
    w, cached = cached_weights(cal, grid, cache_dir=None, max_weights_gb=budget)
    assert w.matrix_free and not cached and isinstance(w.projector, LensletProjector)
    assert isinstance(matrix_free_projector(lf, grid), LensletProjector)
    with pytest.raises(ReconstructionError, match=r"matrix-free reconstruction of a 12 × 18 × "
                                                  r"22-voxel volume needs ~.* GB.*max_weights_gb"):
        choose_projector(lf, grid, max_weights_gb=0.5 * estimate_lenslet_gb(lf, grid))


def test_estimate_covers_the_volumes_and_rays(small_camera):
    lf = light_field(Calibration.from_camera(camera_of(small_camera, "hexagonal")))
    grid = small_grid(lf)
    assert estimate_lenslet_gb(lf, grid) * 1e9 >= 12 * 4 * grid.n_voxels + 30 * lf.n_rays


def test_a_lattice_it_cannot_take_is_refused(small_camera):
    """Lenslet labels that put every ray under one lenslet (a broken calibration): the
    micro-image spans the sensor, and the error names it and what to do."""
    lf = light_field(Calibration.from_camera(camera_of(small_camera, "rotated_10mrad")))
    broken = dataclasses.replace(lf, lenslet=np.zeros_like(lf.lenslet))
    with pytest.raises(ReconstructionError, match=r"lenslet 0 spans \d+ × \d+ pixels.*"
                                                  r"projector = \"sparse\""):
        LensletProjector.from_light_field(broken, small_grid(lf))


def test_profiles_stop_at_the_grid(small_camera):
    """A beam wholly outside the grid along an axis has no voxels (count 0, empty range)."""
    start = np.zeros(1, np.int64)
    count = np.zeros(1, np.int64)
    w = np.zeros((1, 4))
    shape = rk.cdf_shapes(np.array([0.02]), np.array([0.1]))[0]
    lo, hi = rk._profiles(np.array([0.0]), 1, 10.0, 1.0, shape, 0.06, 0.0, 0.1, 8,
                          start, count, w, np.zeros((6, 1)))
    assert count[0] == 0 and lo >= hi


def test_cli_refuses_a_rotated_volume_beyond_the_memory_limit(tmp_path, small_camera, capsys):
    """The CLI's error path: one ``error:`` line naming the figure and the key, exit 2."""
    import tifffile

    from plenopiv.camera.model import load_camera

    cam = load_camera("small_m1")
    mla = dataclasses.replace(cam.microlens_array, rotation=2e-3, offset=(3e-6, -2e-6))
    Calibration.from_camera(cam.replace(microlens_array=mla)).save(tmp_path / "cal.h5")
    img = np.zeros(cam.sensor.shape, np.uint16)
    img[::37, ::41] = 3000
    tifffile.imwrite(tmp_path / "a.tif", img)
    (tmp_path / "exp.toml").write_text(
        'camera = "small_m1"\n[volume]\nx_mm = [-1.0, 1.0]\ny_mm = [-1.0, 1.0]\n'
        'z_mm = [-1.5, 1.5]\nvoxel_mm = 0.125\n[reconstruction]\nmax_weights_gb = 1e-6\n'
        'lateral_subdivision = 1\n'
        '[output]\npng = false\nvtk = false\nweights_cache = ""\n')
    code = main(["reconstruct", str(tmp_path / "cal.h5"), str(tmp_path / "a.tif"), "--config",
                 str(tmp_path / "exp.toml"), "--out", str(tmp_path / "v.h5")])
    err = capsys.readouterr().err
    assert code == 2
    assert "error:" in err and "needs ~" in err and "max_weights_gb" in err
    assert not (tmp_path / "v.h5").exists()


def test_plan_takes_the_matrix_free_path_for_a_rotated_full_camera(auburn_camera):
    """``plenopiv plan`` agrees with the reconstruction: matrix-free, ~3 GB, and a volume
    1.30 times the aligned array's (measured at full size on an idle machine, wall time per
    volume of MLOS and 5 sweeps: 24.8 s rotated against 19.1 s aligned, the light-field
    particles' 10 s included in both; ``benchmarks/full_camera.py --lateral-subdivision 1``,
    docs/performance.md), within 15 %."""
    from plenopiv.workflow import planning

    mm = 1e-3
    grid = VolumeGrid.from_bounds((-37 * mm, 37 * mm), (-25 * mm, 25 * mm),
                                  (-26 * mm, 26 * mm), voxel=0.26 * mm)
    mla = dataclasses.replace(auburn_camera.microlens_array, rotation=2e-3)
    one = ReconstructionSettings(lateral_subdivision=1, iterations=5)     # as measured
    aligned = planning.plan(auburn_camera, grid, memory_total=24e9, reconstruction=one)
    rotated = planning.plan(auburn_camera.replace(microlens_array=mla), grid, memory_total=24e9,
                            reconstruction=one)
    assert rotated.decision.projector == "lenslet" and aligned.decision.projector == "lattice"
    assert rotated.projector == "lattice"
    # nothing stored per weight; at least the three float32 volumes SMART holds (estimate,
    # update, column sums) and a float32 per ray; and far below the explicit weights
    # (10 bytes per non-zero), which is why the matrix-free path was taken
    assert rotated.memory["weights"] == 0.0
    assert rotated.memory["reconstruct_peak"] >= 3 * 4 * grid.n_voxels + 4 * rotated.n_rays
    assert rotated.memory["peak"] < 0.25 * 10 * rotated.nnz
    assert rotated.time["volume"] / aligned.time["volume"] == pytest.approx(1.30, rel=0.15)


def test_explicit_weights_of_a_rotated_lattice_are_the_largest_thing_a_reconstruction_holds(
        small_camera):
    """Explicit weights on a lattice that is not axis-aligned: the sub-cell line-of-sight mask
    projects its refined slabs matrix-free, so a reconstruction allocates less than the
    weights themselves (the memory estimate, 10 bytes per non-zero, counts W once; here 0.6
    W, on a 25 x 36-lenslet patch of the 16 MP camera 0.03 W). Refined explicit weights,
    every slab kept for the next image, allocated 2.6 times W here and 2.5 times on that
    patch (3.8 GB beside 1.5 GB of W: the process of a 49 x 72 patch was killed at 21 GB)."""
    import tracemalloc

    cam = camera_of(small_camera, "rotated_10mrad", (21, 27))
    cal = Calibration.from_camera(cam)
    lf = light_field(cal)
    grid = small_grid(lf, nx=16, ny=12, nz=24, lateral=1.0, depth=2.0)
    img = particle_image(cam, np.zeros((1, 3)), rays_per_particle=4000, seed=2)
    s = ReconstructionSettings(projector="sparse", iterations=2)
    w, _ = cached_weights(cal, grid, cache_dir=None, projector="sparse")
    held = w.projector.nbytes
    tracemalloc.start()
    try:
        reconstruct_volume(cal, img, grid, settings=s, weights=w)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < held, (peak, held)
