"""Reconstruction quality of synthetic particle fields: Q, detection, ghosts, elongation.

A 61 × 91-lenslet patch of the Auburn camera with the 50 mm lens at M = -1 (S_i = S_o =
100 mm, f/2.2: the micro-images nearly fill the lenslets, no substrate) records random
particles seeded over its field of view and ±5 mm in depth, rendered by the ray tracer
(:func:`~plenopiv.synthetic.images.particle_image`). Each image is reconstructed by
:func:`~plenopiv.workflow.volume.reconstruct_volume` on a grid aligned with the lenslet
footprints and compared with the truth:

- Q = Σ E E* / sqrt(Σ E² Σ E*²) against Gaussian blobs at the true positions
  (:func:`~plenopiv.synthetic.truth.gaussian_truth_volume`), for several blob sizes, one of them
  matched to the reconstruction of isolated particles (:func:`matched_sigma`);
- detection rate, ghost rate, position error per axis and depth elongation of the particles
  that :func:`~plenopiv.particles.peaks.find_particles` extracts, matched one-to-one to the true
  particles within the camera's resolution cell (:func:`resolution_cell`).

The stage functions take arrays and small parameter objects and return arrays or dicts;
:func:`pipelines.studies.field_quality_report.run` runs them in order and does the I/O (JSON,
Markdown, PNG).

Conventions: positions are ``(x, y, z)`` metres, volumes ``[z, y, x]``; densities are
particles per lenslet (ppl), i.e. per lenslet footprint on the nominal focal plane, seeded
through the whole depth range.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import CameraModel, load_camera
from plenopiv.camera.resolution import footprint, resolution_cell
from plenopiv.conventions import world_to_voxel
from plenopiv.errors import ReconstructionError
from plenopiv.particles.settings import ParticleSettings
from plenopiv.products.volume import VolumeResult
from plenopiv.reconstruction.build import cached_weights, weights_for
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.weights import Weights
from plenopiv.settings import as_dict
from plenopiv.synthetic.images import finish_image, particle_image
from plenopiv.synthetic.seeding import SeedingBox, random_particles
from plenopiv.synthetic.truth import gaussian_truth_volume
from plenopiv.workflow.volume import reconstruct_volume

#: Densities of the main table, particles per lenslet.
DENSITIES = (0.05, 0.1, 0.2, 0.3)
#: MART variants and sweep counts of the main table.
METHODS = ("mart", "block", "smart")
ITERATIONS = (5, 10)
#: Particles are seeded in |Z| <= PARTICLE_DEPTH; the grid reaches GRID_DEPTH so that no
#: particle's depth-elongated blob is cut by the volume's end faces.
PARTICLE_DEPTH = 5e-3
GRID_DEPTH = 6e-3
#: Depth voxel, metres: about half the depth resolution cell (0.55 mm, :func:`resolution_cell`).
DEPTH_VOXEL = 0.25e-3
#: Aperture samples per particle of the ray tracer.
RAYS_PER_PARTICLE = 4096


def study_settings(**kw) -> ReconstructionSettings:
    """Reconstruction settings as this study ran them: 5 sweeps and relaxation 1 by default.

    A case may say otherwise. These were the library's defaults at the time; they are now 10
    sweeps with relaxation 2 for SMART, the "relaxation (smart)" row of the study.
    """
    kw.setdefault("iterations", 5)
    kw.setdefault("relaxation", 1.0)
    return ReconstructionSettings(**kw)


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


def study_camera(rows: int = 61, cols: int = 91, *, preset: str = "auburn_50mm") -> CameraModel:
    """Return a ``rows`` × ``cols``-lenslet patch of a preset camera, without substrate.

    :meth:`CameraModel.patch`; for ``auburn_50mm``: M = -1, f/2.2, the micro-images 114 µm
    across in the 125 µm pitch.
    """
    return load_camera(preset).patch(rows, cols, substrate=False)


def study_grid(camera: CameraModel, *, depth: float = GRID_DEPTH,
               depth_voxel: float = DEPTH_VOXEL, subdivision: int = 1) -> VolumeGrid:
    """Return the grid over the whole field of view and ``[-depth, depth]`` in Z.

    Laterally the voxels are one footprint (``subdivision = 1``) or a footprint / n wide and
    aligned with the footprints: the voxel edges fall on the footprint edges, so with n = 1
    each column of voxels is the footprint of one lenslet.
    """
    if subdivision < 1:
        raise ValueError(f"subdivision must be >= 1; got {subdivision!r}")
    b = footprint(camera)
    mla = camera.microlens_array
    hx, hy = mla.cols * b / 2, mla.rows * b / 2
    return VolumeGrid.from_bounds((-hx, hx), (-hy, hy), (-depth, depth),
                                  voxel=(b / subdivision, b / subdivision, depth_voxel))


def study_weights(calibration: Calibration, grid: VolumeGrid,
                  settings: ReconstructionSettings | None = None) -> Weights:
    """Build the voxel-pixel weights of ``grid`` in memory (no disk cache)."""
    s = study_settings() if settings is None else settings
    w, _ = cached_weights(calibration, grid, cache_dir=None, f_number=s.f_number,
                          min_lit=s.min_lit)
    return w


def interior_margin(camera: CameraModel, depth: float = PARTICLE_DEPTH) -> float:
    """Half-width of the blur disc on the focal plane of a particle at ``depth``, metres.

    A particle closer than this to the edge of the field of view sends part of its light past
    the lenslet array, so some of its views are missing; rates and Q are evaluated inside.
    """
    radius = camera.main_lens.focal_length / camera.main_lens.f_number / 2
    so = camera.object_distance
    return radius * depth / (so - depth)


# --------------------------------------------------------------------------------------------
# Particle fields
# --------------------------------------------------------------------------------------------


def seed_field(grid: VolumeGrid, camera: CameraModel, per_lenslet: float,
               rng: np.random.Generator, *, depth: float = PARTICLE_DEPTH) -> np.ndarray:
    """Seed random particles (N, 3), metres, uniformly over the grid's lateral extent.

    ``per_lenslet`` particles per lenslet footprint, through ``|Z| <= depth``.
    """
    b = grid.bounds
    box = SeedingBox(tuple(b[0]), tuple(b[1]), (-depth, depth))
    area = (b[0, 1] - b[0, 0]) * (b[1, 1] - b[1, 0]) / footprint(camera) ** 2
    return random_particles(box, int(round(per_lenslet * area)), rng)


def isolated_field(grid: VolumeGrid, camera: CameraModel, rng: np.random.Generator, *,
                   depth: float = PARTICLE_DEPTH, spacing_lenslets: int = 10) -> np.ndarray:
    """Particles that share no micro-image, (N, 3) metres.

    One per ``spacing_lenslets`` footprints along x and y (wider than the blur disc of a
    particle at ``depth``), inside :func:`interior_margin` of the field's edges, each at a
    random point of its footprint, at depths spread evenly over ``[-depth, depth]`` in random
    order.
    """
    b = footprint(camera)
    if 2 * interior_margin(camera, depth) > spacing_lenslets * b:
        raise ValueError(f"spacing_lenslets = {spacing_lenslets} is narrower than the blur disc "
                         f"at depth {depth * 1e3:g} mm")
    half = grid.bounds[:2, 1] - interior_margin(camera, depth) - b / 2
    kx, ky = (int(h // (spacing_lenslets * b)) for h in half)
    x = np.arange(-kx, kx + 1) * spacing_lenslets * b
    y = np.arange(-ky, ky + 1) * spacing_lenslets * b
    xx, yy = np.meshgrid(x, y)
    n = xx.size
    z = np.linspace(-depth, depth, n)
    rng.shuffle(z)
    jitter = rng.uniform(-0.5, 0.5, (n, 2)) * b
    return np.column_stack([xx.ravel() + jitter[:, 0], yy.ravel() + jitter[:, 1], z])


def render(camera: CameraModel, positions, *, seed: int, noise: bool = False,
           rng: np.random.Generator | None = None) -> np.ndarray:
    """Render equally bright point particles.

    Irradiance, or with ``noise`` 16-bit counts with the photon noise of a 20,000-electron
    full well (``rng`` draws it).
    """
    img = particle_image(camera, positions, rays_per_particle=RAYS_PER_PARTICLE, seed=seed)
    if noise:
        return finish_image(img, noise="poisson", bit_depth=16, rng=rng)
    return img


# --------------------------------------------------------------------------------------------
# Scores
# --------------------------------------------------------------------------------------------


def match_particles(true, found, tolerance) -> np.ndarray:
    """One-to-one matches of found to true particles within an ellipsoid.

    Parameters
    ----------
    true, found : (N, 3), (M, 3) array_like
        Positions ``(x, y, z)``, metres.
    tolerance : (3,) array_like
        Semi-axes of the ellipsoid ``(x, y, z)``, metres: a pair matches when
        ``sum(((f - t) / tolerance) ** 2) <= 1``.

    Returns
    -------
    (K, 2) int ndarray
        Index pairs ``(true, found)``, closest pairs (in units of the tolerance) taken first.
    """
    t = np.asarray(true, float).reshape(-1, 3)
    f = np.asarray(found, float).reshape(-1, 3)
    tol = np.asarray(tolerance, float)
    if len(t) == 0 or len(f) == 0:
        return np.zeros((0, 2), int)
    pairs = cKDTree(t / tol).sparse_distance_matrix(cKDTree(f / tol), 1.0,
                                                    output_type="ndarray")
    order = np.argsort(pairs["v"], kind="stable")
    used_t = np.zeros(len(t), bool)
    used_f = np.zeros(len(f), bool)
    out = []
    for i, j in zip(pairs["i"][order], pairs["j"][order], strict=True):
        if not used_t[i] and not used_f[j]:
            used_t[i] = used_f[j] = True
            out.append((i, j))
    return np.array(out, int).reshape(-1, 2)


@dataclass(frozen=True)
class Region:
    """The evaluated part of the volume: the grid less a lateral margin (metres)."""

    grid: VolumeGrid
    margin: float

    @property
    def slices(self) -> tuple[slice, slice, slice]:
        """Voxel slices ``[z, y, x]`` of the region."""
        m = [int(math.ceil(self.margin / self.grid.voxel[i] - 1e-9)) for i in (1, 0)]
        nz, ny, nx = self.grid.shape
        return slice(0, nz), slice(m[0], ny - m[0]), slice(m[1], nx - m[1])

    def contains(self, points) -> np.ndarray:
        """Whether each point (N, 3) lies in the region (laterally)."""
        p = np.asarray(points, float).reshape(-1, 3)
        s = self.slices
        ok = np.ones(len(p), bool)
        for axis, sl in ((0, s[2]), (1, s[1])):
            lo = self.grid.origin[axis] + (sl.start - 0.5) * self.grid.voxel[axis]
            hi = self.grid.origin[axis] + (sl.stop - 0.5) * self.grid.voxel[axis]
            ok &= (p[:, axis] >= lo) & (p[:, axis] < hi)
        return ok


def field_q(volumes, grid: VolumeGrid, positions, sigma_vox,
            region: Region | None = None, intensities=None) -> float:
    """Return Q of a volume against Gaussian blobs at the true positions.

    The blobs have σ ``sigma_vox`` (z, y, x voxels) at ``positions`` (N, 3, metres), each
    scaled by its particle's brightness in ``intensities`` (N,) (default: all equal); Q is
    taken over ``region`` (default: the whole grid).

    ``volumes`` and ``positions`` (and ``intensities``) may also be lists (several images of
    one study): Q is then taken over all of them together, Σ over every voxel of every
    volume.
    """
    if isinstance(volumes, np.ndarray):
        volumes, positions, intensities = [volumes], [positions], [intensities]
    elif intensities is None:
        intensities = [None] * len(volumes)
    s = region.slices if region is not None else (slice(None),) * 3
    num = ee = tt = 0.0
    for vol, pos, bright in zip(volumes, positions, intensities, strict=True):
        e = np.asarray(vol, np.float64)[s]
        t = gaussian_truth_volume(grid, pos, bright, sigma_vox=sigma_vox)[s].astype(np.float64)
        num += float(np.sum(e * t))
        ee += float(np.sum(e * e))
        tt += float(np.sum(t * t))
    if ee == 0 or tt == 0:
        raise ReconstructionError("Q is undefined: a volume or its truth is all zero")
    return num / math.sqrt(ee * tt)


def matched_sigma(volumes, grid: VolumeGrid, positions, *,
                  sigma_z_vox=(0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0),
                  sigma_xy_vox=(0.3, 0.4, 0.5, 0.7, 1.0),
                  region: Region | None = None) -> dict:
    """Find the Gaussian blob (σ_z, σ_xy in voxels) that maximises Q against ``volumes``.

    Used on reconstructions of isolated particles: the blob that a reconstruction without
    crosstalk makes of a point particle is the truth a crowded field is compared with.
    ``volumes``/``positions`` as in :func:`field_q`. Returns ``{"sigma_vox": (z, y, x),
    "q": Q, "scan": [[σ_z, σ_xy, Q], ...]}``.
    """
    scan = []
    for sz in sigma_z_vox:
        for sxy in sigma_xy_vox:
            scan.append([sz, sxy, field_q(volumes, grid, positions, (sz, sxy, sxy), region)])
    best = max(scan, key=lambda r: r[2])
    return {"sigma_vox": (best[0], best[1], best[1]), "q": best[2], "scan": scan}


def score(result: VolumeResult, positions, *, tolerance, sigmas: dict, region: Region,
          focal_slab: float = 1e-3) -> dict:
    """Score one reconstruction against the true particles.

    Parameters
    ----------
    result : VolumeResult
        Volume and particles from :func:`~plenopiv.workflow.volume.reconstruct_volume`.
    positions : (N, 3) array_like
        True particle positions, metres.
    tolerance : (3,) array_like
        Matching ellipsoid (x, y, z), metres (:func:`match_particles`).
    sigmas : dict
        Truth blobs for Q: name -> σ ``(z, y, x)`` in voxels.
    region : Region
        Where rates and Q are counted.
    focal_slab : float
        Half-thickness (metres) of the slab about the nominal focal plane whose share of
        Σ E² is reported (``focal_share``; ``focal_share_truth`` for the first truth blob).

    Returns
    -------
    dict
        ``q`` (name -> Q), ``n_true``, ``n_found``, ``detection_rate``, ``ghost_rate``,
        ``ghost_near_rate`` (ghosts within two matching tolerances of a true particle: second
        peaks of a real particle rather than free-standing ghosts), ``bias_m`` and ``rms_m``
        (found - true, x y z), ``elongation``, ``masked_rate`` (true particles with no
        light at all within their matching ellipsoid: removed before or during the
        iterations, typically by the soft line-of-sight mask), ``focal_share``,
        ``focal_share_truth``.

    Notes
    -----
    Rates count the true particles and the detections inside ``region``; a detection may
    match a true particle just outside it (and vice versa), so the margin creates neither
    ghosts nor misses. Elongation is the median over the matched pairs of σ_z / sqrt(σ_x σ_y)
    of the detected blobs (metres), the lateral σ floored at voxel/√12, the σ of a uniformly
    filled voxel: a particle held by one column of voxels has a centroid σ ≈ 0 laterally.
    """
    grid = result.grid
    found = np.asarray(result.particle_position_effective, float).reshape(-1, 3)
    pos = np.asarray(positions, float)
    tol = np.asarray(tolerance, float)
    pairs = match_particles(pos, found, tol)
    t_in = region.contains(pos)
    f_in = region.contains(found)
    matched_t = np.zeros(len(pos), bool)
    matched_f = np.zeros(len(found), bool)
    matched_t[pairs[:, 0]] = True
    matched_f[pairs[:, 1]] = True
    ghosts = f_in & ~matched_f
    near = np.zeros(len(found), bool)
    if ghosts.any():
        d, _ = cKDTree(pos / tol).query(found[ghosts] / tol)
        near[np.flatnonzero(ghosts)] = d <= 2.0
    n_true, n_found = int(t_in.sum()), int(f_in.sum())
    out = {"q": {name: field_q(result.volume, grid, pos, sg, region)
                 for name, sg in sigmas.items()},
           "n_true": n_true, "n_found": n_found,
           "detection_rate": float(matched_t[t_in].sum() / max(n_true, 1)),
           "ghost_rate": float(ghosts.sum() / max(n_found, 1)),
           "ghost_near_rate": float(near.sum() / max(n_found, 1))}
    vol = np.asarray(result.volume)
    reach = np.ceil(tol[::-1] / np.asarray(grid.voxel)[::-1]).astype(int)   # z, y, x voxels
    centre = np.rint(world_to_voxel(pos[t_in], grid.origin, grid.voxel)).astype(int)
    lo = np.clip(centre - reach, 0, None)
    hi = np.minimum(centre + reach + 1, grid.shape)
    masked = [not np.any(vol[a[0]:b[0], a[1]:b[1], a[2]:b[2]]) for a, b in zip(lo, hi,
                                                                                 strict=True)]
    out["masked_rate"] = float(np.mean(masked)) if masked else 0.0
    p = pairs[t_in[pairs[:, 0]]]
    if len(p):
        err = found[p[:, 1]] - pos[p[:, 0]]
        size = np.asarray(result.particle_size)[p[:, 1]]
        floor = math.sqrt(grid.voxel[0] * grid.voxel[1]) / math.sqrt(12)
        lateral = np.maximum(np.sqrt(size[:, 0] * size[:, 1]), floor)
        out.update(bias_m=err.mean(axis=0).tolist(),
                   rms_m=np.sqrt((err ** 2).mean(axis=0)).tolist(),
                   elongation=float(np.median(size[:, 2] / lateral)))
    else:
        out.update(bias_m=[math.nan] * 3, rms_m=[math.nan] * 3, elongation=math.nan)
    sl = region.slices
    slab = np.abs(grid.z) < focal_slab
    e2 = np.sum(np.asarray(result.volume, np.float64)[sl] ** 2, axis=(1, 2))
    first = next(iter(sigmas.values()))
    t2 = np.sum(gaussian_truth_volume(grid, pos, sigma_vox=first)[sl].astype(np.float64) ** 2,
                axis=(1, 2))
    out["focal_share"] = float(e2[slab].sum() / max(e2.sum(), 1e-300))
    out["focal_share_truth"] = float(t2[slab].sum() / max(t2.sum(), 1e-300))
    return out


def cell_sigma(grid: VolumeGrid, camera: CameraModel) -> tuple[float, float, float]:
    """Truth blob whose full width at half maximum is the resolution cell, σ (z, y, x) voxels.

    σ = cell / (2 sqrt(2 ln 2)) per axis (:func:`resolution_cell`): the sharpest particle the
    camera can resolve, independent of the reconstruction algorithm.
    """
    lat, dep = resolution_cell(camera)
    k = 2 * math.sqrt(2 * math.log(2))
    return (dep / k / grid.voxel[2], lat / k / grid.voxel[1], lat / k / grid.voxel[0])


def particle_settings(grid: VolumeGrid, camera: CameraModel, *,
                      threshold: float = 0.05) -> ParticleSettings:
    """Particle extraction matched to the grid and to the camera's resolution cell.

    Peaks closer than the resolution cell are one particle (semi-axes: the depth cell in
    depth voxels, and 1.5 lateral cells so that the diagonal neighbour column merges too); the
    centroid box is ±1 lateral cell and ±1 mm in depth (about 2 σ_z of a reconstructed
    particle). ``threshold``, the peak's fraction of the volume's maximum, is lower than the
    library's 0.1 because a reconstruction piles the light of a particle near the focal plane
    into a few voxels several times brighter than a particle elsewhere. One peak is one
    particle (``split_brighter = 0``): the study compares reconstructions, whose peaks the
    split would read differently (docs/validation/merged_particles.md studies the split).
    """
    lat, dep = resolution_cell(camera)
    sub = max(1, int(round(lat / grid.voxel[0])))
    dz = grid.voxel[2]
    return ParticleSettings(threshold=threshold, threshold_reference="maximum",
                            method="centroid",
                            min_separation_vox=(max(dep / dz, 1.0), 1.5 * sub, 1.5 * sub),
                            box_vox=(max(1, int(round(1e-3 / dz))), sub, sub),
                            fit_spacing_vox=(2, 1, 1), internal_correction="none",
                            split_brighter=0.0)


def reconstruct_and_score(calibration: Calibration, image, weights: Weights, positions, *,
                          settings: ReconstructionSettings, particles: ParticleSettings,
                          tolerance, sigmas: dict, region: Region):
    """Run :func:`~plenopiv.workflow.volume.reconstruct_volume` and :func:`score`.

    Returns ``(row, volume)``. A reconstruction that fails gives a row holding ``"error"`` and
    a None volume instead of raising, so that one case cannot stop a study.
    """
    t0 = time.perf_counter()
    try:
        res = reconstruct_volume(calibration, image, weights.grid, settings=settings,
                                 particles=particles, weights=weights)
    except ReconstructionError as exc:
        return {"error": str(exc), "time_s": time.perf_counter() - t0}, None
    t1 = time.perf_counter()
    row = score(res, positions, tolerance=tolerance, sigmas=sigmas, region=region)
    row["time_s"] = t1 - t0
    return row, res.volume


# --------------------------------------------------------------------------------------------
# The study
# --------------------------------------------------------------------------------------------


def settings_label(s: ReconstructionSettings) -> str:
    """Describe reconstruction settings in a few words.

    Method and sweeps, the relaxation when it is not 1, and the thresholds that differ from
    the library's defaults.
    """
    if s.iterations == 0:
        parts = ["MLOS (0 it)"]
    else:
        parts = [s.method, f"{s.iterations} it"]
        if s.relaxation != 1.0:
            parts.append(f"relaxation {s.relaxation:g}")
    default = study_settings()
    for key in ("pixel_threshold", "dark_tolerance"):
        if getattr(s, key) != getattr(default, key):
            parts.append(f"{key} {getattr(s, key):g}")
    return ", ".join(parts)


def _row(case: str, density: float, settings: ReconstructionSettings, row: dict,
         **extra) -> dict:
    return {"case": case, "density_ppl": density, "settings": as_dict(settings),
            "label": settings_label(settings), **extra, **row}


#: Reconstructions of the isolated particles; "smart, 20 it" defines the matched truth blob.
ISOLATED_CASES = {"MLOS (0 it)": dict(iterations=0),
                  "mart, 5 it (relaxation 1)": dict(method="mart", iterations=5),
                  "smart, 5 it (defaults)": dict(),
                  "smart, 20 it": dict(method="smart", iterations=20)}

#: Remedies tried at the highest density: (group, settings).
REMEDIES = (
    ("relaxation (mart)", dict(method="mart", iterations=5, relaxation=0.3)),
    ("relaxation (mart)", dict(method="mart", iterations=5, relaxation=0.1)),
    ("relaxation (mart)", dict(method="mart", iterations=5, relaxation=0.03)),
    ("relaxation (mart)", dict(method="mart", iterations=10, relaxation=0.03)),
    ("fewer iterations (mart)", dict(method="mart", iterations=1)),
    ("relaxation (block)", dict(method="block", iterations=5, relaxation=0.03)),
    ("more iterations (smart)", dict(method="smart", iterations=20)),
    ("more iterations (smart)", dict(method="smart", iterations=50)),
    ("relaxation (smart)", dict(method="smart", iterations=10, relaxation=2.0)),
    ("pixel_threshold", dict(method="smart", iterations=20, pixel_threshold=0.0)),
    ("pixel_threshold", dict(method="smart", iterations=20, pixel_threshold=0.02)),
    ("dark_tolerance", dict(method="smart", iterations=20, dark_tolerance=0.3)),
    ("dark_tolerance", dict(method="smart", iterations=20, dark_tolerance=1.0)),
)

#: The settings recommended by the study, run at every density.
RECOMMENDED = dict(method="smart", iterations=20)


@dataclass(frozen=True)
class StudySetup:
    """The camera, grid and scoring rules every reconstruction of the study shares."""

    camera: CameraModel
    calibration: Calibration
    grid: VolumeGrid
    weights: Weights
    particles: ParticleSettings
    #: Matching semi-axes (x, y, z), metres: the resolution cell.
    tolerance: tuple
    region: Region

    def score(self, image, positions, settings: ReconstructionSettings, sigmas: dict):
        """:func:`reconstruct_and_score` of one image with this setup: ``(row, volume)``."""
        return reconstruct_and_score(self.calibration, image, self.weights, positions,
                                     settings=settings, particles=self.particles,
                                     tolerance=self.tolerance, sigmas=sigmas,
                                     region=self.region)


def study_setup(rows: int, cols: int, *, preset: str = "auburn_50mm",
                subdivision: int | str = 1) -> StudySetup:
    """Camera patch of ``rows`` × ``cols`` lenslets of ``preset``, exact calibration, grid
    and weights.

    ``subdivision``: an int n, lateral voxels of a footprint / n (:func:`study_grid`) with
    weights on them; "auto", voxels a footprint wide with the weights of the working grid the
    library's defaults choose for them (``lateral_subdivision = "auto"``): a reconstruction
    returns to the footprint grid as ``plenopiv reconstruct`` does.
    """
    cam = study_camera(rows, cols, preset=preset)
    cal = Calibration.from_camera(cam)
    grid = study_grid(cam, subdivision=1 if subdivision == "auto" else subdivision)
    if subdivision == "auto":
        weights, _ = weights_for(cal, grid, ReconstructionSettings())
    else:
        weights = study_weights(cal, grid)
    lat, dep = resolution_cell(cam)
    return StudySetup(cam, cal, grid, weights, particle_settings(grid, cam),
                      (lat, lat, dep), Region(grid, interior_margin(cam)))


def isolated_study(setup: StudySetup, rng: np.random.Generator, *, seed: int):
    """Reconstruct two fields of isolated particles with each of :data:`ISOLATED_CASES`.

    Returns ``(isolated, volumes, positions)``: per case the matched blob
    (:func:`matched_sigma`) and particle count (or ``"error"``), the reconstructed volumes
    per case, and the true positions of the two fields.
    """
    cam, grid = setup.camera, setup.grid
    iso_pos = [isolated_field(grid, cam, rng) for _ in range(2)]
    iso_img = [render(cam, p, seed=seed + k) for k, p in enumerate(iso_pos)]
    isolated, iso_vol = {}, {}
    for name, kw in ISOLATED_CASES.items():
        s = study_settings(**kw)
        try:
            vols = [reconstruct_volume(setup.calibration, img, grid, settings=s,
                                       particles=setup.particles,
                                       weights=setup.weights).volume for img in iso_img]
        except ReconstructionError as exc:
            isolated[name] = {"error": str(exc)}
            continue
        isolated[name] = {**matched_sigma(vols, grid, iso_pos, region=setup.region),
                          "n_particles": int(sum(len(p) for p in iso_pos))}
        iso_vol[name] = vols
    return isolated, iso_vol, iso_pos


def truth_sigmas(setup: StudySetup, isolated: dict) -> dict:
    """Truth blob σ (z, y, x voxels) per name: the cell blob and the matched isolated blobs."""
    sigmas = {"cell": cell_sigma(setup.grid, setup.camera)}
    for key, name in (("matched", "smart, 20 it"), ("MLOS", "MLOS (0 it)")):
        if "sigma_vox" in isolated.get(name, {}):
            sigmas[key] = tuple(isolated[name]["sigma_vox"])
    return sigmas


def _kept_at_max_density(s: ReconstructionSettings) -> bool:
    """Whether the volume of a main-table case at the highest density goes into the figures."""
    return (s.iterations == 0 or (s.method == "mart" and s.iterations == 5)
            or s == study_settings())


def density_study(setup: StudySetup, fields: dict, sigmas: dict):
    """Every density × (MLOS, :data:`METHODS` × :data:`ITERATIONS`), library defaults otherwise.

    Returns ``(rows, kept)``: the scored rows and, at the highest density, the volumes of
    MLOS, MART 5 it and the study's default, by label.
    """
    dmax = max(fields)
    main, kept = [], {}
    for d, (pos, img) in fields.items():
        cases = [study_settings(iterations=0)]
        cases += [study_settings(method=m, iterations=n) for m in METHODS
                  for n in ITERATIONS]
        for s in cases:
            row, vol = setup.score(img, pos, s, sigmas)
            main.append(_row("main", d, s, row))
            if d == dmax and _kept_at_max_density(s):
                kept[settings_label(s)] = vol
    return main, kept


def remedy_study(setup: StudySetup, fields: dict, sigmas: dict, rng: np.random.Generator, *,
                 seed: int, kept: dict) -> list[dict]:
    """:data:`REMEDIES` and photon noise at the highest density, the recommendation at all.

    Adds the recommended reconstruction's volume at the highest density to ``kept``.
    """
    dmax = max(fields)
    rem = []
    pos, img = fields[dmax]
    for group, kw in REMEDIES:
        s = study_settings(**kw)
        row, vol = setup.score(img, pos, s, sigmas)
        rem.append(_row(group, dmax, s, row))
        if kw == RECOMMENDED:
            kept[settings_label(s)] = vol
    noisy = render(setup.camera, pos, seed=seed + 200, noise=True, rng=rng)
    for s in (study_settings(), study_settings(**RECOMMENDED)):
        row, _ = setup.score(noisy, pos, s, sigmas)
        rem.append(_row("photon noise (20,000 e- full well, 16 bit)", dmax, s, row))
    for d, (p2, i2) in fields.items():
        if d == dmax:
            continue
        s = study_settings(**RECOMMENDED)
        row, _ = setup.score(i2, p2, s, sigmas)
        rem.append(_row("recommended", d, s, row))
    return rem


def sigma_scans(setup: StudySetup, isolated: dict, iso_vol: dict, kept: dict, positions,
                density: float) -> dict:
    """Q against the truth blob's size: isolated MLOS and SMART-20, and the kept volumes."""
    scans = {}
    for name in iso_vol:
        if name in ("MLOS (0 it)", "smart, 20 it"):
            scans[f"isolated, {name}"] = isolated[name]["scan"]
    for name, vol in kept.items():
        if vol is not None:
            scans[f"{density:g} ppl, {name}"] = matched_sigma(vol, setup.grid, positions,
                                                              region=setup.region)["scan"]
    return scans


