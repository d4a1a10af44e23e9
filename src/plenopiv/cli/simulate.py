"""``plenopiv simulate``: render synthetic plenoptic images (and pairs with their truth)."""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING

import numpy as np

from plenopiv import __version__
from plenopiv.cli._common import (
    MAX_SEED,
    _add_common,
    _add_example,
    _add_image_options,
    _camera_from_args,
    _check_out,
    _input_files,
    _integer,
    _number,
    _seed,
)
from plenopiv.cli._progress import _progress_bar
from plenopiv.errors import ConfigError, ResourceError
from plenopiv.products.files import check_output_path

if TYPE_CHECKING:
    from plenopiv.camera.model import CameraModel


#: The kinds of ``simulate`` and their help, in the order ``--help`` lists them.
KINDS = (("focal-point", "white sheet through the stopped-down lens"),
         ("alignment", "collimated light, main lens removed"),
         ("ruler", "a ruler with ticks on a plane at a given depth"),
         ("particles", "random point particles"),
         ("pair", "a particle image pair moved by a flow, with ground truth"),
         ("dark", "dark frames of the sensor: black level, fixed pattern, hot pixels, noise"),
         ("white", "white frames for a flat field: a uniform sheet at the recording's "
                   "aperture"))

#: Most frames one ``simulate dark`` or ``simulate white`` records.
MAX_FRAMES = 1000

#: The example line of each kind's ``--help``.
EXAMPLES = {"focal-point": "plenopiv simulate focal-point small_m1 --f-number 16 --out fp.tif",
            "alignment": "plenopiv simulate alignment small_m1 --out al.tif",
            "ruler": "plenopiv simulate ruler small_m1 --spacing-mm 1 --out ruler.tif",
            "particles": "plenopiv simulate particles small_m1 --n-particles 500 --out p.tif",
            "pair": "plenopiv simulate pair small_m1 --flow oseen --dt 1e-3 --out pair.h5",
            "dark": "plenopiv simulate dark small_m1 --realistic --frames 16 --out dark.tif",
            "white": "plenopiv simulate white small_m1 --realistic --frames 4 --out white.tif"}

#: The recording's options: ``(flag, RecordingSettings field, type, metavar, help)``; the
#: help ends with the value of :data:`plenopiv.synthetic.sensor.REALISTIC` (a test checks).
SENSOR_OPTIONS = (
    ("--black-level", "black_level_counts", float, "C",
     "black level (offset of every pixel), counts (default 0; 100 with --realistic)"),
    ("--column-offset", "column_offset_counts", float, "C",
     "rms of the offset of each column (fixed pattern), counts (default 0; 1.5 with "
     "--realistic)"),
    ("--pixel-offset", "pixel_offset_counts", float, "C",
     "rms of the offset of each pixel (fixed pattern), counts (default 0; 2.6 with "
     "--realistic)"),
    ("--gain", "gain_counts_per_electron", float, "G",
     "counts per photo-electron (default: the ADC's full scale over --full-well)"),
    ("--adc-bits", "adc_bits", int, "B",
     "bit depth of the ADC, 8 to 16: counts saturate at 2^B - 1 (default: --bit-depth; 12 "
     "with --realistic)"),
    ("--hot-pixels", "hot_pixel_fraction", float, "F",
     "fraction of hot pixels, bright in every frame (default 0; 1e-4 with --realistic)"),
    ("--hot-pixel-counts", "hot_pixel_counts", float, "C",
     "mean dark signal of a hot pixel per frame, counts; each is 0.5 to 1.5 times it "
     "(default 1000)"),
    ("--dead-pixels", "dead_pixel_fraction", float, "F",
     "fraction of dead pixels, without response to light (default 0; 1e-5 with "
     "--realistic)"),
)
OPTICS_OPTIONS = (
    ("--throughput-spread", "throughput_spread", float, "S",
     "each lenslet passes a factor uniform in 1 +- S of the light (default 0; 0.1 with "
     "--realistic)"),
    ("--vignetting", "vignetting", float, "V",
     "fraction of the light lost at the rim of a micro-image, half a pitch from its centre; "
     "cos^4-like fall-off (default 0; 0.2 with --realistic)"),
    ("--vignetting-centre", "vignetting_centre", str, None,
     "centre of the fall-off: each micro-image's centre, or its lenslet's axis (the point "
     "under the lenslet's centre; pulls focal spots towards it) (default micro-image)"),
)
#: The recording options that take one of a few words.
CHOICES = {"sheet_profile": ("none", "gaussian", "tophat"),
           "vignetting_centre": ("micro-image", "lenslet")}
