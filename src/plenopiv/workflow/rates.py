"""The rates that turn a plan's sizes into times.

Measured on small samples of the reconstruction's and the PIV's own kernels in this process
(:func:`measure_rates`), or the benchmark's (:data:`BENCHMARK_RATES`). A matrix-free
reconstruction is also rehearsed whole on two patches of the camera (:class:`Rehearsal`):
its light field, line of sight, row and column sums and sweeps, as they run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import CameraModel
from plenopiv.errors import ConfigError, PlenopivError
from plenopiv.piv.settings import PIVSettings


@dataclass(frozen=True)
class Rates:
    """Seconds per unit of work, and where they come from.

    build_s_per_nnz : building explicit weights (count + fill), per non-zero.
    sweep_s_per_nnz : one forward plus one back projection with explicit weights, per non-zero.
    sweep_s_per_call : the same, per sweep, whatever the non-zeros (the grid's voxels).
    lattice_s_per_call, piv_s_per_call : the fixed cost of a lattice sweep, of a PIV.
    lattice_s_per_ray_slice : one forward plus one back projection with the lattice projector,
        per ray and depth slice, on voxels cut ``lattice_subdivision`` laterally.
    piv_s_per_window_voxel : 3-D PIV, per window voxel correlated (summed over the windows of
        every pass; the deformation of the volumes between passes included).
    lattice_subdivision : ``(ky, kx)`` the lattice rate was measured at: the reconstruction's
        own subdivision of the planned grid (a sweep's cost grows more slowly than
        ``ky kx`` on a small grid, about as ``ky kx`` on a large one).
    source : "measured" (in this process) or "benchmark".
    threads : numba threads the rates were measured with.
    rehearsal : the matrix-free reconstruction rehearsed whole, or None.
    """

    build_s_per_nnz: float
    sweep_s_per_nnz: float
    lattice_s_per_ray_slice: float
    piv_s_per_window_voxel: float
    source: str
    sweep_s_per_call: float = 0.0
    lattice_s_per_call: float = 0.0
    piv_s_per_call: float = 0.0
    threads: int = 2
    lattice_subdivision: tuple[int, int] = (1, 1)
    rehearsal: Rehearsal | None = None


@dataclass(frozen=True)
class Rehearsal:
    """Seconds of a matrix-free reconstruction rehearsed on two patches of the camera.

    weights_s_per_ray : the weights (light field, projector tables, row maxima) per
        light-field ray, on the grid's depth slices.
    volume_s_per_ray_slice : one volume of an image (line of sight, first guess, sweeps; not
        the particles) per ray and depth slice.
    first_s_per_ray_slice : what the first volume of a weights object adds (row and column
        sums, the line of sight's refined projectors and their cell sums).
    check_s_per_pixel : the check of a recording against its calibration, per sensor pixel.
    projector, subdivision, iterations : the reconstruction rehearsed; its figures stand
        for that one alone.

    Each is the larger patch's time over its work, not a slope through both patches: the
    larger one's arrays outgrow the caches as the camera's do, and the time per unit of a
    larger problem is higher still (the 16 MP camera's weights cost about twice a patch's per
    ray: docs/performance.md#the-plan-against-the-run).
    """

    weights_s_per_ray: float
    volume_s_per_ray_slice: float
    first_s_per_ray_slice: float
    check_s_per_pixel: float
    projector: str
    subdivision: tuple[int, int]
    iterations: int

    def matches(self, projector: str, subdivision, iterations: int) -> bool:
        """Whether these figures are those of this reconstruction."""
        return (self.projector == projector and tuple(subdivision) == self.subdivision
                and iterations == self.iterations)


#: Lenslets a side of the patches the reconstruction is rehearsed on (the camera's size where
#: smaller): the larger one's arrays outgrow the processor's caches, as the camera's do.
REHEARSAL_PATCHES = (19, 41)
#: Particles per lenslet of the rehearsal's image.
REHEARSAL_SEEDING = 0.15


BENCHMARK_RATES = Rates(build_s_per_nnz=1.2e-7, sweep_s_per_nnz=1.5e-8, sweep_s_per_call=0.07,
                        lattice_s_per_ray_slice=1.2e-9, piv_s_per_window_voxel=4e-8,
                        source="benchmark", threads=2)


def _best(fn, budget_s: float, min_reps: int = 2, max_reps: int = 10) -> float:
    """Shortest time of a few calls of ``fn`` (the least disturbed by other work)."""
    best, start, reps = math.inf, time.perf_counter(), 0
    while reps < min_reps or (time.perf_counter() - start < budget_s and reps < max_reps):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
        reps += 1
    return best


def _slope(x1: float, t1: float, x2: float, t2: float) -> tuple[float, float]:
    """``(rate, fixed)`` with t = fixed + rate x through two timings.

    The rate is kept at least a quarter of t2/x2 (timing noise on a busy computer).
    """
    rate = (t2 - t1) / (x2 - x1) if x2 > x1 else t2 / x2
    rate = max(rate, 0.25 * t2 / x2)
    return rate, max(t2 - rate * x2, 0.0)


def measure_rates(camera: CameraModel, grid: VolumeGrid, *, f_number=None,
                  min_lit: float = 0.5, piv: PIVSettings | None = None,
                  lateral_subdivision: str | int = "auto", budget_s: float = 2.0,
                  reconstruction=None) -> Rates:
    """Time the reconstruction's kernels and the PIV on samples of this plan.

    Each is timed at two sample sizes (the shortest of a few calls), which separates the rate
    per unit of work from the fixed cost per call: the weights of a few hundred lenslets'
    rays built on ``grid`` (the kernels of :mod:`plenopiv.reconstruction.weights`) and projected
    forward and back; the lattice projector on two patches of the camera, on the grid's
    slices and its voxels cut as the reconstruction will cut them (``lateral_subdivision``,
    ``[reconstruction] lateral_subdivision``); the PIV of two random particle volumes of two
    and three first windows a side. The first call also compiles the kernels (cached on
    disk), before any timing. ``reconstruction`` (``[reconstruction]``, whose f-number,
    ``min_lit`` and subdivision then win) also has a matrix-free reconstruction rehearsed
    (:func:`rehearse`).
    """
    import numba

    depth_binning = "auto"
    if reconstruction is not None:
        f_number, min_lit = reconstruction.f_number, reconstruction.min_lit
        lateral_subdivision = reconstruction.lateral_subdivision
        depth_binning = reconstruction.depth_binning
    cut_setting = (lateral_subdivision, depth_binning, f_number)

    from plenopiv.reconstruction._kernels import weights as K
    from plenopiv.reconstruction.projector import SparseProjector

    u, lit, lf = _ray_pattern(camera, f_number, min_lit)
    mla = camera.microlens_array
    centres = mla.nominal_centres() / camera.magnification
    b = grid.bounds
    inside = np.flatnonzero((centres[:, 0] >= b[0, 0]) & (centres[:, 0] <= b[0, 1])
                            & (centres[:, 1] >= b[1, 0]) & (centres[:, 1] <= b[1, 1]))
    if not len(inside):
        inside = np.array([int(np.argmin(np.hypot(*centres.T)))])
    rng = np.random.default_rng(0)
    pick = rng.choice(inside, size=min(len(inside), 128), replace=False)
    xf = np.repeat(centres[pick], len(u), axis=0)
    uu = np.tile(u, (len(pick), 1))
    ll = np.tile(lit, len(pick)).astype(np.float64)
    area = math.pi * lf.aperture_radius ** 2

    def args(n):
        return (np.ascontiguousarray(uu[:n, 0]), np.ascontiguousarray(uu[:n, 1]),
                np.ascontiguousarray(xf[:n, 0]), np.ascontiguousarray(xf[:n, 1]),
                np.ascontiguousarray(ll[:n]), lf.object_distance, lf.cell, lf.footprint, area,
                np.ascontiguousarray(grid.z, dtype=np.float64), grid.origin[0], grid.origin[1],
                grid.voxel[0], grid.voxel[1], grid.shape[2], grid.shape[1], 1e-7)

    def build(a):
        counts = K.count_nnz(*a)
        indptr = np.zeros(len(counts) + 1, np.int64)
        np.cumsum(counts, out=indptr[1:])
        idx = np.empty(indptr[-1], np.int32)
        data = np.empty(indptr[-1], np.float32)
        K.fill_rows(indptr, *a, idx, data)
        return indptr, idx, data

    build(args(1))                                   # compile (or load) the kernels
    vol = np.ones(grid.n_voxels, np.float32)
    samples = []
    for n in (max(len(uu) // 4, 1), len(uu)):
        a = args(n)
        t_build = _best(lambda a=a: build(a), 0.1 * budget_s)
        indptr, idx, data = build(a)
        proj = SparseProjector(indptr, idx, data, n_voxels=grid.n_voxels, check=False)
        img = np.ones(proj.n_pixels, np.float32)
        proj.back(proj.forward(vol))                 # compile, allocate the scratch
        t_sweep = _best(lambda p=proj, i=img: (p.back(i), p.forward(vol)), 0.1 * budget_s)
        samples.append((max(int(indptr[-1]), 1), t_build, t_sweep))
    (n1, b1, s1), (n2, b2, s2) = samples
    build_rate, _ = _slope(n1, b1, n2, b2)
    sweep_rate, sweep_call = _slope(n1, s1, n2, s2)

    lattice_rate, lattice_call, cut = _measure_lattice(camera, grid, f_number, min_lit,
                                                       cut_setting, 0.15 * budget_s)
    piv_rate, piv_call = _measure_piv(piv or PIVSettings(), grid, 0.2 * budget_s)
    rehearsal = None
    if reconstruction is not None:
        # a box the rehearsal cannot take is planned from the kernels' rates alone
        with contextlib.suppress(PlenopivError):
            rehearsal = rehearse(camera, grid, reconstruction,
                                 _subdivision(camera, grid, cut_setting))
    return Rates(build_s_per_nnz=build_rate, sweep_s_per_nnz=sweep_rate,
                 sweep_s_per_call=sweep_call, lattice_s_per_ray_slice=lattice_rate,
                 lattice_s_per_call=lattice_call, piv_s_per_window_voxel=piv_rate,
                 piv_s_per_call=piv_call, source="measured", threads=numba.get_num_threads(),
                 lattice_subdivision=cut, rehearsal=rehearsal)


def _subdivision(camera: CameraModel, grid: VolumeGrid, setting: tuple) -> tuple:
    """``(ky, kx)``: the reconstruction's cut of ``grid`` as the camera model judges it.

    ``setting``: ``(lateral_subdivision, depth_binning, f_number)`` of ``[reconstruction]``.
    """
    from plenopiv.camera.resolution import footprint, resolution_cell
    from plenopiv.reconstruction.choose import (
        depth_binning_for,
        model_projector_cost,
        subdivision_for,
    )

    lateral, binning, f_number = setting
    kz = depth_binning_for(resolution_cell(camera, f_number)[1], grid, binning)
    return tuple(int(k) for k in subdivision_for(footprint(camera), grid, lateral,
                                                 cost=model_projector_cost(camera),
                                                 depth_binning=kz))


def _measure_lattice(camera: CameraModel, grid: VolumeGrid, f_number, min_lit: float,
                     cut_setting: tuple, budget_s: float) -> tuple[float, float, tuple]:
    """``(rate, fixed, (ky, kx))`` of the lattice projector, :func:`measure_rates`'s terms.

    A forward and a back projection on patches of 7 and 19 lenslets a side, on the grid's
    slices and its voxels cut as the reconstruction will cut them; the benchmark rate where
    the lattice is not square. A turned or shifted square lattice is timed as made straight
    (the separable projector's rate, which the plan scales for the per-lenslet one); the
    subdivision is the camera's own.
    """
    from plenopiv.calibration.model import Calibration
    from plenopiv.lightfield import light_field
    from plenopiv.reconstruction.choose import (
        subdivided_grid,
    )
    from plenopiv.reconstruction.lattice import LatticeProjector

    mla = camera.microlens_array
    if mla.grid != "square":
        return BENCHMARK_RATES.lattice_s_per_ray_slice, 0.0, BENCHMARK_RATES.lattice_subdivision
    cut = _subdivision(camera, grid, cut_setting)
    straight = camera.replace(microlens_array=dataclasses.replace(mla, rotation=0.0,
                                                                  offset=(0.0, 0.0)))
    points = []
    for k in sorted({min(7, mla.rows, mla.cols), min(19, mla.rows, mla.cols)}):
        plf = light_field(Calibration.from_camera(straight.patch(k, k)), f_number=f_number,
                          min_lit=min_lit, edge_centroid=False)
        half = np.abs(plf.focal_plane_position).max(axis=0) + plf.footprint
        sub = subdivided_grid(VolumeGrid.from_bounds(
            (-half[0], half[0]), (-half[1], half[1]), tuple(grid.bounds[2]),
            voxel=grid.voxel), *cut)
        lp = LatticeProjector.from_light_field(plf, sub)
        vs = np.ones(sub.n_voxels, np.float32)
        ones = np.ones(lp.n_pixels, np.float32)
        lp.back(lp.forward(vs))
        t = _best(lambda lp=lp, o=ones, v=vs: (lp.back(o), lp.forward(v)), budget_s)
        points.append((lp.n_pixels * sub.shape[0], t))
    if len(points) == 2:
        return (*_slope(*points[0], *points[1]), cut)
    return points[0][1] / points[0][0], 0.0, cut


def rehearse(camera: CameraModel, grid: VolumeGrid, settings, cut, *,
             budget_s: float = 2.0) -> Rehearsal | None:
    """Rehearse a matrix-free reconstruction on a patch of the camera (:data:`REHEARSAL_PATCHES`).

    Each patch's calibration is the camera's own; its grid covers the same share of the
    patch's field of view as ``grid`` does of the camera's, on ``grid``'s voxels and depth
    slices, cut ``cut = (ky, kx)`` as the reconstruction will cut them; its image is the
    forward projection of one bright voxel per 1 / :data:`REHEARSAL_SEEDING` lenslets.
    Timed on the larger patch: the check of the image against the calibration, the weights,
    the first volume and a second one of the same image, each the shortest of the runs that
    ``budget_s`` allows (at least two: one alone varies by a fifth); a tiny patch and
    the smaller one run first, untimed, to compile the kernels and settle the caches. The
    patch takes the matrix-free projector its lattice allows; None where ``settings`` ask
    for explicit weights (or a method that walks their rows) or the cut is not square.
    """
    if cut[0] != cut[1] or settings.projector == "sparse" or settings.method != "smart":
        return None
    # matrix-free as the camera would take it: a patch's explicit weights would fit where
    # the camera's do not
    settings = dataclasses.replace(settings, lateral_subdivision=int(cut[0]),
                                   projector="lattice")
    mla = camera.microlens_array
    share = covered_share(camera, grid)
    sizes = sorted({min(k, mla.rows, mla.cols) for k in REHEARSAL_PATCHES})
    for k in [min(5, *sizes), *sizes[:-1]]:
        _rehearse_patch(camera, k, grid, share, settings)
    best, start, runs = None, time.perf_counter(), 0
    while runs < 2 or time.perf_counter() - start < budget_s:
        runs += 1
        run = _rehearse_patch(camera, sizes[-1], grid, share, settings)
        if run is None:
            return None
        seconds, (kind, n_rays, ray_slices, n_pixels) = run
        best = seconds if best is None else tuple(map(min, best, seconds))
    t_check, t_weights, t_first, t_volume = best
    return Rehearsal(weights_s_per_ray=t_weights / n_rays,
                     volume_s_per_ray_slice=t_volume / ray_slices,
                     first_s_per_ray_slice=max(t_first - t_volume, 0.0) / ray_slices,
                     check_s_per_pixel=t_check / n_pixels, projector=kind,
                     subdivision=tuple(int(c) for c in cut), iterations=settings.iterations)


def covered_share(camera: CameraModel, grid: VolumeGrid) -> np.ndarray:
    """The share (x, y) of the camera's field of view that ``grid`` covers, 0 to 1.

    Its width inside the field over the field's, wherever the box lies in it.
    """
    from plenopiv.synthetic.images import field_of_view

    half = np.asarray(field_of_view(camera), dtype=np.float64)
    b = np.asarray(grid.bounds[:2], dtype=np.float64)
    inside = np.minimum(b[:, 1], half) - np.maximum(b[:, 0], -half)
    return np.clip(inside / (2.0 * half), 0.0, 1.0)


def _rehearse_patch(camera: CameraModel, k: int, grid: VolumeGrid, share, settings):
    """One rehearsal on a k × k patch: ``(seconds, sizes)``, or None for explicit weights.

    ``seconds``: the check of the recording against its calibration (``[reconstruction]
    lattice_check``), the weights, the first volume and the second; ``sizes``: the
    projector's kind, the rays, the rays times depth slices and the sensor's pixels.
    """
    import warnings

    from plenopiv.calibration.model import Calibration
    from plenopiv.reconstruction.build import weights_for
    from plenopiv.reconstruction.solve import solve_volume
    from plenopiv.synthetic.images import field_of_view
    from plenopiv.workflow.volume import check_lattice

    cal = Calibration.from_camera(camera.patch(k, k))
    half = np.maximum(np.asarray(field_of_view(cal.effective_camera)) * share,
                      2.0 * np.asarray(grid.voxel[:2], dtype=np.float64))
    patch_grid = VolumeGrid.from_bounds((-half[0], half[0]), (-half[1], half[1]),
                                        tuple(grid.bounds[2]), voxel=grid.voxel)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        weights, _ = weights_for(cal, patch_grid, settings)
        _ = weights.normalised
        seconds = [time.perf_counter() - t0]
        kind = _KINDS.get(type(weights.projector).__name__)
        if kind is None:
            return None
        image = _rehearsal_image(weights, cal.camera.sensor.shape, k * k * float(np.prod(share)))
        t0 = time.perf_counter()
        with contextlib.suppress(PlenopivError):
            check_lattice(cal, [image], settings)
        seconds.insert(0, time.perf_counter() - t0)
        for _volume in range(2):
            t0 = time.perf_counter()
            solve_volume(weights, image, settings)
            seconds.append(time.perf_counter() - t0)
    n_rays = len(weights.pixel)
    return tuple(seconds), (kind, n_rays, n_rays * weights.grid.shape[0], image.size)


#: The matrix-free projectors by class, as :class:`ReconstructionChoice` names them.
_KINDS = {"LatticeProjector": "lattice", "LensletProjector": "lenslet"}


def _rehearsal_image(weights, shape, lenslets: float) -> np.ndarray:
    """A sensor image of bright voxels scattered through the weights' grid (counts).

    :data:`REHEARSAL_SEEDING` per lenslet of the ``lenslets`` the grid covers.
    """
    rng = np.random.default_rng(0)
    n = max(1, int(round(REHEARSAL_SEEDING * lenslets)))
    volume = np.zeros(weights.grid.n_voxels, np.float32)
    volume[rng.choice(weights.grid.n_voxels, size=n, replace=False)] = 1.0
    return weights.forward_image(volume, shape) * np.float32(1000.0)


def _window_voxels(shape, windows, overlap, passes) -> float:
    """Window voxels correlated over all passes (the PIV's work)."""
    total = 0.0
    for k, n in enumerate(vectors_per_pass(shape, windows, overlap, passes)):
        w = windows[min(k, len(windows) - 1)]
        total += float(np.prod(n)) * float(np.prod(w))
    return total


def _measure_piv(cfg: PIVSettings, grid: VolumeGrid, budget_s: float) -> tuple[float, float]:
    """``(seconds per window voxel, seconds per call)`` of this plan's PIV.

    Correlations of two random particle volumes of two and three first windows a side (the
    grid where smaller), after a small run that compiles the kernels.
    """
    from plenopiv.piv import correlate_volumes

    rng = np.random.default_rng(1)
    points = []
    for scale in (0.0, 2.0, 3.0):            # the first, tiny run compiles the kernels
        shape = tuple(int(min(n, max(8, scale * w))) for n, w in
                      zip(grid.shape, cfg.windows[0], strict=True))
        windows = [tuple(min(w, n) for w, n in zip(ws, shape, strict=True))
                   for ws in cfg.windows]
        run = dataclasses.replace(cfg, windows=windows)
        a = np.zeros(shape, np.float32)
        idx = tuple(rng.integers(0, n, max(8, int(np.prod(shape) / 300))) for n in shape)
        a[idx] = 1.0
        bb = np.roll(a, 1, axis=2)
        g = VolumeGrid((0.0, 0.0, 0.0), tuple(float(v) for v in grid.voxel), shape)
        t = _best(lambda a=a, bb=bb, g=g, run=run: correlate_volumes(a, bb, g, settings=run),
                  budget_s / 2, min_reps=1, max_reps=3)
        if scale:
            points.append((_window_voxels(shape, windows, cfg.overlap, run.passes), t))
    (x1, t1), (x2, t2) = points
    if x2 <= x1:
        return t2 / max(x2, 1.0), 0.0
    return _slope(x1, t1, x2, t2)


def vectors_per_pass(shape, windows, overlap: float, passes: int):
    """Vectors ``(nz, ny, nx)`` of every pass (0 along an axis the window does not fit)."""
    out = []
    for k in range(passes):
        w = windows[min(k, len(windows) - 1)]
        counts = []
        for n, wk in zip(shape, w, strict=True):
            step = max(1, int(round(wk * (1 - overlap))))
            counts.append(0 if wk > n else (n - wk) // step + 1)
        out.append(tuple(counts))
    return tuple(out)


def _ray_pattern(camera: CameraModel, f_number, min_lit):
    """Aperture positions ``u`` (R, 2) and ``lit`` (R,) of the rays of the lenslet on the axis.

    Returned with the light field's cell, footprint, aperture radius and S_o.
    """
    from plenopiv.calibration.model import Calibration
    from plenopiv.lightfield import light_field

    mla = camera.microlens_array
    patch = camera.patch(min(3, mla.rows), min(3, mla.cols))
    lf = light_field(Calibration.from_camera(patch), f_number=f_number, min_lit=min_lit)
    if not lf.n_rays:
        raise ConfigError(f"camera {camera.name!r}: no pixel is lit at this f-number")
    sel = lf.lenslet == lf.lenslet[int(np.argmin(np.hypot(*lf.s.T)))]
    return lf.u[sel], lf.lit[sel], lf

