"""Volume particles under noise: detection against the threshold, sub-voxel estimators.

Two kinds of volume, each against its truth:

- synthetic: isolated Gaussian blobs with the plenoptic depth elongation (:data:`BLOBS`), each
  voxel the blob's integral over it, the peak voxel of a centred blob 1, centres on a
  jittered lattice with sub-voxel offsets uniform in [-0.5, 0.5) per axis, plus white
  Gaussian noise of :data:`NOISE_LEVELS` times that peak (signed, and clipped at zero as a
  reconstruction is);
- reconstructed: ray-traced particles on the demo's camera (``small_m1``, footprint voxels)
  with Gaussian image noise of :data:`NOISE_LEVELS` times the image's particle peak, clipped
  at zero, reconstructed with the library's defaults, and an image of noise alone.

Detection is scored with the relative threshold alone (``noise_sigmas = 0``) and with the
default ``[particles]`` threshold; each sub-voxel estimator (:data:`ESTIMATORS`) by its bias
and rms error per axis on the same matched particles. :func:`run` writes the report.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from scipy.special import erf

from pipelines.studies.field_quality import match_particles
from pipelines.studies.output import fmt, section, table, write_json, write_text
from plenopiv.particles.peaks import find_particles
from plenopiv.particles.settings import ParticleSettings
from plenopiv.particles.threshold import background_noise, peak_threshold

#: Noise standard deviations, fractions of the particles' peak.
NOISE_LEVELS = (0.0, 0.01, 0.03, 0.1)
#: Blob standard deviations ``(z, y, x)`` in voxels: the demo camera's resolution cell
#: (depth 4.4 voxels, lateral one footprint voxel, full widths at half maximum) on footprint
#: voxels, and on voxels half as large along every axis.
BLOBS = {"footprint voxels": (1.9, 0.5, 0.5), "half-size voxels": (3.8, 1.0, 1.0)}
#: The sub-voxel estimators compared: ``find_particles`` keywords.
ESTIMATORS = {
    "centroid": {"method": "centroid"},
    "gaussian 1,1,1": {"method": "gaussian", "fit_spacing_vox": (1, 1, 1)},
    "gaussian 2,1,1": {"method": "gaussian", "fit_spacing_vox": (2, 1, 1)},
    "gaussian 4,1,1": {"method": "gaussian", "fit_spacing_vox": (4, 1, 1)},
}
#: Full width at half maximum over sigma of a Gaussian.
FWHM = 2.0 * math.sqrt(2.0 * math.log(2.0))
#: Peak voxels at least this many noise deviations above the background count as "bright":
#: the default 5 plus 2, so that the noise at the peak voxel drops one below the threshold
#: with probability Phi(-2) = 2.3 %.
BRIGHT_SIGMAS = 7.0


def cell_options(sigma) -> dict:
    """``find_particles`` separation and box for blobs of ``sigma`` (z, y, x) voxels.

    As :func:`plenopiv.workflow.volume.particle_options` sets them from the resolution cell
    (the blob's full width at half maximum): peaks within one cell in depth and 1.5 cells
    laterally are one particle, the centroid box is ±1 cell.
    """
    cell = FWHM * np.asarray(sigma, float)
    return {"min_separation_vox": (cell[0], 1.5 * cell[1], 1.5 * cell[2]),
            "box_vox": tuple(max(1, int(round(c))) for c in cell)}


def _integrated(k, centre, sigma):
    """Integral over voxel ``[k - 1/2, k + 1/2]`` of exp(-(x - c)^2 / (2 s^2)) / (s sqrt(2 pi))."""
    a = (k - centre + 0.5) / (math.sqrt(2.0) * sigma)
    b = (k - centre - 0.5) / (math.sqrt(2.0) * sigma)
    return 0.5 * (erf(a) - erf(b))


def blob_volume(sigma, rng: np.random.Generator, *, shape=(64, 48, 48)):
    """Noise-free isolated blobs: ``(volume, centres (N, 3) z, y, x voxels, peak voxels (N,))``.

    One blob per lattice cell of 2.5 resolution cells, at a uniformly random point within ±0.5
    voxel of the cell's centre; each voxel holds the blob's integral over it, scaled so that a
    blob centred on a voxel has 1 there.
    """
    sigma = np.asarray(sigma, float)
    step = np.ceil(2.5 * FWHM * sigma).astype(int)
    counts = (np.asarray(shape) - 2) // step
    grids = np.meshgrid(*(1 + step[a] * (np.arange(counts[a]) + 0.5) for a in range(3)),
                        indexing="ij")
    centres = np.stack([g.ravel() for g in grids], axis=1) + rng.uniform(-0.5, 0.5,
                                                                         (grids[0].size, 3))
    norm = np.prod([_integrated(0.0, 0.0, s) for s in sigma])
    vol = np.zeros(shape)
    half = np.ceil(5 * sigma).astype(int)
    peaks = np.empty(len(centres))
    for n, c in enumerate(centres):
        lo = np.maximum(np.round(c).astype(int) - half, 0)
        hi = np.minimum(np.round(c).astype(int) + half + 1, shape)
        f = [_integrated(np.arange(lo[a], hi[a]), c[a], sigma[a]) for a in range(3)]
        blob = f[0][:, None, None] * f[1][None, :, None] * f[2][None, None, :] / norm
        vol[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] += blob
        peaks[n] = blob.max()
    return vol, centres, peaks


def score(volume, truth, options: dict, threshold: float, *, noise_sigma: float = 0.0,
          peaks=None) -> dict:
    """Detection and estimator errors of ``find_particles`` on ``volume`` against ``truth``.

    ``truth`` (N, 3) voxels ``(z, y, x)``; found peaks match true particles one to one within
    the separation ellipsoid. Returns counts (true, found, matched, and the bright particles,
    ``peaks`` at least :data:`BRIGHT_SIGMAS` noise deviations, found or not) and per
    estimator the errors ``(z, y, x)`` of the matched positions, voxels; :func:`summary`
    turns one or several into rates, biases and rms.
    """
    tol = np.asarray(options["min_separation_vox"], float)
    errors, matched = {}, None
    for name, kw in ESTIMATORS.items():
        found = find_particles(volume, threshold=threshold, **options, **kw)
        if matched is None:         # the same peaks for every estimator
            matched = match_particles(truth / tol, found.position_vox / tol, np.ones(3))
            n_found = len(found)
        errors[name] = found.position_vox[matched[:, 1]] - truth[matched[:, 0]]
    out = {"n_true": len(truth), "n_found": n_found, "n_matched": len(matched),
           "errors": errors}
    if peaks is not None and noise_sigma > 0:
        bright = peaks >= BRIGHT_SIGMAS * noise_sigma
        out["n_bright"] = int(bright.sum())
        out["n_bright_found"] = int(np.isin(np.flatnonzero(bright), matched[:, 0]).sum())
    return out


def summary(parts: list[dict]) -> dict:
    """Pool :func:`score` results: detected and spurious shares, and per estimator the bias,
    rms and 68th percentile of the absolute error per axis ``(z, y, x)``, voxels."""
    n = {k: sum(p.get(k, 0) for p in parts)
         for k in ("n_true", "n_found", "n_matched", "n_bright", "n_bright_found")}
    out = {"n_true": n["n_true"], "n_found": n["n_found"],
           "detected": n["n_matched"] / max(n["n_true"], 1),
           "spurious": (n["n_found"] - n["n_matched"]) / max(n["n_found"], 1)}
    if "noise_over_relative" in parts[0]:
        out["noise_over_relative"] = max(p["noise_over_relative"] for p in parts)
    if n["n_bright"]:
        out["n_bright"] = n["n_bright"]
        out["bright_detected"] = n["n_bright_found"] / n["n_bright"]
    out["estimators"] = {}
    for name in parts[0]["errors"]:
        e = np.concatenate([p["errors"][name] for p in parts]).reshape(-1, 3)
        out["estimators"][name] = {
            "bias_vox": e.mean(axis=0).tolist() if len(e) else [np.nan] * 3,
            "rms_vox": np.sqrt((e**2).mean(axis=0)).tolist() if len(e) else [np.nan] * 3,
            "p68_vox": np.percentile(np.abs(e), 68.27, axis=0).tolist() if len(e)
            else [np.nan] * 3}
    return out


def synthetic_rows(*, volumes: int = 2, seed: int = 5, progress=print) -> list[dict]:
    """:func:`summary` of every blob shape, noise level and noise sign (signed or clipped)."""
    rows = []
    for shape_name, sigma in BLOBS.items():
        opts = cell_options(sigma)
        for level in NOISE_LEVELS:
            for clipped in (False, True) if level > 0 else (False,):
                rng = np.random.default_rng(seed)
                parts = {"relative": [], "default": []}
                ratio = []
                for _ in range(volumes):
                    clean, truth, peaks = blob_volume(sigma, rng)
                    vol = clean + rng.normal(0.0, level, clean.shape) if level else clean
                    vol = np.clip(vol, 0.0, None) if clipped else vol
                    ratio.append(background_noise(vol).sigma / level if level else np.nan)
                    for rule, got in parts.items():
                        got.append(score(vol, truth, opts, _threshold(vol, rule), peaks=peaks,
                                         noise_sigma=level))
                row = {"blob": shape_name, "sigma_vox": list(sigma), "noise": level,
                       "clipped": clipped, "sigma_ratio": float(np.mean(ratio)),
                       **{rule: summary(got) for rule, got in parts.items()}}
                rows.append(row)
                d = row["default"]
                progress(f"{shape_name} noise {level} {'clipped' if clipped else 'signed'}: "
                         f"spurious {row['relative']['spurious']:.3f} -> {d['spurious']:.3f}, "
                         f"detected {d['detected']:.3f}")
    return rows


def _threshold(volume, rule: str) -> float:
    """The library's threshold: relative alone (``rule = "relative"``) or the default."""
    s = ParticleSettings()
    return peak_threshold(volume, fraction=s.threshold, reference=s.threshold_reference,
                          noise_sigmas=0.0 if rule == "relative" else s.noise_sigmas)


# ---- reconstructed volumes -------------------------------------------------------------------


class _Chain:
    """The demo's camera, its exact calibration, grid and weights, built once."""

    def __init__(self, cache_dir=None):
        from plenopiv.calibration.model import Calibration
        from plenopiv.camera.model import load_camera
        from plenopiv.reconstruction.build import weights_for
        from plenopiv.reconstruction.settings import ReconstructionSettings
        from plenopiv.workflow.vortex_case import VortexCase, aligned_grid, seeding_box

        self.camera = load_camera("small_m1")
        case = VortexCase()
        self.grid = aligned_grid(self.camera, case)
        self.box = seeding_box(case, self.grid)
        self.calibration = Calibration.from_camera(self.camera)
        self.settings = ReconstructionSettings()
        self.weights, _ = weights_for(self.calibration, self.grid, self.settings,
                                      cache_dir=cache_dir)

    def image(self, positions, level: float, rng: np.random.Generator) -> np.ndarray:
        """Ray-traced image of ``positions`` plus Gaussian noise of ``level`` times its peak
        (the 99.9th percentile of the lit pixels), clipped at zero as a camera's counts."""
        from plenopiv.synthetic.images import particle_image

        img = particle_image(self.camera, positions, rays_per_particle=2048, seed=3)
        lit = img[img > 0]
        peak = float(np.percentile(lit, 99.9)) if lit.size else 1.0
        return np.clip(img + rng.normal(0.0, level * peak, img.shape), 0.0, None)

    def reconstruct(self, image):
        from plenopiv.workflow.volume import reconstruct_volume

        return reconstruct_volume(self.calibration, image, self.grid, settings=self.settings,
                                  weights=self.weights)

    def to_voxels(self, points) -> np.ndarray:
        """World ``(x, y, z)`` metres to voxel ``(z, y, x)`` of the grid."""
        from plenopiv.conventions import world_to_voxel

        return world_to_voxel(points, self.grid.origin, self.grid.voxel)


def reconstructed_rows(chain: _Chain, *, densities=(0.05, 0.15), seeds=(7, 8),
                       progress=print) -> list[dict]:
    """:func:`summary` of reconstructed particle fields at each density and image noise level.

    The particles inside the grid less one voxel are the truth (the camera has no interface:
    effective and physical positions agree); each seed draws its own field. Each row also
    holds the error of the light-field positions (``[particles] position = "light_field"``,
    the pipeline's) on the particles the default threshold finds, as
    ``estimators["light field"]``.
    """
    rows = []
    for density in densities:
        for level in NOISE_LEVELS:
            parts = {"relative": [], "default": []}
            for seed in seeds:
                for rule, got in _reconstructed_score(chain, density, level, seed).items():
                    parts[rule].append(got)
            row = {"density_ppl": density, "noise": level,
                   **{rule: summary(got) for rule, got in parts.items()}}
            rows.append(row)
            progress(f"reconstructed {density} ppl, noise {level}: spurious "
                     f"{row['relative']['spurious']:.3f} -> {row['default']['spurious']:.3f}, "
                     f"detected {row['default']['detected']:.3f}")
    return rows


def _reconstructed_score(chain: _Chain, density: float, level: float, seed: int) -> dict:
    """:func:`score` of one reconstructed field per threshold rule, with the light field's."""
    from plenopiv.synthetic.seeding import particle_count, random_particles
    from plenopiv.workflow.volume import particle_options

    rng = np.random.default_rng(seed)
    positions = random_particles(chain.box, particle_count(chain.camera, chain.box,
                                                           per_lenslet=density), rng)
    truth = chain.to_voxels(positions)
    truth = truth[np.all((truth >= 1) & (truth <= np.array(chain.grid.shape) - 2), axis=1)]
    res = chain.reconstruct(chain.image(positions, level, rng))
    vol = res.volume
    opts = particle_options(ParticleSettings(), chain.grid, chain.calibration, vol)
    geo = {k: opts[k] for k in ("min_separation_vox", "box_vox")}
    out = {rule: score(vol, truth, geo, _threshold(vol, rule))
           for rule in ("relative", "default")}
    bg, s = background_noise(vol), ParticleSettings()
    out["default"]["noise_over_relative"] = ((bg.level + s.noise_sigmas * bg.sigma)
                                             / _threshold(vol, "relative"))
    lf = chain.to_voxels(res.particle_position_effective)
    tol = np.asarray(geo["min_separation_vox"])
    m = match_particles(truth / tol, lf / tol, np.ones(3))
    out["default"]["errors"]["light field"] = lf[m[:, 1]] - truth[m[:, 0]]
    return out


def noise_only_rows(chain: _Chain, *, seed: int = 11,
                    sigmas=(0.0, 3.0, 5.0, 8.0, 12.0, 16.0, 24.0)) -> list:
    """Peaks per voxel in volumes reconstructed from images of noise alone.

    For each noise level (a fraction of the 0.05-ppl image's particle peak, so that the
    volumes compare with those of :func:`reconstructed_rows`), the share of voxels that hold
    a peak above the relative threshold and ``noise_sigmas`` in ``sigmas`` (0: relative
    alone): MART's false-alarm rate per voxel.
    """
    from plenopiv.synthetic.images import particle_image
    from plenopiv.synthetic.seeding import particle_count, random_particles
    from plenopiv.workflow.volume import particle_options

    rng = np.random.default_rng(seed)
    positions = random_particles(chain.box, particle_count(chain.camera, chain.box,
                                                           per_lenslet=0.05), rng)
    img = particle_image(chain.camera, positions, rays_per_particle=2048, seed=3)
    peak = float(np.percentile(img[img > 0], 99.9))
    rows = []
    for level in NOISE_LEVELS[1:]:
        img = np.clip(rng.normal(0.0, level * peak, chain.camera.sensor.shape), 0.0, None)
        vol = chain.reconstruct(img).volume
        opts = particle_options(ParticleSettings(), chain.grid, chain.calibration, vol)
        geo = {k: opts[k] for k in ("min_separation_vox", "box_vox")}
        s = ParticleSettings()
        counts = {}
        for k in sigmas:
            thr = peak_threshold(vol, fraction=s.threshold, reference=s.threshold_reference,
                                 noise_sigmas=k)
            counts[f"{k:g}"] = len(find_particles(vol, threshold=thr, **geo)) / vol.size
        rows.append({"noise": level, "peaks_per_voxel": counts, "n_voxels": int(vol.size)})
    return rows


# ---- report ----------------------------------------------------------------------------------


def run(out: str | Path, *, cache_dir=None, progress=print) -> dict:
    """Measure and write ``particle_noise.json`` and ``particle_noise.md`` under ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    chain = _Chain(cache_dir)
    result = {"synthetic": synthetic_rows(progress=progress),
              "reconstructed": reconstructed_rows(chain, progress=progress),
              "noise_only": noise_only_rows(chain),
              "noise_sigmas": ParticleSettings().noise_sigmas,
              "default_method": ParticleSettings().method,
              "default_fit_spacing_vox": list(ParticleSettings().fit_spacing_vox)}
    result["seconds"] = round(time.perf_counter() - t0, 1)
    write_json(out / "particle_noise.json", result)
    write_text(out / "particle_noise.md", markdown(result))
    return {"json": str(out / "particle_noise.json"),
            "markdown": str(out / "particle_noise.md"), "seconds": result["seconds"]}


def _axes(values, spec=".3f") -> str:
    return " / ".join(fmt(v, spec) for v in values)


def markdown(r: dict) -> str:
    """The report's page."""
    k = fmt(r["noise_sigmas"], "g")
    lines = ["# Volume particles under noise", "",
             "Made by `python pipelines/validate_particles.py --out docs/validation` "
             f"({r['seconds']:.0f} s); the numbers are in `particle_noise.json`. The study is "
             "`pipelines/studies/particle_noise.py`; the method is described in "
             "[methods.md](../methods.md#peaks).", "",
             f"Thresholds: *relative* is `threshold = 0.1` of the 99.9th percentile of the "
             f"positive voxels alone (`noise_sigmas = 0`); *default* adds `noise_sigmas = {k}`. "
             "Errors are found minus true positions `z / y / x` in voxels, on the particles "
             "the default threshold finds (the same peaks for every estimator); p68 is the "
             "68th percentile of the absolute error.", ""]
    lines += section("Detection on Gaussian blobs")
    lines += [f"Blobs of σ `z, y, x` = {', '.join(f'{n} {tuple(s)}' for n, s in BLOBS.items())}"
              " voxels, integrated over each voxel, on a lattice 2.5 resolution cells apart, "
              "two volumes of 64 × 48 × 48 voxels per row; white Gaussian noise, signed or "
              "clipped at zero. σ̂/σ: the estimated over the true noise deviation. *Bright*: "
              f"particles whose peak voxel is at least {BRIGHT_SIGMAS:g} σ.", ""]
    lines += table(["blob", "noise", "noise sign", "σ̂/σ", "spurious (relative)",
                    "spurious (default)", "detected (default)", "bright detected"],
                   [[s["blob"], fmt(s["noise"], "g"), "clipped" if s["clipped"] else "signed",
                     fmt(s["sigma_ratio"], ".2f"), fmt(s["relative"]["spurious"], ".3f"),
                     fmt(s["default"]["spurious"], ".3f"), fmt(s["default"]["detected"], ".3f"),
                     fmt(s["default"].get("bright_detected"), ".3f")]
                    for s in r["synthetic"]])
    lines += ["", *section("Detection on reconstructed volumes"),
              "The demo's camera (`small_m1`, footprint voxels, M = -1, f/2.2), ray-traced "
              "particles, Gaussian image noise of a fraction of the image's particle peak "
              "(clipped at zero), the library's reconstruction; two seeds per row. *noise term "
              "/ relative*: the background level plus `noise_sigmas` deviations over the "
              "relative threshold (the larger of the two seeds): below 1 the relative term "
              "decides.", ""]
    lines += table(["particles per lenslet", "image noise", "true", "noise term / relative",
                    "spurious (relative)", "spurious (default)", "detected (default)"],
                   [[fmt(s["density_ppl"], "g"), fmt(s["noise"], "g"),
                     s["default"]["n_true"], fmt(s["default"]["noise_over_relative"], ".2f"),
                     fmt(s["relative"]["spurious"], ".3f"),
                     fmt(s["default"]["spurious"], ".3f"), fmt(s["default"]["detected"], ".3f")]
                    for s in r["reconstructed"]])
    ks = list(r["noise_only"][0]["peaks_per_voxel"])
    lines += ["", "Images of noise alone, reconstructed the same way: peaks per voxel above "
              "the relative threshold and `noise_sigmas` (0: relative alone).", ""]
    lines += table(["image noise", *(f"noise_sigmas {x}" for x in ks)],
                   [[fmt(s["noise"], "g"), *(fmt(s["peaks_per_voxel"][x], ".1e") for x in ks)]
                    for s in r["noise_only"]])
    lines += ["", *section("Sub-voxel estimators on Gaussian blobs (signed noise)")]
    lines += table(["blob", "noise", "estimator", "bias z / y / x", "rms z / y / x",
                    "p68 z / y / x"],
                   [[s["blob"], fmt(s["noise"], "g"), name, _axes(e["bias_vox"]),
                     _axes(e["rms_vox"]), _axes(e["p68_vox"])]
                    for s in r["synthetic"] if not s["clipped"]
                    for name, e in s["default"]["estimators"].items()])
    lines += ["", *section("Sub-voxel estimators on reconstructed volumes"),
              "*light field*: the pipeline's positions (`position = \"light_field\"`, seeded "
              f"by the `{r['default_method']}` estimate), for comparison.", ""]
    lines += table(["particles per lenslet", "image noise", "estimator", "bias z / y / x",
                    "rms z / y / x", "p68 z / y / x"],
                   [[fmt(s["density_ppl"], "g"), fmt(s["noise"], "g"), name,
                     _axes(e["bias_vox"]), _axes(e["rms_vox"]), _axes(e["p68_vox"])]
                    for s in r["reconstructed"]
                    for name, e in s["default"]["estimators"].items()])
    return "\n".join(lines) + "\n"