LIGHT_OPTIONS = (
    ("--glow", "glow", float, "G",
     "smooth background glow, its peak G times the irradiance of an in-focus particle of "
     "unit brightness (default 0; 0.02 with --realistic)"),
    ("--brightness-spread", "brightness_sigma_ln", float, "S",
     "standard deviation of the log of particle brightness, log-normal with median 1 "
     "(default 0; 0.3 with --realistic)"),
    ("--sheet", "sheet_profile", str, None,
     "depth profile of the light: none (uniform), gaussian (FWHM --sheet-thickness-mm) or "
     "tophat (full width --sheet-thickness-mm) (default none)"),
    ("--sheet-centre-mm", "sheet_centre_mm", float, "Z",
     "depth Z of the sheet's centre, mm (default 0)"),
    ("--sheet-thickness-mm", "sheet_thickness_mm", float, "W",
     "the sheet's thickness, mm (default 10)"),
)
PAIR_OPTIONS = (
    ("--pulse-ratio", "pulse_ratio", float, "R",
     "energy of the second pulse over the first's (default 1; 0.85 with --realistic)"),
)


def add_parser(sub) -> None:
    """Add ``simulate`` and its kinds (:data:`KINDS`) to the subcommands ``sub``."""
    from plenopiv.camera.model import preset_names

    sim = sub.add_parser("simulate", help="render synthetic plenoptic images by ray tracing")
    _add_example(sim, EXAMPLES["pair"])
    simsub = sim.add_subparsers(dest="kind", required=True)
    presets = ", ".join(preset_names())
    for kind, helptext in KINDS:
        p = simsub.add_parser(kind, help=helptext)
        p.add_argument("camera", help=f"camera TOML file or preset name ({presets})")
        p.add_argument("--out", required=True,
                       help="output file (.tif, .png; .h5 for pairs; .tif or .h5 for dark and "
                            "white frames)")
        if kind != "dark":
            p.add_argument("--image-distance-mm", type=float, default=None,
                           help="override [main_lens] image_distance_mm (effective S_i)")
            p.add_argument("--f-number", type=float, default=None,
                           help="stop for this image (default: the camera's f_number)")
        if kind == "dark":
            _add_lenslets_option(p)
        elif kind != "pair":
            _add_render_options(p)
        _add_image_options(p)
        _add_common(p)
        _add_example(p, EXAMPLES[kind])
        p.set_defaults(func=cmd_simulate)
        if kind == "ruler":
            _add_ruler_options(p)
        if kind in ("particles", "pair"):
            _add_seeding_options(p)
        if kind == "pair":
            _add_flow_options(p)
        _add_recording_options(p, kind)


def _add_render_options(p) -> None:
    p.add_argument("--splat", choices=("bilinear", "pixel"), default="bilinear",
                   help="a ray's energy shared by area among the 4 nearest pixel "
                        "centres (default), or all into the pixel it hits")
    p.add_argument("--psf-px", type=float, default=0.0,
                   help="Gaussian point-spread sigma before the pixels integrate, "
                        "pixels (default 0)")
    p.add_argument("--sensor-shift-px", type=float, nargs=2, default=(0.0, 0.0),
                   metavar=("DROW", "DCOL"),
                   help="shift the image content by a (sub-)pixel amount (default 0 0)")
    _add_lenslets_option(p)


def _add_lenslets_option(p) -> None:
    p.add_argument("--lenslets", type=int, nargs=2, metavar=("ROWS", "COLS"),
                   help="render the central ROWS x COLS lenslets of the camera, on a "
                        "sensor cut to them (odd counts put a lenslet on the axis)")


