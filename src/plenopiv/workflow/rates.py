"""The rates that turn a plan's sizes into times.

Measured on small samples of the reconstruction's and the PIV's own kernels in this process
(:func:`measure_rates`), or the benchmark's (:data:`BENCHMARK_RATES`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import CameraModel
from plenopiv.errors import ConfigError
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
                  lateral_subdivision: str | int = "auto", budget_s: float = 2.0) -> Rates:
    """Time the reconstruction's kernels and the PIV on samples of this plan.

    Each is timed at two sample sizes (the shortest of a few calls), which separates the rate
    per unit of work from the fixed cost per call: the weights of a few hundred lenslets'
    rays built on ``grid`` (the kernels of :mod:`plenopiv.reconstruction.weights`) and projected
    forward and back; the lattice projector on two patches of the camera, on the grid's
    slices and its voxels cut as the reconstruction will cut them (``lateral_subdivision``,
    ``[reconstruction] lateral_subdivision``); the PIV of two random particle volumes of two
    and three first windows a side. The first call also compiles the kernels (cached on
    disk), before any timing.
    """
    import numba

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
                                                       lateral_subdivision, 0.15 * budget_s)
    piv_rate, piv_call = _measure_piv(piv or PIVSettings(), grid, 0.2 * budget_s)
    return Rates(build_s_per_nnz=build_rate, sweep_s_per_nnz=sweep_rate,
                 sweep_s_per_call=sweep_call, lattice_s_per_ray_slice=lattice_rate,
                 lattice_s_per_call=lattice_call, piv_s_per_window_voxel=piv_rate,
                 piv_s_per_call=piv_call, source="measured", threads=numba.get_num_threads(),
                 lattice_subdivision=cut)


def _measure_lattice(camera: CameraModel, grid: VolumeGrid, f_number, min_lit: float,
                     lateral_subdivision, budget_s: float) -> tuple[float, float, tuple]:
    """``(rate, fixed, (ky, kx))`` of the lattice projector, :func:`measure_rates`'s terms.

    A forward and a back projection on patches of 7 and 19 lenslets a side, on the grid's
    slices and its voxels cut as the reconstruction will cut them; the benchmark rate where
    the lattice is not square.
    """
    from plenopiv.calibration.model import Calibration
    from plenopiv.camera.resolution import footprint
    from plenopiv.lightfield import light_field
    from plenopiv.reconstruction.choose import (
        model_projector_cost,
        subdivided_grid,
        subdivision_for,
    )
    from plenopiv.reconstruction.lattice import LatticeProjector

    mla = camera.microlens_array
    if mla.grid != "square":
        return BENCHMARK_RATES.lattice_s_per_ray_slice, 0.0, BENCHMARK_RATES.lattice_subdivision
    cut = tuple(int(k) for k in subdivision_for(footprint(camera), grid, lateral_subdivision,
                                                cost=model_projector_cost(camera)))
    points = []
    for k in sorted({min(7, mla.rows, mla.cols), min(19, mla.rows, mla.cols)}):
        plf = light_field(Calibration.from_camera(camera.patch(k, k)), f_number=f_number,
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

