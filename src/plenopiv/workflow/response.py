"""The chain's response, measured on synthetic pairs through the experiment's own chain.

The test pairs are rendered through the experiment's camera and reconstructed and correlated
on its grid with its settings (the per-vector uncertainty's calibration,
:func:`measure_response`). It is measured once per experiment (:func:`experiment_response`),
under a key of what the experiment fixes (:func:`experiment_response_key`), never of one
pair's images, so every pair of the experiment shares it.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from plenopiv.errors import PlenopivError
from plenopiv.piv.response import (
    Response,
    _cell,
    _fill_empty_layers,
    _modulation,
    cell_blob_vox,
    lateral_edge,
    rejected_disagreements,
    response_shifts,
    spurious_disagreement,
)
from plenopiv.settings import as_dict


def measure_response(calibration, grid, correction, *, reconstruct, correlate, n_particles: int,
                     f_number=None, rays_per_particle: int = 1024, seed: int = 0,
                     displacements: int = 3) -> Response:
    """Measure the chain's response to known uniform displacements (module notes).

    Parameters
    ----------
    calibration : Calibration
        The calibration of the experiment: its camera, with the calibrated S_i, renders the
        test images, blurred by the point spread measured on its focal-point image
        (:attr:`~plenopiv.calibration.model.Calibration.point_spread_sigma_px`; none when not
        measured).
    grid : VolumeGrid
        The reconstruction grid (effective coordinates).
    correction : DepthCorrection
        From effective to physical depth (the particles are seeded in physical depth).
    reconstruct : callable
        ``reconstruct(image) -> volume``, the reconstruction of the real images.
    correlate : callable
        ``correlate(volume_a, volume_b) -> VectorField``, the correlation of the real volumes.
    n_particles : int
        Particles per test pair (the experiment's seeding: :func:`response_particle_count`).
    f_number : float, optional
        Aperture of the recording (default: the camera's).
    rays_per_particle : int
        Rays per particle of the ray tracer.
    seed : int
        Seed of the particle positions and the tracer.
    displacements : {3, 1}
        Test displacements (:func:`response_shifts`): two reconstructions each; with 3,
        three more pairs measure the chain's gain for sinusoidal displacements of
        ``MODULATION_PERIOD`` vector spacings (``Response.modulation``).

    Returns
    -------
    Response or None
        None when no test pair gave a vector field (too few particles).
    """
    from plenopiv.synthetic.images import blurred, particle_image

    rng = np.random.default_rng(seed)
    psf = calibration.point_spread_sigma_px or 0.0
    camera = calibration.camera
    shifts = response_shifts(calibration.effective_camera, f_number, displacements)
    b = grid.bounds
    lo = np.array([b[0, 0], b[1, 0], correction.depth(b[2, 0])])
    hi = np.array([b[0, 1], b[1, 1], correction.depth(b[2, 1])])
    to_physical = np.array([1.0, 1.0, correction.scale])
    cell = _cell(calibration.effective_camera, f_number)
    blob_vox = cell_blob_vox(calibration.effective_camera, grid, f_number)
    seeds = itertools.count(seed)    # the tracer's seed, one per rendered image

    def render(positions):
        return blurred(particle_image(camera, positions, rays_per_particle=rays_per_particle,
                                      f_number=f_number, seed=next(seeds)), psf)

    def seeding():
        return rng.uniform(lo, hi, size=(max(int(n_particles), 1), 3))

    rows = []       # per test pair: gain, spread, statistics, placement, edge's (or None)
    rejected = []   # per test pair: its rejected vectors' disagreements (n_rejected, 3)
    z = field = None
    for s in shifts:
        pos = seeding()
        ia, ib = render(pos), render(pos + s * to_physical)
        try:
            volume_a = reconstruct(ia)
            field = correlate(volume_a, reconstruct(ib))
            place = placement_offset(volume_a, pos / to_physical, grid, correlate, blob_vox)
        except PlenopivError:   # too few particles for a field: this test pair says nothing
            rows.append(None)
            continue
        z = np.asarray(field.z)
        gain, spread, stats, edge_spread, edge_stats = _layer_statistics(field, s)
        rows.append((gain, spread, stats, place, edge_spread, edge_stats))
        rejected.append(rejected_disagreements(field))
    if z is None:           # no test pair gave a field
        return None

    def modulated_pair(displacement):
        pos = seeding()
        mid = pos / to_physical
        for _ in range(2):      # the displacement at the pair's midpoint, as PIV measures it
            d = displacement(mid)
            mid = pos / to_physical + 0.5 * d
        try:
            return correlate(reconstruct(render(pos)), reconstruct(render(pos + d * to_physical)))
        except PlenopivError:
            return None

    modulation = (_modulation(field, grid.voxel, modulated_pair) if displacements == 3
                  else None)
    keep = [i for i, row in enumerate(rows) if row is not None]
    tables = [np.stack(values) for values in zip(*(rows[i] for i in keep), strict=True)]
    _fill_empty_layers(tables[0], z, 1.0, shifts[keep] != 0.0)   # no gain along no motion
    for values in tables[1:]:
        _fill_empty_layers(values, z, 0.0)
    return Response(z, shifts[keep], *tables[:3], int(n_particles), cell, *tables[3:],
                    modulation, spurious_disagreement(rejected))


def _layer_statistics(field, shift):
    """Gain, spread and rms uncertainty of a test pair's vectors, interior and edge apart.

    Five arrays ``(3, nz)``: gain, spread and rms uncertainty of the interior vectors, spread
    and rms uncertainty of the lateral-edge vectors. Per component and layer of valid
    vectors: the mean over the true ``shift`` (metres; NaN along an axis it does not move),
    the rms deviation from the layer's mean of its interior vectors and of its edge vectors
    (:func:`lateral_edge`; metres), and the rms of the correlation statistics with the
    iteration tail over the same vectors (metres). A class without vectors in a layer takes
    the whole layer's; NaN in a layer with fewer than two vectors.
    """
    from plenopiv.piv.uncertainty import iteration_uncertainty

    comps = np.stack([field.u, field.v, field.w])
    sigma = iteration_uncertainty(field)
    if sigma is None:
        sigma = np.stack([field.u_uncertainty, field.v_uncertainty, field.w_uncertainty])
    ok = np.asarray(field.valid) & np.all(np.isfinite(comps), axis=0)
    edge = lateral_edge(ok.shape)
    nz = comps.shape[1]
    gain, spread, stats, edge_spread, edge_stats = (np.full((3, nz), np.nan) for _ in range(5))
    for layer in range(nz):
        sel = ok[layer]
        if sel.sum() < 2:
            continue
        for k in range(3):
            m = comps[k, layer]
            mean = m[sel].mean()
            if shift[k] != 0.0:     # a gain along the axes the test pair moves along
                gain[k, layer] = mean / shift[k]
            for out_r, out_s, cls in ((spread, stats, sel & ~edge[layer]),
                                      (edge_spread, edge_stats, sel & edge[layer])):
                if not cls.any():
                    cls = sel
                out_r[k, layer] = np.sqrt(np.mean((m[cls] - mean) ** 2))
                sk = sigma[k, layer][cls]
                sk = sk[np.isfinite(sk)]
                out_s[k, layer] = np.sqrt(np.mean(sk**2)) if sk.size else 0.0
    return gain, spread, stats, edge_spread, edge_stats


def placement_offset(volume, positions, grid, correlate, blob_vox) -> np.ndarray:
    """Where a reconstruction puts its particles relative to where they are, ``(3, nz)``.

    Parameters
    ----------
    volume : ndarray, shape (nz, ny, nx)
        A reconstruction of particles at ``positions``.
    positions : ndarray, shape (n, 3)
        Their true positions ``(x, y, z)``, metres, in the grid's effective coordinates.
    grid : VolumeGrid
        The grid of ``volume``.
    correlate : callable
        ``correlate(volume_a, volume_b) -> VectorField``, as the real pair is correlated.
    blob_vox : sequence of 3 floats
        Standard deviation ``(z, y, x)``, voxels, of the Gaussian drawn at each true
        position (the resolution cell's).

    Returns
    -------
    ndarray, shape (3, nz)
        Per axis ``(x, y, z)`` and layer of vectors, the mean displacement from the true
        particles' volume to the reconstruction, metres (reconstructed minus true); NaN in
        a layer without a valid vector.

    Notes
    -----
    A vector is reported at its window's centre; if the reconstruction places the particles
    a distance δ from where they are, the window holds particles from around ``centre - δ``
    and the vector measures the flow there. Correlating the true particles' volume with the
    reconstruction measures δ as the windows see it (the correlation peak of each window
    follows the bulk of its particles' reconstructed intensity, elongation and ghosts
    included). Behind a thick substrate and beyond the focal plane δz grows with Z, the
    particles' own centroids agree with it, and it depends little on the width of the
    Gaussians (docs/validation/uncertainty.md).
    """
    from plenopiv.synthetic.truth import gaussian_truth_volume

    truth = gaussian_truth_volume(grid, positions, sigma_vox=blob_vox)
    field = correlate(truth, volume)
    comps = np.stack([field.u, field.v, field.w])
    ok = np.asarray(field.valid) & np.all(np.isfinite(comps), axis=0)
    out = np.full((3, ok.shape[0]), np.nan)
    for layer in range(ok.shape[0]):
        if ok[layer].any():
            out[:, layer] = comps[:, layer][:, ok[layer]].mean(axis=1)
    return out



# ---- once per experiment --------------------------------------------------------------------


def response_particle_count(calibration, grid, per_lenslet: float) -> int:
    """Particles of one response test pair for a seeding of ``per_lenslet``.

    ``per_lenslet`` (particles per lenslet) × the lenslet count × the box's lateral area
    (``grid`` bounds, m²) over the field of view at the focal plane of the calibrated camera
    (:func:`plenopiv.synthetic.images.field_of_view`, m²): the density of the experiment
    spread through the whole box, as :func:`measure_response` seeds it. At least 1.
    """
    from plenopiv.synthetic.images import field_of_view

    cam = calibration.effective_camera
    fx, fy = field_of_view(cam, 0.0)
    b = grid.bounds
    area = float((b[0, 1] - b[0, 0]) * (b[1, 1] - b[1, 0]))
    return max(1, int(round(per_lenslet * cam.microlens_array.count * area / (4.0 * fx * fy))))


def array_hash(array) -> str:
    """A short hash of an array's bytes and shape (for cache keys)."""
    import hashlib

    a = np.ascontiguousarray(array)
    return hashlib.sha256(a.tobytes() + str(a.shape).encode()).hexdigest()[:16]


def experiment_response_key(experiment, calibration, weights_key: str, image_mask=None,
                            volume_mask=None) -> str:
    """The response cache key: only what the experiment fixes, nothing of a pair.

    The weights' key (camera, calibration, working grid, f-number, lit fraction), the
    ``[volume]`` grid, the ``[reconstruction]`` and ``[piv]`` tables (with the response's
    seeding, ``response_particles_per_lenslet``, and the particle count it gives), the
    internal depth correction, the point spread the calibration measured, and the masks.
    """
    from plenopiv.products.caches import response_key

    grid = experiment.volume
    piv = experiment.piv
    n = response_particle_count(calibration, grid, piv.response_particles_per_lenslet)
    return response_key(weights_key, grid.key(), as_dict(experiment.reconstruction),
                        as_dict(piv), n, experiment.particles.internal_correction,
                        calibration.point_spread_sigma_px,
                        None if image_mask is None else array_hash(image_mask),
                        None if volume_mask is None else array_hash(volume_mask))


@dataclass(frozen=True)
class ExperimentResponse:
    """The chain's response of one experiment (:func:`experiment_response`).

    response : the measured :class:`~plenopiv.piv.response.Response`, or None when no test
        pair gave a vector field (too few particles).
    key : :func:`experiment_response_key`.
    from_cache : found in the response cache (``[output] weights_cache``).
    seconds : wall-clock time spent getting it here, s (measuring, or reading the cache).
    n_particles : particles per test pair (:func:`response_particle_count`).
    """

    response: object
    key: str
    from_cache: bool
    seconds: float
    n_particles: int

    def summary(self) -> dict:
        """JSON values for a run's summary (``seconds``, ``from_cache``, ...)."""
        return {"seconds": round(self.seconds, 3), "from_cache": self.from_cache,
                "measured": self.response is not None, "n_particles": self.n_particles,
                "key": self.key[:24]}


def experiment_response(experiment, calibration, weights, settings, *, image_mask=None,
                        volume_mask=None, workers=None,
                        announce: Callable[[object], None] | None = None
                        ) -> ExperimentResponse:
    """The chain's response of ``experiment``: from the cache, or measured and cached.

    Parameters
    ----------
    experiment : Experiment
        Its grid, ``[reconstruction]``, ``[particles]`` and ``[piv]`` tables; the cache is
        ``[output] weights_cache`` (``response-KEY.json``; none when it is "").
    calibration : Calibration
    weights : Weights
        The projector every pair of the experiment uses.
    settings : PIVSettings
        The PIV of the pairs (``experiment.piv.settings()``).
    image_mask, volume_mask : bool arrays, optional
        The experiment's masks (:mod:`plenopiv.workflow.masks`).
    workers : int, optional
        Threads of the correlation.
    announce : callable, optional
        ``announce(weights)``, called once just before a measurement starts (not when the
        cache has it).
    """
    from plenopiv.camera.corrections import DepthCorrection
    from plenopiv.piv import correlate_volumes
    from plenopiv.products.caches import cached_response
    from plenopiv.workflow.volume import reconstruct_volume

    t0 = time.perf_counter()
    grid = experiment.volume
    n = response_particle_count(calibration, grid, experiment.piv.response_particles_per_lenslet)
    key = experiment_response_key(experiment, calibration, weights.key, image_mask, volume_mask)
    cache = experiment.output.weights_cache
    path = experiment.path(cache) / f"response-{key[:24]}.json" if cache else None
    correction = DepthCorrection.for_camera(
        calibration.camera, internal=experiment.particles.internal_correction)

    def reconstruct(image):
        return reconstruct_volume(calibration, image, grid, settings=experiment.reconstruction,
                                  particles=experiment.particles, weights=weights,
                                  image_mask=image_mask).volume

    def correlate(a, b):
        return correlate_volumes(a, b, grid, settings=settings, workers=workers,
                                 mask=volume_mask)

    def measure():
        if announce is not None:
            announce(weights)
        return measure_response(calibration, grid, correction, reconstruct=reconstruct,
                                correlate=correlate, n_particles=n,
                                f_number=experiment.reconstruction.f_number,
                                displacements=experiment.piv.response_displacements)

    resp, hit = cached_response(path, key, measure)
    return ExperimentResponse(resp, key, hit, time.perf_counter() - t0, n)


#: Seconds per ray the tracer renders (:func:`plenopiv.synthetic.images.particle_image`), for
#: the response's time estimate; measured in docs/performance.md.
SECONDS_PER_RENDERED_RAY = 2e-7


def response_counts(displacements: int = 3) -> tuple[int, int]:
    """``(reconstructions, correlations)`` of one :func:`measure_response`.

    Per uniform test pair two reconstructions, its correlation and the placement's; with 3
    displacements three more modulated pairs, two reconstructions and one correlation each.
    """
    from plenopiv.piv.response import DEPTH_SHIFTS, SEPARATING_SHIFTS

    uniform = len(DEPTH_SHIFTS) + len(SEPARATING_SHIFTS) if displacements == 3 else 1
    modulated = 3 if displacements == 3 else 0
    return 2 * (uniform + modulated), 2 * uniform + modulated


def response_seconds(volume_s: float, piv_s: float, n_particles: int, displacements: int = 3,
                     rays_per_particle: int = 1024) -> float:
    """Estimated time of :func:`measure_response`, s.

    ``volume_s`` and ``piv_s``: one reconstruction (its particles included) and one PIV of
    the experiment, s (:func:`plenopiv.workflow.planning.plan`); each reconstruction's
    image is rendered first (:data:`SECONDS_PER_RENDERED_RAY`).
    """
    n_rec, n_piv = response_counts(displacements)
    render = SECONDS_PER_RENDERED_RAY * n_particles * rays_per_particle
    return n_rec * (volume_s + render) + n_piv * piv_s
