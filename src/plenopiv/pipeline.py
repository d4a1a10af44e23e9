"""One image -> one volume; one image pair -> one vector field (orchestration, no physics).

::

    image --(weights from the calibration's S_i,eff)--> MART volume --> particles
          --> depth corrections (external n1/n2, internal n3/n4) --> products

The stages are the library's stage functions; this module chooses defaults, keeps the weights
(built once per geometry, cached on disk), reports progress and writes products atomically.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.camera import CameraModel
from plenopiv.config import ParticleSettings, ReconstructionSettings
from plenopiv.corrections import DepthCorrection
from plenopiv.errors import ReconstructionError
from plenopiv.io import check_image, write_h5
from plenopiv.lattice import LatticeProjector, separable_axes
from plenopiv.lightfield import light_field
from plenopiv.mart import mlos, reconstruct
from plenopiv.particles import find_particles
from plenopiv.volume import VolumeGrid
from plenopiv.weights import Weights, cached_weights, check_grid_in_view, weights_key

if TYPE_CHECKING:  # imported lazily at run time (scipy.fft, numba kernels)
    from plenopiv.piv import PIVSettings

Progress = Callable[[str, float], None] | None


@dataclass(frozen=True)
class VolumeResult:
    """A reconstructed volume and its particles.

    Attributes
    ----------
    volume : (nz, ny, nx) float32
        Reconstructed intensity on ``grid`` (effective coordinates).
    grid : VolumeGrid
        Effective (air-equivalent) grid of the reconstruction.
    correction : DepthCorrection
        From effective to physical depth.
    particle_position_effective : (N, 3)
        Particle (x, y, z) in effective coordinates, metres.
    particle_position : (N, 3)
        The same after the depth corrections, metres.
    particle_intensity, particle_size : (N,), (N, 3)
        Integrated intensity; blob σ along (x, y, z) in metres (effective).
    """

    volume: np.ndarray
    grid: VolumeGrid
    correction: DepthCorrection
    particle_position_effective: np.ndarray
    particle_position: np.ndarray
    particle_intensity: np.ndarray
    particle_size: np.ndarray
    timings: dict = field(default_factory=dict)

    @property
    def z_corrected(self) -> np.ndarray:
        """Physical depth of each voxel layer, metres."""
        return self.correction.depth(self.grid.z)

    def save(self, path: str | Path, *, config: dict | None = None, extra_attrs=None) -> Path:
        """Write the volume product (DESIGN.md §7), atomically."""
        ds = {"/volume": self.volume.astype(np.float32), "/x": self.grid.x, "/y": self.grid.y,
              "/z": self.z_corrected, "/z_effective": self.grid.z,
              "/particles/position_m": self.particle_position,
              "/particles/position_effective_m": self.particle_position_effective,
              "/particles/intensity": self.particle_intensity,
              "/particles/size_m": self.particle_size}
        units = {k: "m" for k in ("/x", "/y", "/z", "/z_effective", "/particles/position_m",
                                  "/particles/position_effective_m", "/particles/size_m")}
        attrs = {"n_particles": len(self.particle_position), "voxel_m": np.array(self.grid.voxel),
                 "depth_correction_scale": self.correction.scale,
                 "depth_correction_external": self.correction.external,
                 "depth_correction_internal": self.correction.internal,
                 "volume_axes": "z, y, x", **(extra_attrs or {})}
        return write_h5(path, ds, attrs=attrs, units=units, config=config, kind="volume")


def load_volume(path: str | Path) -> VolumeResult:
    """Read a volume product written by :meth:`VolumeResult.save`."""
    from plenopiv.io import open_product

    with open_product(path, "volume", ReconstructionError) as fh:
        x, y, ze = fh["/x"][()], fh["/y"][()], fh["/z_effective"][()]
        vol = fh["/volume"][()]
        corr = DepthCorrection(float(fh.attrs["depth_correction_external"]),
                               float(fh.attrs["depth_correction_internal"]))
        pos = fh["/particles/position_m"][()]
        pos_e = fh["/particles/position_effective_m"][()]
        inten = fh["/particles/intensity"][()]
        size = fh["/particles/size_m"][()]
    step = [a[1] - a[0] if len(a) > 1 else 1.0 for a in (x, y, ze)]
    grid = VolumeGrid((float(x[0]), float(y[0]), float(ze[0])), tuple(float(v) for v in step),
                      vol.shape)
    return VolumeResult(vol, grid, corr, pos_e, pos, inten, size)


def footprint(camera: CameraModel) -> float:
    """Lenslet footprint on the nominal focal plane, p_m S_o/S_i, metres."""
    return camera.microlens_array.pitch * camera.object_distance / camera.image_distance


def resolution_cell(camera: CameraModel, f_number: float | None = None) -> tuple[float, float]:
    """Lateral and depth resolution of the camera near the focal plane, metres.

    Lateral: one lenslet footprint b = p_m S_o/S_i. Depth: the views at the two edges of the
    aperture (diameter D = f_m/N) see a particle at depth Z displaced by D Z/S_o relative to
    each other, so two depths are told apart when that shift changes by one footprint:
    ΔZ = b S_o/D (0.55 mm for the 50 mm lens at M = -1, f/2.2). The ratio ΔZ/b = S_o/D is the
    depth elongation expected of a reconstructed particle. Give the effective camera
    (``calibration.effective_camera``) for effective coordinates.
    """
    n = camera.main_lens.f_number if f_number is None else f_number
    b = footprint(camera)
    return b, b * camera.object_distance * n / camera.main_lens.focal_length


def particle_options(particles: ParticleSettings, grid: VolumeGrid, calibration: Calibration,
                     volume, *, f_number: float | None = None) -> dict:
    """Keywords of :func:`~plenopiv.particles.find_particles` for ``particles`` and a volume.

    The threshold is ``particles.threshold`` times the reference intensity (the 99.9th
    percentile of the positive voxels, or the maximum). Unset separation and box follow the
    resolution cell (:func:`resolution_cell`) in voxels of ``grid``: peaks closer than one
    cell (1.5 cells laterally, so that diagonal neighbours merge) are one particle; the
    centroid box is ±1 cell.
    """
    v = np.asarray(volume)
    if particles.threshold_reference == "maximum":
        ref = float(v.max())
    else:
        pos = v[v > 0]
        ref = float(np.percentile(pos, 99.9)) if pos.size else 0.0
    lat, dep = resolution_cell(calibration.effective_camera, f_number)
    vx, vy, vz = (float(a) for a in grid.voxel)
    sep = particles.min_separation_vox
    if sep is None:
        sep = (max(dep / vz, 1.0), max(1.5 * lat / vy, 1.0), max(1.5 * lat / vx, 1.0))
    box = particles.box_vox
    if box is None:
        box = tuple(max(1, int(round(c / d))) for c, d in ((dep, vz), (lat, vy), (lat, vx)))
    return {"threshold": particles.threshold * ref, "method": particles.method,
            "min_separation_vox": tuple(sep), "box_vox": tuple(box),
            "fit_spacing_vox": particles.fit_spacing_vox}


#: Largest working voxel of the ``"auto"`` lateral subdivision, in lenslet footprints.
SUBDIVIDED_VOXEL_FOOTPRINTS = 1 / 3


def lateral_subdivision(calibration: Calibration, grid: VolumeGrid,
                        settings: ReconstructionSettings) -> tuple[int, int]:
    """Subdivision ``(ky, kx)`` of the lateral voxels during the reconstruction.

    ``settings.lateral_subdivision`` as given, or for ``"auto"`` the smallest k per axis for
    which the working voxel is at most a third of a lenslet footprint (5 % slack, at most
    :data:`plenopiv.config.MAX_SUBDIVISION`). Depth along a pixel's beam is told apart by
    the beams of the other views shifting sideways by a fraction of a footprint; voxels a
    footprint wide hold those shifts in one voxel, and the reconstructed particle is 2-3
    times longer in depth than with half-footprint voxels. On the CI camera (Oseen, 0.3
    particles per lenslet, footprint voxels) the w gain is 0.73 with k = 2, 0.89 with 3 and
    0.89 with 4 (w rms 0.60, 0.48, 0.40 voxel; without subdivision see
    docs/validation/vortex.md).
    """
    from plenopiv.config import MAX_SUBDIVISION

    k = settings.lateral_subdivision
    if k != "auto":
        return int(k), int(k)
    half = SUBDIVIDED_VOXEL_FOOTPRINTS * footprint(calibration.effective_camera)
    return tuple(int(min(MAX_SUBDIVISION, max(1, math.ceil(d / half - 0.05))))
                 for d in (grid.voxel[1], grid.voxel[0]))


def subdivided_grid(grid: VolumeGrid, ky: int, kx: int) -> VolumeGrid:
    """``grid`` with every voxel cut into ``ky × kx`` laterally (same box, same depth)."""
    dx, dy, dz = grid.voxel
    ox, oy, oz = grid.origin
    nz, ny, nx = grid.shape
    return VolumeGrid((ox - 0.5 * dx + 0.5 * dx / kx, oy - 0.5 * dy + 0.5 * dy / ky, oz),
                      (dx / kx, dy / ky, dz), (nz, ny * ky, nx * kx))


def reconstruction_grid(calibration: Calibration, grid: VolumeGrid,
                        settings: ReconstructionSettings) -> VolumeGrid:
    """The working grid of a reconstruction on ``grid``: laterally subdivided
    (:func:`lateral_subdivision`)."""
    return subdivided_grid(grid, *lateral_subdivision(calibration, grid, settings))


def merge_subdivided(volume, ky: int, kx: int, *, kernel: str = "gaussian") -> np.ndarray:
    """A volume of laterally subdivided voxels back on the grid it subdivides, float32.

    ``volume`` is ``(nz, ny * ky, nx * kx)`` (:func:`subdivided_grid`). ``"box"`` sums each
    voxel's ``ky × kx`` working voxels. ``"gaussian"`` weights the working volume by a
    Gaussian of σ = half a voxel (``k/2`` working voxels) about each voxel's centre (linear
    between the two middle working voxels for an even k), scaled by ``ky kx`` so that the
    total is kept: a particle narrower than a voxel then spreads over its neighbours in the
    ratio of where it lies inside the voxel, which the box sum loses (the peak locking of
    voxels a lenslet footprint wide: docs/validation/vortex.md). The samples of a Gaussian
    of half a voxel sum to 1 within ±1.4 % per axis (2 exp(-π²/2)), a ripple of a particle's
    merged intensity with its position inside the voxel.
    """
    import scipy.ndimage

    v = np.asarray(volume, dtype=np.float32)
    nz, wy, wx = v.shape
    if wy % ky or wx % kx:
        raise ValueError(f"volume of shape {v.shape} is not subdivided by ({ky}, {kx})")
    if kernel == "box":
        return v.reshape(nz, wy // ky, ky, wx // kx, kx).sum(axis=(2, 4), dtype=np.float32)
    if kernel != "gaussian":
        raise ValueError(f"kernel = {kernel!r}: expected 'gaussian' or 'box'")
    for axis, k in ((1, ky), (2, kx)):
        if k == 1:
            continue
        f = scipy.ndimage.gaussian_filter1d(v, 0.5 * k, axis=axis, mode="constant")
        take = [slice(None)] * 3
        take[axis] = slice(k // 2, None, k)
        sampled = f[tuple(take)]
        if k % 2 == 0:             # the centre lies between two working voxels
            take[axis] = slice(k // 2 - 1, None, k)
            sampled = 0.5 * (sampled + f[tuple(take)])
        v = (sampled * k).astype(np.float32)
    return v


def _subdivision_of(work: VolumeGrid, grid: VolumeGrid) -> tuple[int, int]:
    """``(ky, kx)`` when ``work`` is ``grid`` subdivided laterally, else ReconstructionError."""
    nz, ny, nx = grid.shape
    wz, wy, wx = work.shape
    if wz == nz and wy % ny == 0 and wx % nx == 0:
        ky, kx = wy // ny, wx // nx
        expect = subdivided_grid(grid, ky, kx)
        scale = max(grid.voxel)
        if (np.allclose(expect.origin, work.origin, rtol=0, atol=1e-9 * scale)
                and np.allclose(expect.voxel, work.voxel, rtol=1e-9, atol=0)):
            return ky, kx
    raise ReconstructionError("the given weights were built for another volume grid (neither "
                              "the volume's grid nor a lateral subdivision of it)")


def weights_for(calibration: Calibration, grid: VolumeGrid, settings: ReconstructionSettings,
                cache_dir: str | Path | None = None) -> tuple[Weights, bool]:
    """The weights a reconstruction on ``grid`` with ``settings`` uses: explicit (cached in
    ``cache_dir``) or the matrix-free lattice projector, by ``settings.projector``, on the
    laterally subdivided working grid (:func:`reconstruction_grid`); ``(weights, from_cache)``.

    Row-action and block MART walk explicit rows, so ``"auto"`` keeps them explicit; SMART
    on a subdivided grid takes the matrix-free projector where the lattice allows. With
    ``lateral_subdivision = "auto"``, weights that would not fit in memory on a lattice the
    matrix-free projector cannot take (rotated or hexagonal) fall back to a coarser
    subdivision, with a warning, instead of failing.
    """
    projector = settings.projector
    if projector == "auto" and settings.method != "smart":
        projector = "sparse"
    ky, kx = lateral_subdivision(calibration, grid, settings)
    if projector == "auto" and (ky, kx) != (1, 1):
        # a subdivided grid has k² times the explicit weights; the matrix-free projector is
        # built in seconds and projects it about ten times faster (docs/validation/vortex.md)
        lf = light_field(calibration, f_number=settings.f_number, min_lit=settings.min_lit)
        if separable_axes(lf) is not None:
            work = subdivided_grid(grid, ky, kx)
            check_grid_in_view(lf, work)
            key = weights_key(calibration, work, f_number=settings.f_number,
                              min_lit=settings.min_lit, min_weight=1e-7)
            return Weights(LatticeProjector.from_light_field(lf, work), lf.pixel, work,
                           key), False
    while True:
        try:
            return cached_weights(calibration, subdivided_grid(grid, ky, kx),
                                  cache_dir=cache_dir, f_number=settings.f_number,
                                  min_lit=settings.min_lit, projector=projector,
                                  max_weights_gb=settings.max_weights_gb)
        except ReconstructionError as exc:
            if (settings.lateral_subdivision != "auto" or max(ky, kx) == 1
                    or "max_weights_gb" not in str(exc)):
                raise
            warnings.warn(f"lateral_subdivision = \"auto\": the weights of a {ky} x {kx} "
                          f"subdivision do not fit ({exc}); trying "
                          f"{max(1, ky - 1)} x {max(1, kx - 1)}", stacklevel=2)
            ky, kx = max(1, ky - 1), max(1, kx - 1)


def reconstruct_volume(calibration: Calibration, image, grid: VolumeGrid, *,
                       settings: ReconstructionSettings = ReconstructionSettings(),
                       particles: ParticleSettings = ParticleSettings(),
                       weights: Weights | None = None, cache_dir: str | Path | None = None,
                       progress: Progress = None) -> VolumeResult:
    """Reconstruct one image into a volume and extract its particles.

    Parameters
    ----------
    calibration : Calibration
    image : ndarray
        Raw plenoptic image of the calibration's sensor shape.
    grid : VolumeGrid
        Effective (air-equivalent) reconstruction grid.
    weights : Weights, optional
        Pre-built weights for this calibration (e.g. shared by a pair): from
        :func:`weights_for`, on the working grid; weights built for ``grid`` itself
        reconstruct on it without subdivision. Default: :func:`weights_for`.
    cache_dir : path, optional
        Weight cache folder (used when ``weights`` is not given).
    progress : callable, optional
        ``progress(stage, fraction)`` for long stages.
    """
    t = {}
    t0 = time.perf_counter()
    img = check_image(image, shape=calibration.camera.sensor.shape, name="particle image")
    if weights is None:
        weights, _ = weights_for(calibration, grid, settings, cache_dir=cache_dir)
    ky, kx = (1, 1) if weights.grid == grid else _subdivision_of(weights.grid, grid)
    if weights.matrix_free and settings.method != "smart":
        raise ReconstructionError(
            f"[reconstruction] method = {settings.method!r} walks the rows of explicit weights; "
            "the matrix-free lattice projector supports method = \"smart\" only")
    t["weights_s"] = time.perf_counter() - t0
    proj, row_scale = weights.normalised
    raw = weights.image_vector(img)
    threshold = settings.pixel_threshold * float(img.max())
    # rows that barely touch the volume (their beam mostly passes beside it) would claim the
    # light of particles outside the volume: leave them out
    nonempty = weights.row_max > 0
    touching = nonempty & (row_scale >= 0.25 * float(np.percentile(row_scale[nonempty], 95)))
    bright = (raw > threshold) & touching
    if not bright.any():
        raise ReconstructionError(f"no pixel seen by the volume is above the threshold "
                                  f"{threshold:g} ([reconstruction] pixel_threshold = "
                                  f"{settings.pixel_threshold}): is the volume in view?")
    values = (raw / row_scale).astype(np.float32)

    def report(iteration, _volume):
        if progress is not None:
            progress("mart", iteration / max(settings.iterations, 1))

    t1 = time.perf_counter()
    # Soft line-of-sight mask: a voxel is empty when most of the light that would reach the
    # sensor from it falls on dark pixels. (A hard "any dark pixel" rule would delete the
    # voxel holding a point particle: the voxel is wider than the particle, so some beams
    # through the voxel miss the particle and stay dark.)
    seen = np.asarray(proj.column_sums())
    dark_weight = np.asarray(proj.back(((raw <= threshold) & touching).astype(np.float32)))
    with np.errstate(invalid="ignore", divide="ignore"):
        keep = (seen > 0) & (dark_weight <= settings.dark_tolerance * seen)
    lit = proj.select_rows(bright)
    first = np.where(keep, mlos(values[bright], lit), np.float32(0.0))
    blocks = None
    if settings.method == "block":
        blocks = _perspective_blocks(weights, calibration, settings)[bright]
    vol = reconstruct(values[bright], lit, method=settings.method,
                      iterations=settings.iterations, relaxation=settings.relaxation_used,
                      pixel_threshold=0.0, blocks=blocks, initial=first,
                      shape=weights.grid.shape, callback=report)
    if ky > 1 or kx > 1:            # the working voxels back onto the volume's grid
        vol = merge_subdivided(vol, ky, kx, kernel=settings.subdivision_kernel)
    t["mart_s"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    vmax = float(vol.max())
    if vmax <= 0:
        raise ReconstructionError("the reconstructed volume is empty: no particle light in "
                                  "the volume (check [volume] and the image)")
    found = find_particles(vol, **particle_options(particles, grid, calibration, vol))
    eff = found.position_world(grid.origin, grid.voxel)
    corr = DepthCorrection.for_camera(calibration.camera, internal=particles.internal_correction)
    t["particles_s"] = time.perf_counter() - t2
    return VolumeResult(vol, grid, corr, eff, corr.points(eff) if len(eff) else eff,
                        found.intensity, found.size_world(grid.voxel), t)


def _perspective_blocks(weights: Weights, calibration: Calibration, settings) -> np.ndarray:
    """Block label of each weight row: its perspective view (aperture cell), so that a block
    holds one pixel per lenslet and its pixels share few voxels."""
    from plenopiv.lightfield import light_field

    lf = light_field(calibration, f_number=settings.f_number, min_lit=settings.min_lit)
    idx = np.searchsorted(lf.pixel, weights.pixel)       # lf.pixel is sorted
    cell = np.rint(lf.u[idx] / lf.cell)
    _, labels = np.unique(cell, axis=0, return_inverse=True)
    return labels.ravel().astype(np.int64)


def reconstruction_quality(volume, volume_true) -> float:
    """Q = Σ E E* / sqrt(Σ E² Σ E*²) (DESIGN.md §5)."""
    from plenopiv.mart import reconstruction_quality as q

    return q(volume, volume_true)


def gaussian_truth_volume(grid: VolumeGrid, positions, intensities=None, *,
                          sigma_vox=(1.0, 1.0, 1.0)) -> np.ndarray:
    """The true volume for Q: a Gaussian blob (σ in voxels, z y x) per particle, float32.

    ``positions`` are (x, y, z) in the grid's (effective) coordinates, metres.
    """
    from plenopiv.conventions import world_to_voxel

    vol = np.zeros(grid.shape, np.float32)
    p = world_to_voxel(np.asarray(positions, float), grid.origin, grid.voxel)
    w = np.ones(len(p)) if intensities is None else np.asarray(intensities, float)
    s = np.asarray(sigma_vox, float)
    r = np.ceil(3 * s).astype(int)
    for (cz, cy, cx), wi in zip(p, w, strict=True):
        lo = np.maximum(np.floor([cz, cy, cx]).astype(int) - r, 0)
        hi = np.minimum(np.floor([cz, cy, cx]).astype(int) + r + 2, grid.shape)
        if np.any(hi <= lo):
            continue
        zz, yy, xx = np.meshgrid(*(np.arange(a, b) for a, b in zip(lo, hi, strict=True)),
                                 indexing="ij")
        g = np.exp(-0.5 * (((zz - cz) / s[0]) ** 2 + ((yy - cy) / s[1]) ** 2
                           + ((xx - cx) / s[2]) ** 2))
        vol[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] += (wi * g).astype(np.float32)
    return vol


# --------------------------------------------------------------------------------------------
# vectors and pairs
# --------------------------------------------------------------------------------------------


def piv_settings(cfg) -> PIVSettings:
    """PIV settings from a ``[piv]`` config table (:class:`plenopiv.config.PIVConfig`)."""
    from plenopiv.piv import PIVSettings

    return PIVSettings(windows=tuple(tuple(w) for w in cfg.windows), overlap=cfg.overlap,
                       passes=cfg.passes, deformation=cfg.deformation,
                       median_threshold=cfg.median_threshold,
                       overlap_correction=cfg.overlap_correction, broad_peaks=cfg.broad_peaks)


@dataclass(frozen=True)
class VectorResult:
    """A 3-D vector field in physical coordinates.

    Attributes
    ----------
    x, y, z : 1-D arrays
        Window centres, metres; z is the physical depth (depth corrections applied).
    u, v, w : (nz, ny, nx)
        Displacement along x, y, z in metres (w corrected to physical depth).
    valid : (nz, ny, nx) bool
    snr : (nz, ny, nx)
        Correlation peak ratio.
    dt : float or None
        Seconds between exposures; velocity = displacement / dt.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    u: np.ndarray
    v: np.ndarray
    w: np.ndarray
    valid: np.ndarray
    snr: np.ndarray
    dt: float | None = None
    n_replaced: int = 0

    @classmethod
    def from_field(cls, field, correction: DepthCorrection, dt=None) -> VectorResult:
        """Convert a :class:`plenopiv.piv.VectorField` of effective coordinates."""
        return cls(np.asarray(field.x), np.asarray(field.y), correction.depth(field.z),
                   np.asarray(field.u), np.asarray(field.v), correction.depth(field.w),
                   np.asarray(field.valid), np.asarray(field.snr), dt, int(field.n_replaced))

    def save(self, path: str | Path, *, config: dict | None = None, vtk: bool = False,
             extra_attrs=None) -> list[Path]:
        """Write the vectors product (CF style HDF5), and a ``.vti`` for ParaView if asked.

        ``/u, /v, /w`` are displacements in metres, or velocities in m/s when ``dt`` is set
        (their ``units`` attribute says which).
        """
        scale, unit = (1.0, "m") if self.dt is None else (1.0 / self.dt, "m s-1")
        names = {"u": "x", "v": "y", "w": "z"}
        ds = {"/x": self.x, "/y": self.y, "/z": self.z, "/valid": self.valid.astype(np.int8),
              "/snr": self.snr}
        units = {"/x": "m", "/y": "m", "/z": "m", "/valid": "1", "/snr": "1"}
        for comp in "uvw":
            ds[f"/{comp}"] = (getattr(self, comp) * scale).astype(np.float32)
            units[f"/{comp}"] = unit
        attrs = {"dt_s": np.nan if self.dt is None else self.dt,
                 "quantity": "displacement" if self.dt is None else "velocity",
                 "n_replaced": self.n_replaced, "Conventions": "CF-1.8",
                 **(extra_attrs or {})}
        p = write_h5(path, ds, attrs=attrs, units=units, config=config, kind="vectors")
        _cf_dimensions(p, names)
        out = [p]
        if vtk:
            out.append(self.save_vtk(Path(path).with_suffix("")))
        return out

    def save_vtk(self, stem: Path) -> Path:
        """A ``.vti`` image data file (ParaView) with the vector field and validity."""
        from pyevtk.hl import imageToVTK

        from plenopiv.io import atomic_path

        def spacing(a):
            return float(a[1] - a[0]) if len(a) > 1 else 1.0

        origin = (float(self.x[0]), float(self.y[0]), float(self.z[0]))
        sp = (spacing(self.x), spacing(self.y), spacing(self.z))
        scale = 1.0 if self.dt is None else 1.0 / self.dt
        # VTK point data is x-fastest: transpose [z, y, x] -> [x, y, z]
        data = {"displacement" if self.dt is None else "velocity": tuple(
            np.ascontiguousarray((getattr(self, c) * scale).transpose(2, 1, 0), np.float64)
            for c in "uvw"),
            "valid": np.ascontiguousarray(self.valid.transpose(2, 1, 0), np.float64)}
        final = Path(str(stem) + ".vti")
        with atomic_path(final) as tmp:
            written = imageToVTK(str(tmp.with_suffix("")), origin=origin, spacing=sp,
                                 pointData=data)
            Path(written).replace(tmp)
        return final