def _add_recording_options(p, kind: str) -> None:
    """The real recording's effects (:class:`plenopiv.synthetic.sensor.RecordingSettings`)."""
    g = p.add_argument_group("real recording (default: an ideal render, every effect off)")
    g.add_argument("--realistic", action="store_true",
                   help="a typical real recording (plenopiv.synthetic.sensor.REALISTIC; "
                        "photon noise on); the options below override its values")
    g.add_argument("--camera-seed", type=int, default=0,
                   help="seed of the camera instance: its fixed pattern, hot and dead pixels, "
                        "lenslet throughputs and glow, shared by its dark, white and particle "
                        "frames (default 0)")
    options = SENSOR_OPTIONS
    if kind != "dark":
        options += OPTICS_OPTIONS
    if kind in ("particles", "pair"):
        options += LIGHT_OPTIONS
    if kind == "pair":
        options += PAIR_OPTIONS
    for flag, field, kind_, metavar, helptext in options:
        if field in CHOICES:
            g.add_argument(flag, dest=field, choices=CHOICES[field], default=None,
                           help=helptext)
        else:
            g.add_argument(flag, dest=field, type=kind_, metavar=metavar, default=None,
                           help=helptext)
    if kind in ("dark", "white"):
        g.add_argument("--frames", type=int, default=1,
                       help="frames to record, each with its own noise: a multi-page TIFF or "
                            "an HDF5 stack /frames (default 1)")


def _add_ruler_options(p) -> None:
    p.add_argument("--spacing-mm", type=float, default=1.0, help="tick spacing (mm)")
    p.add_argument("--tick-width-mm", type=float, default=0.15, help="tick width (mm)")
    p.add_argument("--depth-mm", type=float, default=0.0,
                   help="ruler plane depth Z from the focal plane (mm, default 0)")
    p.add_argument("--rays-per-lenslet", type=int, default=2000,
                   help="rays per lenslet footprint (default 2000)")


def _add_seeding_options(p) -> None:
    dens = p.add_mutually_exclusive_group()
    dens.add_argument("--particles-per-lenslet", type=float, default=0.1,
                      help="seeding density per lenslet (default 0.1)")
    dens.add_argument("--particles-per-mm3", type=float, default=None,
                      help="seeding density per mm³ of the seeded box")
    dens.add_argument("--n-particles", type=int, default=None, help="particle count")
    p.add_argument("--depth-mm", type=float, nargs=2, default=(-5.0, 5.0),
                   metavar=("ZMIN", "ZMAX"),
                   help="seeded depth range Z (mm, default -5 5)")
    p.add_argument("--fill", type=float, default=0.9,
                   help="fraction of the lateral field of view seeded (default 0.9)")
    p.add_argument("--rays-per-particle", type=int, default=2048,
                   help="aperture samples per particle (default 2048)")


def _add_flow_options(p) -> None:
    p.add_argument("--flow", choices=("uniform", "oseen", "hill"), default="oseen",
                   help="flow moving the particles (default oseen, axis along Y)")
    p.add_argument("--dt", type=float, default=1e-3, help="time between exposures (s)")
    p.add_argument("--max-displacement-mm", type=float, default=0.5,
                   help="largest particle displacement of the flow (mm, default 0.5)")
    p.add_argument("--no-tiff", action="store_true",
                   help="write only the HDF5 file (no A/B TIFFs beside it)")


def cmd_simulate(args) -> dict:
    """Render a synthetic image (or a pair, or dark or white frames) and write it."""
    from plenopiv.products.images import write_image
    from plenopiv.synthetic import images as S

    _check_simulate_args(args)
    recording = _recording_settings(args)
    cam = _camera_from_args(args)
    rec = _Recording(cam, args, recording)
    # the resolved values, as the files' config records them
    args.noise, args.read_noise = rec.noise, recording.read_noise_counts
    rng = np.random.default_rng(args.seed)
    kind = args.kind
    t0 = time.perf_counter()
    summary: dict = {"command": f"simulate {kind}", "camera": cam.name,
                     "image_distance_mm": cam.image_distance * 1e3}
    if kind in ("focal-point", "alignment", "ruler"):
        out = _check_out(args.out, (".tif", ".tiff", ".png"), inputs=_input_files(args.camera))
        bar, tick = _progress_bar(cam.microlens_array.count if kind != "ruler" else 32,
                                  f"render {kind}", args.quiet or args.json)
        with bar:
            render = _render_options(args)
            summary.update(render)
            if rec.instance is not None:
                render["instance"] = rec.instance
            if kind == "focal-point":
                f_number = args.f_number or cam.main_lens.f_number
                irr = S.focal_point_image(cam, f_number=f_number, progress=tick, **render)
                summary["f_number"] = f_number
            elif kind == "alignment":
                irr = S.alignment_image(cam, progress=tick, **render)
            else:
                ruler = S.Ruler(spacing=args.spacing_mm * 1e-3,
                                tick_width=args.tick_width_mm * 1e-3, depth=args.depth_mm * 1e-3)
                bar.total = None
                irr = S.ruler_image(cam, ruler, f_number=args.f_number, seed=args.seed,
                                    rays_per_lenslet=args.rays_per_lenslet, **render)
                summary.update(spacing_mm=args.spacing_mm, depth_mm=args.depth_mm)
        img = rec.finish(irr, rng)
        summary.update(rec.summary())
        meta = {"plenopiv": __version__, "kind": kind, "camera": cam.to_dict(), **summary,
                **rec.metadata()}
        write_image(out, img, metadata=meta)
    elif kind in ("particles", "pair"):
        summary.update(_simulate_particles(cam, args, rng, rec))
        return {**summary, "seconds": round(time.perf_counter() - t0, 3)}
    else:
        summary.update(_simulate_frames(cam, args, rng, rec))
        return {**summary, "seconds": round(time.perf_counter() - t0, 3)}
    summary.update(out=str(out), **_image_summary(img),
                   seconds=round(time.perf_counter() - t0, 3))
    return summary