def headline(results: dict) -> dict:
    """Q of the study's default and of the best reconstruction at the highest density."""
    dmax = max(r["density_ppl"] for r in results["main"])
    at_max = [r for r in results["main"] + results["remedies"] if "q" in r
              and r["density_ppl"] == dmax and "noise" not in r["case"]]
    best = max(at_max, key=lambda r: r["q"]["matched"]) if at_max else None
    default = next((r for r in at_max if r["case"] == "main"
                    and r["settings"] == study_settings().model_dump()), None)
    return {"q_default_at_max_density": None if default is None else default["q"]["matched"],
            "q_best_at_max_density": None if best is None else best["q"]["matched"],
            "best": None if best is None else best["label"]}


def slice_panels(volumes: dict, grid: VolumeGrid, positions, sigmas: dict) -> list[tuple]:
    """The x-z slab figure's panels: ``(name, volume)``, the truth blobs first.

    The truth is :func:`~plenopiv.synthetic.truth.gaussian_truth_volume` of ``positions`` with the
    matched blob (the cell blob where no matched one was found); the reconstructions follow in
    the order of ``volumes``, failed ones (None) left out.
    """
    truth = gaussian_truth_volume(grid, positions, sigma_vox=sigmas.get("matched",
                                                                        sigmas["cell"]))
    return [("truth (matched blobs)", truth)] + [(k, v) for k, v in volumes.items()
                                                 if v is not None]