def _cf_dimensions(path: Path, names) -> None:
    """Attach the 1-D coordinates as HDF5 dimension scales so that xarray/netCDF see them."""
    import h5py

    with h5py.File(path, "a") as fh:
        for axis in ("x", "y", "z"):
            fh[axis].make_scale(axis)
            fh[axis].attrs["axis"] = axis.upper()
            fh[axis].attrs["standard_name"] = {"x": "projection_x_coordinate",
                                               "y": "projection_y_coordinate",
                                               "z": "depth"}[axis]
        for name in ("u", "v", "w", "valid", "snr"):
            for dim, axis in enumerate(("z", "y", "x")):
                fh[name].dims[dim].attach_scale(fh[axis])
        for comp, axis in names.items():
            fh[comp].attrs["long_name"] = f"{fh.attrs['quantity']} along {axis}"


def correlate(result_a: VolumeResult, result_b: VolumeResult, settings=None, *, dt=None,
              workers=None, progress=None) -> VectorResult:
    """3-D PIV between two reconstructed volumes of the same grid (effective coordinates),
    returned in physical coordinates."""
    from plenopiv.piv import correlate_volumes

    if result_a.grid != result_b.grid:
        raise ReconstructionError("the two volumes were reconstructed on different grids")
    field = correlate_volumes(result_a.volume, result_b.volume, result_a.grid,
                              settings=settings, workers=workers, progress=progress)
    return VectorResult.from_field(field, result_a.correction, dt)


