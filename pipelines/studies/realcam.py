"""The chain on a real recording: ideal renders against renders with a real camera's effects.

One camera (``small_m1``, the demo's) records an Oseen pair and its calibration images
(focal-point at f/16, alignment) twice from the same particles and seeds: ideal, and through a
real camera (:mod:`plenopiv.synthetic.sensor`) with one effect of
:data:`~plenopiv.synthetic.sensor.REALISTIC` at a time (black level with its fixed pattern,
read noise, hot and dead pixels, lenslet throughput, vignetting, glow, particle brightness,
pulse ratio) and all of them together, with the matching dark and white frames (what
``plenopiv simulate dark|white`` writes). Each case then runs as ``plenopiv calibrate
--dark --white`` and ``plenopiv run`` would: the calibration images with the master dark
subtracted (:func:`~plenopiv.workflow.preprocess.calibration_dark`, its hot and cold pixels
ignored) and divided by the white, then the pair without and with a ``[preprocess]`` table
(dark, white, ``hot_pixels = "auto"``), and is
scored against the truth: S_i error, particles detected and ghosts (matched within the
resolution cell, :func:`pipelines.studies.field_quality.match_particles`), the velocity's gain,
bias and rms per component (:func:`plenopiv.workflow.vortex_case.compare_with_truth`) and
whether the preprocessing stage warned about the image.

:func:`pipelines.studies.realcam_report.run` runs the cases and writes the page.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pipelines.studies.field_quality import match_particles
from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.model import Calibration
from plenopiv.camera.model import CameraModel, load_camera
from plenopiv.camera.resolution import resolution_cell
from plenopiv.errors import PlenopivError, PlenopivWarning
from plenopiv.preprocess.settings import PreprocessSettings
from plenopiv.products.images import write_image_stack
from plenopiv.reconstruction.build import weights_for
from plenopiv.synthetic.flows import advect
from plenopiv.synthetic.images import (
    alignment_image,
    auto_exposure,
    field_of_view,
    finish_image,
    focal_point_image,
    particle_image,
    white_image,
)
from plenopiv.synthetic.seeding import particle_count, random_particles
from plenopiv.synthetic.sensor import REALISTIC, RecordingSettings, camera_instance
from plenopiv.workflow.pair import process_pair
from plenopiv.workflow.preprocess import calibration_dark
from plenopiv.workflow.vortex_case import (
    FOCAL_POINT_F_NUMBER,
    VortexCase,
    aligned_grid,
    case_experiment,
    case_flow,
    compare_with_truth,
    seeding_box,
)

#: Each effect of :data:`REALISTIC` on its own: the fields of RecordingSettings it sets. The
#: sensor's effects come with REALISTIC's 12-bit ADC, whose counts they are (100 counts of
#: black level are 2.4 % of a 12-bit range, 0.15 % of a 16-bit one).
EFFECTS = {
    "black level + fixed pattern": ("black_level_counts", "column_offset_counts",
                                    "pixel_offset_counts", "adc_bits"),
    "read noise": ("read_noise_counts", "adc_bits"),
    "hot and dead pixels": ("hot_pixel_fraction", "hot_pixel_counts", "dead_pixel_fraction",
                            "adc_bits"),
    "throughput spread": ("throughput_spread",),
    "vignetting": ("vignetting",),
    "glow": ("glow",),
    "brightness spread": ("brightness_sigma_ln",),
    "pulse ratio": ("pulse_ratio",),
}
#: The name of the case with every effect of REALISTIC.
ALL = "all (REALISTIC)"
IDEAL = "ideal"

#: Photon noise of every frame: electrons at the ADC's full scale (simulate's default).
FULL_WELL = 20000.0
#: The files' bit depth.
BIT_DEPTH = 16
#: Dark and white frames of each case (simulate dark|white --frames).
DARK_FRAMES = 8
WHITE_FRAMES = 4


def recording(effect: str) -> RecordingSettings:
    """The recording of a case: ideal, one effect of :data:`REALISTIC`, or all of them."""
    if effect == IDEAL:
        return RecordingSettings()
    if effect == ALL:
        return REALISTIC
    fields = EFFECTS[effect]
    return RecordingSettings(**{f: getattr(REALISTIC, f) for f in fields})


@dataclass(frozen=True)
class StudyCase:
    """The shared set-up: camera, Oseen case, seeds.

    ``lenslets``: run on the central patch of the camera (None: all of it); ``windows``: the
    PIV's (z, y, x) voxels per pass; ``calibrate``: False takes the true camera's calibration
    instead of calibrating (a small patch gives the focal-point fit too little leverage: S_i
    7 mm short on 19 × 27 lenslets at f/16).
    """

    camera: str = "small_m1"
    lenslets: tuple[int, int] | None = None
    particles_per_lenslet: float = 0.15
    seed: int = 1
    camera_seed: int = 7
    rays_per_particle: int = 2048
    windows: tuple = ((16, 16, 16), (12, 12, 12))
    calibrate: bool = True

    def vortex(self) -> VortexCase:
        """The Oseen case of the chain (correlation uncertainty: no response test pairs)."""
        return VortexCase(flow="oseen", camera=self.camera, lenslets=self.lenslets,
                          particles_per_lenslet=self.particles_per_lenslet, seed=self.seed,
                          uncertainty="correlation",
                          rays_per_particle=self.rays_per_particle, windows=self.windows)

    def truth_camera(self) -> CameraModel:
        cam = load_camera(self.camera)
        return cam if self.lenslets is None else cam.patch(*self.lenslets)


def _rng(seed: int, *stream: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), *stream])


@dataclass(frozen=True)
class Truth:
    """The particles of the pair, the same for every case."""

    positions_a: np.ndarray
    positions_b: np.ndarray
    brightness_normal: np.ndarray   # standard normal per particle, scaled by each case's σ_ln
    flow: object
    dt: float
    render_seed: int


def truth(setup: StudyCase) -> Truth:
    """Seed the Oseen case's box on the true camera's grid and move the particles."""
    case = setup.vortex()
    cam = setup.truth_camera()
    grid = aligned_grid(Calibration.from_camera(cam).effective_camera, case)
    box = seeding_box(case, grid)
    flow = case_flow(case, grid)
    n = particle_count(cam, box, per_lenslet=case.particles_per_lenslet)
    n = int(n * (box.x[1] - box.x[0]) * (box.y[1] - box.y[0])
            / np.prod(2 * np.array(field_of_view(cam, 0.0))))
    rng = _rng(setup.seed, 0)
    pa = random_particles(box, n, rng)
    pb = advect(flow, pa, case.dt)
    return Truth(pa, pb, rng.standard_normal(n), flow, case.dt, int(rng.integers(2 ** 31)))


@dataclass
class Recording:
    """What one camera recorded: calibration images, pair, dark and white frames."""

    focal_point: np.ndarray
    alignment: np.ndarray
    image_a: np.ndarray
    image_b: np.ndarray
    dark: np.ndarray | None
    white: np.ndarray | None


def _finisher(instance, seed: int):
    """``finish(irradiance, stream, exposure=None)``: the frame recorded, noise per stream."""
    sensor = instance if instance is not None and instance.settings.has_sensor else None

    def finish(irr, stream: int, exposure=None):
        return finish_image(irr, exposure=exposure, noise="poisson", full_well=FULL_WELL,
                            bit_depth=BIT_DEPTH, rng=_rng(seed, 1, stream), sensor=sensor)
    return finish, sensor


def record_case(setup: StudyCase, rec: RecordingSettings, t: Truth) -> Recording:
    """Render and record every frame of one case from the shared particles and seeds.

    Every frame's noise comes from its own stream of the seed, so the ideal and the realistic
    case differ only by the effects. Dark and white frames only where the case has a sensor
    (dark) or anything but the ideal (white).
    """
    cam = setup.truth_camera()
    instance = None if rec.is_ideal else camera_instance(cam, rec, seed=setup.camera_seed)
    finish, sensor = _finisher(instance, setup.seed)
    fp, al, dark, white = record_calibration(setup, rec)
    w = None
    if rec.brightness_sigma_ln > 0:
        w = np.exp(rec.brightness_sigma_ln * t.brightness_normal)
    ia = particle_image(cam, t.positions_a, w, rays_per_particle=setup.rays_per_particle,
                        seed=t.render_seed, instance=instance)
    ib = particle_image(cam, t.positions_b, w, rays_per_particle=setup.rays_per_particle,
                        seed=t.render_seed + 1, instance=instance,
                        pulse_energy=rec.pulse_ratio)
    # one exposure for both frames, fixed by A, so that B shows its pulse energy
    exposure = auto_exposure(ia, bit_depth=BIT_DEPTH, sensor=sensor)
    a, b = finish(ia, 2, exposure), finish(ib, 3, exposure)
    return Recording(fp, al, a, b, dark, white)


def record_calibration(setup: StudyCase, rec: RecordingSettings):
    """The focal-point and alignment images, dark and white stacks (or None) of one case.

    Each from its own stream of the seed, as :func:`record_case` records them.
    """
    cam = setup.truth_camera()
    instance = None if rec.is_ideal else camera_instance(cam, rec, seed=setup.camera_seed)
    finish, sensor = _finisher(instance, setup.seed)
    fp = finish(focal_point_image(cam, f_number=FOCAL_POINT_F_NUMBER, instance=instance), 0)
    al = finish(alignment_image(cam, instance=instance), 1)
    dark = white = None
    if sensor is not None:
        zero = np.zeros(cam.sensor.shape)
        dark = np.stack([finish(zero, 10 + k, 1.0) for k in range(DARK_FRAMES)])
    if instance is not None:
        irr = white_image(cam, instance=instance)
        e = auto_exposure(irr, bit_depth=BIT_DEPTH, sensor=sensor)
        white = np.stack([finish(irr, 30 + k, e) for k in range(WHITE_FRAMES)])
    return fp, al, dark, white


def _calibrate(cam: CameraModel, fp, al, dark_path: Path | None, white=None):
    """``plenopiv calibrate`` (``--dark``, ``--white`` when given): ``(calibration or None,
    S_i, error or warning)``.

    ``white``: the mean white frame (raw counts); ``calibrate`` takes the dark off it and the
    calibration images, and divides them by it (its flat field,
    :class:`~plenopiv.calibration.defects.WhiteFlat`). Its warnings are returned as
    ``"warned: ..."``.
    """
    dark = None if dark_path is None else calibration_dark(dark_path, cam.sensor.shape)[0]
    user = cam.replace(main_lens=replace(cam.main_lens, image_distance=None))
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", PlenopivWarning)
            rep = calibrate(user, fp, alignment_image=al, method="focal-point",
                            focal_point_f_number=FOCAL_POINT_F_NUMBER, white_image=white,
                            dark=dark)
    except PlenopivError as exc:
        return None, float("nan"), f"{type(exc).__name__}: {exc}"
    said = [str(w.message) for w in caught if issubclass(w.category, PlenopivWarning)]
    return (rep.calibration, rep.calibration.image_distance,
            "; ".join(f"warned: {m}" for m in said) or None)


def calibration_figures(setup: StudyCase, effect: str, frames, work: Path) -> tuple:
    """S_i of one case with its dark, without it and without the white: ``(calibration or
    None, the row's calibration keys)``. ``frames``: ``(focal point, alignment, dark stack,
    white stack)``; the stacks are written under ``work`` as ``plenopiv calibrate`` reads them.
    """
    rec = recording(effect)
    cam = setup.truth_camera()
    fp, al, dark_stack, white_stack = frames
    work.mkdir(parents=True, exist_ok=True)
    dark_path = None if dark_stack is None else write_image_stack(work / "dark.tif",
                                                                   dark_stack)
    white = None if white_stack is None else white_stack.mean(axis=0)
    if setup.calibrate:
        cal, s_i, failed = _calibrate(cam, fp, al, dark_path, white)
    else:
        cal, s_i, failed = Calibration.from_camera(cam), cam.image_distance, None
    out = {"true_image_distance_mm": cam.image_distance * 1e3,
           "image_distance_mm": s_i * 1e3,
           "image_distance_error_mm": (s_i - cam.image_distance) * 1e3,
           "calibration_dark": dark_path is not None, "calibration_error": failed}
    if dark_path is not None and setup.calibrate:
        # the same calibration images without their dark, as a calibration without --dark
        _, s_raw, failed_raw = _calibrate(cam, fp, al, None, white)
        out.update(image_distance_raw_mm=s_raw * 1e3,
                   image_distance_raw_error_mm=(s_raw - cam.image_distance) * 1e3,
                   calibration_raw_error=failed_raw)
    if setup.calibrate and rec.has_optics:
        # the same calibration images without the white: what the optics do to S_i
        _, s_bare, failed_bare = _calibrate(cam, fp, al, dark_path)
        out.update(image_distance_no_white_mm=s_bare * 1e3,
                   image_distance_no_white_error_mm=(s_bare - cam.image_distance) * 1e3,
                   calibration_no_white_error=failed_bare)
    return cal, out


def _particles(result, positions, tolerance) -> dict:
    """Particles of volume A found, matched to the truth; ghosts: found and not matched."""
    found = np.asarray(result.particle_position, float).reshape(-1, 3)
    pairs = match_particles(positions, found, tolerance)
    grid = result.grid
    inside = np.ones(len(positions), bool)
    for axis in range(3):
        lo, hi = grid.bounds[axis]
        inside &= (positions[:, axis] >= lo) & (positions[:, axis] <= hi)
    matched = np.zeros(len(positions), bool)
    matched[pairs[:, 0]] = True
    n_found = len(found)
    return {"n_true": int(inside.sum()), "n_found": n_found,
            "detected": int(matched[inside].sum()),
            "detection_rate": float(matched[inside].sum() / max(int(inside.sum()), 1)),
            "ghosts": int(n_found - len(pairs)),
            "ghost_rate": float((n_found - len(pairs)) / max(n_found, 1))}


def _run_pair(cal, exp, a, b, weights, t: Truth, case: VortexCase, tolerance) -> dict:
    """One pair through the chain; its scores and the preprocessing's warnings."""
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = process_pair(cal, a, b, exp, weights=weights)
    texts = [str(w.message) for w in caught if issubclass(w.category, PlenopivWarning)]
    disp = replace(res.vectors, dt=None)
    err = compare_with_truth(disp, t.flow, t.dt, exp.volume, case.windows_vox[-1])
    out = {"warned": bool(texts), "warnings": texts,
           "particles": _particles(res.volume_a, t.positions_a, tolerance),
           "gain": err["gain"], "bias_vox": err["bias_vox"], "rms_vox": err["rms_vox"],
           "n_vectors": err["n_vectors"], "valid_fraction": err["valid_fraction"],
           "seconds": round(time.perf_counter() - t0, 1)}
    if res.preprocess is not None and res.preprocess.get("applied"):
        p = res.preprocess
        out["preprocess"] = {"bad_pixels": p.get("bad_pixels"),
                             "scale_b": (p.get("normalisation") or {}).get("scale_b"),
                             "masked_pixels": p["exposures"]["A"].get("masked_pixels")}
    return out