def voxel_size_study(rng: np.random.Generator, *, seed: int, density: float = 0.3,
                     rows: int = 31, cols: int = 45) -> list[dict]:
    """Compare voxel sizes on a ``rows`` × ``cols``-lenslet patch (same optics).

    Grids: a footprint × 0.25 mm (the main study's), half a footprint laterally, and 0.125 mm
    in depth; reconstructions: MLOS, the defaults and the recommendation. Q uses blobs of the
    same physical size on every grid (the main study's cell blob, σ = resolution cell / 2.355)
    and, as ``best``, the blob that fits each reconstruction best (σ scanned).
    """
    cam = study_camera(rows, cols)
    cal = Calibration.from_camera(cam)
    lat, dep = resolution_cell(cam)
    base = study_grid(cam)
    pos = seed_field(base, cam, density, rng)
    img = render(cam, pos, seed=seed)
    out = []
    for sub, dz in ((1, DEPTH_VOXEL), (2, DEPTH_VOXEL), (1, DEPTH_VOXEL / 2)):
        grid = study_grid(cam, subdivision=sub, depth_voxel=dz)
        region = Region(grid, interior_margin(cam))
        weights = study_weights(cal, grid)
        sig = {"cell": cell_sigma(grid, cam)}
        for s in (study_settings(iterations=0), study_settings(),
                  study_settings(**RECOMMENDED)):
            row, vol = reconstruct_and_score(cal, img, weights, pos, settings=s,
                                             particles=particle_settings(grid, cam),
                                             tolerance=(lat, lat, dep), sigmas=sig,
                                             region=region)
            if vol is not None:
                best = matched_sigma(vol, grid, pos, region=region,
                                     sigma_z_vox=tuple(x * DEPTH_VOXEL / dz
                                                       for x in (0.75, 1, 1.5, 2, 3)),
                                     sigma_xy_vox=tuple(x * sub for x in (0.3, 0.4, 0.5, 0.7)))
                row["q"]["best"] = best["q"]
                row["best_sigma_mm"] = [best["sigma_vox"][0] * dz * 1e3,
                                        best["sigma_vox"][1] * grid.voxel[0] * 1e3]
            out.append(_row("voxel size", density, s, row, camera=f"{rows} x {cols}",
                            voxel_mm=[v * 1e3 for v in grid.voxel], nnz=weights.nnz))
        del weights
    return out