@dataclass(frozen=True)
class PairResult:
    """Everything one pair produced."""

    volume_a: VolumeResult
    volume_b: VolumeResult
    vectors: VectorResult
    timings: dict


def process_pair(calibration: Calibration, image_a, image_b, experiment, *,
                 weights: Weights | None = None, progress: Progress = None,
                 workers=None) -> PairResult:
    """Images A and B -> two volumes (weights built once) -> particles -> corrections ->
    vectors, with the experiment's settings (:class:`plenopiv.config.Experiment`)."""
    t0 = time.perf_counter()
    if weights is None:
        cache = experiment.output.weights_cache
        weights, _ = weights_for(calibration, experiment.volume, experiment.reconstruction,
                                 cache_dir=experiment.path(cache) if cache else None)
    kw = dict(settings=experiment.reconstruction, particles=experiment.particles,
              weights=weights, progress=progress)
    va = reconstruct_volume(calibration, image_a, experiment.volume, **kw)
    vb = reconstruct_volume(calibration, image_b, experiment.volume, **kw)
    t1 = time.perf_counter()
    vec = correlate(va, vb, piv_settings(experiment.piv), dt=experiment.images.dt_s,
                    workers=workers)
    t2 = time.perf_counter()
    return PairResult(va, vb, vec, {"reconstruct_s": t1 - t0, "piv_s": t2 - t1})