def run_case(setup: StudyCase, effect: str, t: Truth, work: Path) -> dict:
    """One case: record, calibrate (with its dark), run the pair raw and preprocessed."""
    t0 = time.perf_counter()
    rec = recording(effect)
    frames = record_case(setup, rec, t)
    work.mkdir(parents=True, exist_ok=True)
    white_path = None
    if frames.white is not None:
        white_path = write_image_stack(work / "white.tif", frames.white)
    cal, figures = calibration_figures(
        setup, effect, (frames.focal_point, frames.alignment, frames.dark, frames.white), work)
    dark_path = work / "dark.tif" if frames.dark is not None else None
    out: dict = {"effect": effect,
                 "recording": {k: v for k, v in dataclasses.asdict(rec).items()
                               if v != getattr(RecordingSettings(), k)},
                 **figures}
    if cal is None:
        out["seconds"] = round(time.perf_counter() - t0, 1)
        return out
    case = setup.vortex()
    exp = case_experiment(case, cal, work)
    exp = replace(exp, base_dir=work)
    weights, _ = weights_for(cal, exp.volume, exp.reconstruction)
    b_cell, z_cell = resolution_cell(cal.effective_camera)
    tolerance = (b_cell, b_cell, z_cell)
    out["raw"] = _run_pair(cal, exp, frames.image_a, frames.image_b, weights, t, case,
                           tolerance)
    if effect != IDEAL:
        table = PreprocessSettings(dark=None if dark_path is None else dark_path.name,
                                   white=None if white_path is None else white_path.name,
                                   hot_pixels="auto")
        out["preprocess_table"] = dataclasses.asdict(table)
        out["preprocessed"] = _run_pair(cal, replace(exp, preprocess=table), frames.image_a,
                                        frames.image_b, weights, t, case, tolerance)
    out["seconds"] = round(time.perf_counter() - t0, 1)
    return out


def cases(effects=None) -> list[str]:
    """The cases in the page's order: ideal, each effect, all together."""
    return [IDEAL, *(EFFECTS if effects is None else effects), ALL]