def _recording_settings(args):
    """The :class:`~plenopiv.synthetic.sensor.RecordingSettings` of the command line.

    ``--realistic`` starts from :data:`~plenopiv.synthetic.sensor.REALISTIC`, else from the
    ideal defaults; every recording option given overrides its field.
    """
    import dataclasses

    from pydantic import ValidationError

    from plenopiv.synthetic.sensor import REALISTIC, RecordingSettings

    base = REALISTIC if args.realistic else RecordingSettings()
    flags = {field: flag for flag, field, *_ in
             SENSOR_OPTIONS + OPTICS_OPTIONS + LIGHT_OPTIONS + PAIR_OPTIONS}
    flags["read_noise_counts"] = "--read-noise"
    given = {field: getattr(args, field) for field in flags
             if getattr(args, field, None) is not None and field != "read_noise_counts"}
    if args.read_noise is not None:
        given["read_noise_counts"] = args.read_noise
    try:
        return RecordingSettings(**{**dataclasses.asdict(base), **given})
    except ValidationError as exc:
        lines = []
        for err in exc.errors():
            field = str(err["loc"][0]) if err["loc"] else ""
            flag = flags.get(field)
            what = err["msg"].removeprefix("Value error, ").lower()
            lines.append(f"{flag} {err.get('input')!r}: {what}" if flag else what)
        raise ConfigError("; ".join(lines)) from None


class _Recording:
    """The recording of one ``simulate`` command: its settings, camera instance and finish.

    With every effect off there is no instance, and images are finished exactly as the ideal
    simulator always did.
    """

    def __init__(self, cam: CameraModel, args, settings):
        from plenopiv.synthetic.sensor import camera_instance

        self.args = args
        self.settings = settings
        self.noise = args.noise or ("poisson" if args.realistic else "none")
        self.bits = None if args.bit_depth == 0 else args.bit_depth
        self.instance = None if settings.is_ideal else camera_instance(
            cam, settings, seed=args.camera_seed)
        self.exposure: float | None = None
        if self.instance is not None and settings.has_sensor:
            from plenopiv.synthetic.sensor import adc_full_scale

            adc_full_scale(settings, self.bits)      # refuses float output before rendering

    def fix_exposure(self, irradiance) -> None:
        """Fix the exposure from this frame (the first of a pair) for the frames after it."""
        from plenopiv.synthetic.images import auto_exposure

        if self.instance is not None:
            self.exposure = auto_exposure(irradiance, bit_depth=self.bits,
                                          blur_px=self.args.blur_px, sensor=self.instance)

    def finish(self, irradiance, rng):
        """The recorded image of ``irradiance``: ideal finish, or through the camera instance."""
        from plenopiv.synthetic.images import finish_image

        a = self.args
        if self.instance is None:
            return finish_image(irradiance, blur_px=a.blur_px, noise=self.noise,
                                bit_depth=self.bits, full_well=a.full_well,
                                read_noise=self.settings.read_noise_counts, rng=rng)
        if self.exposure is None:
            self.fix_exposure(irradiance)
        return finish_image(irradiance, exposure=self.exposure,
                            blur_px=a.blur_px, noise=self.noise, bit_depth=self.bits,
                            full_well=a.full_well, rng=rng, sensor=self.instance)

    def metadata(self) -> dict:
        """Every effect, both seeds and how the frames were finished (none when ideal)."""
        from plenopiv.synthetic.sensor import describe

        if self.instance is None:
            return {}
        a = self.args
        return {"recording": {"preset": "realistic" if a.realistic else "none",
                              **describe(self.instance), "seed": a.seed,
                              "noise": self.noise, "full_well": a.full_well,
                              "bit_depth": self.bits, "blur_px": a.blur_px,
                              "exposure_counts_per_irradiance": self.exposure}}

    def summary(self) -> dict:
        """For ``--json``: the preset, both seeds and the effects that differ from ideal."""
        import dataclasses

        from plenopiv.synthetic.sensor import RecordingSettings

        if self.instance is None:
            return {}
        ideal = dataclasses.asdict(RecordingSettings())
        effects = {k: v for k, v in dataclasses.asdict(self.settings).items() if v != ideal[k]}
        return {"recording": {"preset": "realistic" if self.args.realistic else "none",
                              "camera_seed": self.instance.seed, "seed": self.args.seed,
                              "effects": effects}}