def save_pair(result: PairResult, out_dir: str | Path, name: str, experiment, *,
              extra_attrs=None) -> dict:
    """Write a pair's products: ``NAME_vectors.h5`` (+ ``.vti``), the two volumes, PNGs.

    The vectors file is written last and marked complete, so that a batch can resume.
    """
    out = Path(out_dir)
    cfg = experiment.to_dict()
    paths = {}
    for tag, vol in (("A", result.volume_a), ("B", result.volume_b)):
        paths[f"volume_{tag}"] = str(vol.save(out / f"{name}_volume_{tag}.h5", config=cfg))
    if experiment.output.png:
        from plenopiv.plots import vector_slices, volume_slices

        va = result.volume_a
        paths["png_volume"] = str(volume_slices(va.volume, va.grid.x, va.grid.y, va.grid.z,
                                                out / f"{name}_volume_A.png",
                                                particles=va.particle_position_effective))
        paths["png_vectors"] = str(vector_slices(result.vectors, out / f"{name}_vectors.png"))
    files = result.vectors.save(out / f"{name}_vectors.h5", config=cfg, vtk=experiment.output.vtk,
                                extra_attrs={"complete": True, **(extra_attrs or {})})
    paths["vectors"] = str(files[0])
    if len(files) > 1:
        paths["vtk"] = str(files[1])
    return paths