def _simulate_frames(cam: CameraModel, args, rng, rec: _Recording) -> dict:
    """``simulate dark`` or ``simulate white``: ``--frames`` recordings, one file."""
    from plenopiv.products.hdf5 import write_h5
    from plenopiv.products.images import write_image, write_image_stack
    from plenopiv.synthetic.images import white_image

    out = _check_out(args.out, (".tif", ".tiff", ".h5"), inputs=_input_files(args.camera))
    info: dict = {"frames": args.frames}
    if args.kind == "dark":
        irr = np.zeros(cam.sensor.shape)
        rec.exposure = 1.0
    else:
        f_number = args.f_number or cam.main_lens.f_number
        bar, tick = _progress_bar(cam.microlens_array.count, "render white",
                                  args.quiet or args.json)
        with bar:
            irr = white_image(cam, f_number=f_number, instance=rec.instance, progress=tick,
                              **_render_options(args))
        info.update(f_number=f_number, **_render_options(args))
        rec.fix_exposure(irr)
    frames = np.stack([rec.finish(irr, rng) for _ in range(args.frames)])
    info.update(rec.summary())
    if out.suffix.lower() == ".h5":
        config = {"camera": cam.to_dict(), "simulate": _args_config(args), **rec.metadata()}
        write_h5(out, {"/frames": frames}, attrs={"frames": args.frames},
                 units={"/frames": "1"}, config=config, kind=f"synthetic {args.kind}")
    else:
        meta = {"plenopiv": __version__, "kind": args.kind, "camera": cam.to_dict(),
                "seed": args.seed, **info, **rec.metadata()}
        if args.frames == 1:
            write_image(out, frames[0], metadata=meta)
        else:
            write_image_stack(out, frames, metadata=meta)
    return {**info, "out": str(out), **_image_summary(frames)}


def _args_config(args) -> dict:
    return {k: v for k, v in vars(args).items() if k not in ("func",)}


def _check_simulate_args(args) -> None:
    """The options of ``simulate``, before the camera is loaded or anything rendered."""
    _seed(args.seed)
    _integer("--camera-seed", args.camera_seed, minimum=0, maximum=MAX_SEED)
    if args.kind in ("dark", "white"):
        _integer("--frames", args.frames, minimum=1, maximum=MAX_FRAMES)
    _number("--f-number", getattr(args, "f_number", None), minimum=0, open_min=True)
    _number("--blur-px", args.blur_px, minimum=0, maximum=100, unit="pixels")
    _number("--psf-px", getattr(args, "psf_px", None), minimum=0, maximum=100, unit="pixels")
    for shift in getattr(args, "sensor_shift_px", ()):
        _number("--sensor-shift-px", shift, minimum=-1e6, maximum=1e6, unit="pixels")
    _number("--full-well", args.full_well, minimum=0, open_min=True, unit="electrons")
    _number("--read-noise", args.read_noise, minimum=0, unit="counts")
    if args.kind == "ruler":
        _number("--spacing-mm", args.spacing_mm, minimum=0, open_min=True, unit="mm")
        _number("--tick-width-mm", args.tick_width_mm, minimum=0, open_min=True,
                maximum=args.spacing_mm, open_max=True, unit="mm, less than --spacing-mm")
        _number("--depth-mm", args.depth_mm, unit="mm")
        _integer("--rays-per-lenslet", args.rays_per_lenslet, minimum=1, maximum=10 ** 6)
    if args.kind in ("particles", "pair"):
        _number("--particles-per-lenslet", args.particles_per_lenslet, minimum=0,
                open_min=True, maximum=100)
        _number("--particles-per-mm3", args.particles_per_mm3, minimum=0, open_min=True)
        _integer("--n-particles", args.n_particles, minimum=1, maximum=10 ** 7)
        lo = _number("--depth-mm ZMIN", args.depth_mm[0], unit="mm")
        _number("--depth-mm ZMAX", args.depth_mm[1], minimum=lo, open_min=True,
                unit="mm, more than ZMIN")
        _number("--fill", args.fill, minimum=0, open_min=True, maximum=1)
        _integer("--rays-per-particle", args.rays_per_particle, minimum=1, maximum=10 ** 6)
    if args.kind == "pair":
        _number("--dt", args.dt, minimum=0, open_min=True, unit="seconds")
        _number("--max-displacement-mm", args.max_displacement_mm, minimum=0, open_min=True,
                unit="mm")


def _render_options(args) -> dict:
    """Return the rendering choices of ``simulate`` (splat, PSF, sensor shift) as kwargs."""
    return {"splat": args.splat, "psf_px": args.psf_px,
            "sensor_shift_px": tuple(args.sensor_shift_px)}


def _image_summary(img) -> dict:
    return {"shape": list(img.shape), "dtype": str(img.dtype), "max": float(img.max()),
            "mean": float(img.mean())}


def _seeding(cam: CameraModel, args, rng):
    from plenopiv.synthetic.seeding import SeedingBox, particle_count

    depth = (args.depth_mm[0] * 1e-3, args.depth_mm[1] * 1e-3)
    box = SeedingBox.field_of_view(cam, depth, fill=args.fill)
    if args.n_particles is not None:
        n = args.n_particles
    elif args.particles_per_mm3 is not None:
        n = particle_count(cam, box, per_mm3=args.particles_per_mm3)
    else:
        n = particle_count(cam, box, per_lenslet=args.particles_per_lenslet)
    if n < 1:
        raise ConfigError(f"the seeding gives {n} particles: expected at least 1")
    if n > 10 ** 7:
        raise ResourceError(f"the seeding gives {n} particles: expected at most 10^7 (lower "
                            "the density)")
    return box, n


def _flow_from_args(cam: CameraModel, args, box):
    from plenopiv.synthetic import flows

    dt = args.dt
    vmax = args.max_displacement_mm * 1e-3 / dt      # m/s at the fastest point
    half_y = 0.5 * (box.y[1] - box.y[0])
    if args.flow == "uniform":
        return flows.Uniform((vmax, 0.0, 0.0))
    if args.flow == "oseen":
        rc = 0.4 * half_y
        # the peak of v_θ is 0.638 Γ/(2π r_c) at r = 1.121 r_c
        gamma = vmax * 2 * math.pi * rc / 0.6382
        return flows.LambOseen(circulation=gamma, core_radius=rc, axis=(0.0, 1.0, 0.0),
                               centre=(0.0, 0.0, 0.5 * (box.z[0] + box.z[1])))
    if args.flow == "hill":
        return flows.HillVortex(radius=0.6 * half_y, speed=vmax / 1.5,
                                centre=(0.0, 0.0, 0.5 * (box.z[0] + box.z[1])))
    raise ConfigError(f"--flow {args.flow!r}: expected one of uniform, oseen, hill")


def _simulate_particles(cam: CameraModel, args, rng, rec: _Recording) -> dict:
    """``simulate particles`` or ``simulate pair``: seed the box, render, write; the summary."""
    box, n = _seeding(cam, args, rng)
    info = {"n_particles": n, "rays_per_particle": args.rays_per_particle,
            "box_mm": [[v * 1e3 for v in box.x], [v * 1e3 for v in box.y],
                       [v * 1e3 for v in box.z]]}
    config = {"camera": cam.to_dict(), "simulate": _args_config(args)}
    render = _render_particle_image if args.kind == "particles" else _render_pair
    return {**info, **render(cam, args, rng, box, n, info, config, rec)}