@dataclass(frozen=True)
class ExperimentPairProcess:
    """The per-pair work of ``plenopiv run``: picklable, so dask workers can run it.

    Each call loads the experiment and the calibration (small files), reads the pair's images,
    processes it with the weights from the on-disk cache (built once, before the batch) and
    writes the products; the vectors file is written last, marked complete.
    """

    experiment_path: str
    calibration_path: str
    out_dir: str

    def __call__(self, job) -> dict:
        """Process one :class:`plenopiv.batch.PairJob`; returns a small summary."""
        from plenopiv.config import load_experiment
        from plenopiv.io import read_image

        exp = load_experiment(self.experiment_path)
        cal = experiment_calibration(exp, self.calibration_path)
        ia, ib = read_image(job.image_a), read_image(job.image_b)
        res = process_pair(cal, ia, ib, exp)
        paths = save_pair(res, self.out_dir, job.name, exp,
                          extra_attrs={"image_a": str(job.image_a),
                                       "image_b": str(job.image_b)})
        vec = res.vectors
        return {"vectors": paths["vectors"], "valid_fraction": float(np.mean(vec.valid)),
                "n_particles_a": len(res.volume_a.particle_position),
                **{k: round(v, 3) for k, v in res.timings.items()}}


def experiment_calibration(experiment, calibration_path) -> Calibration:
    """The calibration to use with an experiment: S_i and the lenslets from the calibration
    product, the interfaces and back-side model from the experiment's camera."""
    cal = Calibration.load(calibration_path)
    cam = experiment.camera
    if (cal.camera.sensor.shape != cam.sensor.shape
            or cal.camera.microlens_array.pitch != cam.microlens_array.pitch):
        from plenopiv.errors import ConfigError

        raise ConfigError(f"the calibration {str(calibration_path)!r} was made for another "
                          f"camera (sensor {cal.camera.sensor.shape}, pitch "
                          f"{cal.camera.microlens_array.pitch * 1e6:g} µm) than the "
                          f"experiment's ({cam.sensor.shape}, "
                          f"{cam.microlens_array.pitch * 1e6:g} µm)")
    from dataclasses import replace

    return replace(cal, camera=cam.with_image_distance(cal.image_distance))