def _render_particle_image(cam: CameraModel, args, rng, box, n: int, info: dict,
                           config: dict, rec: _Recording) -> dict:
    """Render ``n`` random particles in ``box`` into one image and write it (TIFF/PNG/HDF5)."""
    from plenopiv.products.hdf5 import write_h5
    from plenopiv.products.images import write_image
    from plenopiv.synthetic.images import particle_image
    from plenopiv.synthetic.seeding import random_particles
    from plenopiv.synthetic.sensor import particle_brightness

    out = _check_out(args.out, (".tif", ".tiff", ".png", ".h5"),
                     inputs=_input_files(args.camera))
    pos = random_particles(box, n, rng)
    brightness = particle_brightness(n, rec.settings, rng)
    extra = {} if rec.instance is None else {"instance": rec.instance}
    bar, tick = _progress_bar(n, "render particles", args.quiet or args.json)
    with bar:
        irr = particle_image(cam, pos, brightness, rays_per_particle=args.rays_per_particle,
                             f_number=args.f_number, seed=args.seed, progress=tick,
                             **_render_options(args), **extra)
    img = rec.finish(irr, rng)
    meta = rec.metadata()
    if out.suffix.lower() == ".h5":
        datasets = {"/image": img, "/truth/position_m": pos}
        if brightness is not None:
            datasets["/truth/intensity"] = brightness
        write_h5(out, datasets, units={"/truth/position_m": "m"}, config={**config, **meta},
                 kind="synthetic particles")
    else:
        write_image(out, img, metadata={"camera": cam.to_dict(), **info, **meta})
    return {"out": str(out), **_image_summary(img), **rec.summary()}


def _render_pair(cam: CameraModel, args, rng, box, n: int, info: dict, config: dict,
                 rec: _Recording) -> dict:
    """Render a pair moved by the flow; write the HDF5 file with its truth, and the TIFFs."""
    from plenopiv.products.hdf5 import write_h5
    from plenopiv.products.images import write_image
    from plenopiv.synthetic.seeding import simulate_pair

    out = _check_out(args.out, (".h5",), inputs=_input_files(args.camera))
    if not args.no_tiff:
        for tag in "AB":
            check_output_path(out.with_name(f"{out.stem}_{tag}.tif"),
                              inputs=_input_files(args.camera), what=f"the {tag} TIFF beside --out")
    flow = _flow_from_args(cam, args, box)
    bar, tick = _progress_bar(2 * n, "render pair", args.quiet or args.json)
    with bar:
        pair = simulate_pair(cam, flow, dt=args.dt, box=box, n_particles=n, rng=rng,
                             rays_per_particle=args.rays_per_particle, f_number=args.f_number,
                             progress=tick, instance=rec.instance)
    # one exposure for both frames, fixed by A, so that B shows its pulse energy
    rec.fix_exposure(pair.image_a)
    ia, ib = rec.finish(pair.image_a, rng), rec.finish(pair.image_b, rng)
    disp = pair.displacement
    meta = rec.metadata()
    config.update(meta)
    config["flow"] = {"kind": args.flow, **{k: (list(v) if isinstance(v, tuple) else v)
                                            for k, v in vars(flow).items()}}
    write_h5(out, {"/image_a": ia, "/image_b": ib, "/truth/position_a_m": pair.positions_a,
                   "/truth/position_b_m": pair.positions_b, "/truth/displacement_m": disp,
                   "/truth/intensity": pair.intensities},
             attrs={"dt_s": args.dt, "flow": args.flow},
             units={"/truth/position_a_m": "m", "/truth/position_b_m": "m",
                    "/truth/displacement_m": "m"}, config=config, kind="synthetic pair")
    tifs = []
    if not args.no_tiff:
        for tag, im in (("A", ia), ("B", ib)):
            p = out.with_name(f"{out.stem}_{tag}.tif")
            write_image(p, im, metadata={"camera": cam.to_dict(), "exposure": tag, **meta})
            tifs.append(str(p))
    return {"out": str(out), "tiff": tifs, "flow": args.flow, "dt_s": args.dt,
            "max_displacement_mm": float(np.linalg.norm(disp, axis=1).max() * 1e3),
            **_image_summary(ia), **rec.summary()}
