"""The ``plenopiv`` command (DESIGN.md §7). Every subcommand takes ``--json``.

Orchestration only: parse, validate, call the library, write products atomically, report.

One error path (:func:`main`): every failure is one line on stderr, ``error: ...``, naming the
thing, the value and what was expected, and with ``--json`` also one JSON object holding
``"error"`` on stdout. Exit status (README "Exit status"): 0 done; 1 a computation or a write
failed (a full disk, pairs of a batch failed); 2 bad input, refused before any work (nothing
is written); 130 interrupted (Ctrl-C). Arguments, output paths and sizes are checked before
the computation, next to each subcommand; no input file is ever overwritten.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from tqdm import tqdm

from plenopiv import __version__
from plenopiv.camera import CameraModel, load_camera, preset_names
from plenopiv.errors import (
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    ConfigError,
    PlenopivError,
    PlenopivWarning,
    ResourceError,
)
from plenopiv.io import check_output_path, to_json, write_h5, write_image

# ---- shared helpers ------------------------------------------------------------------------


def _progress_bar(total: int, desc: str, quiet: bool):
    # disable=None: tqdm shows the bar only when stderr is a terminal (never in logs)
    bar = tqdm(total=total, desc=desc, unit="", disable=True if quiet else None, leave=False,
               file=sys.stderr, dynamic_ncols=True)
    return bar, (lambda n: bar.update(n))


class _StageBar:
    """One progress bar over a command's named stages, on a terminal only.

    ``stages`` maps each stage the library reports (``progress(stage, fraction)``) to its
    expected share of the time; a reported stage counts for the longest listed name it starts
    with ("piv pass 2/3" for "piv"). The bar shows the stage and the overall percentage, and
    never goes back. A stage not listed only changes the text.
    """

    def __init__(self, desc: str, stages: dict[str, float], quiet: bool):
        self.desc = desc
        self.bar = tqdm(total=100, desc=desc, disable=True if quiet else None, leave=False,
                        file=sys.stderr, dynamic_ncols=True,
                        bar_format="{desc} {percentage:3.0f}%|{bar}| {elapsed}")
        total = float(sum(stages.values())) or 1.0
        self.span, acc = {}, 0.0
        for name, weight in stages.items():
            self.span[name] = (acc / total, weight / total)
            acc += weight

    def __call__(self, stage: str, fraction: float = 0.0) -> None:
        self.bar.set_description_str(f"{self.desc}: {stage}", refresh=False)
        names = [k for k in self.span if stage.startswith(k)]
        if names:
            lo, width = self.span[max(names, key=len)]
            n = int(100 * (lo + width * min(max(float(fraction), 0.0), 1.0)))
            self.bar.n = max(self.bar.n, n)
        self.bar.refresh()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        """Remove the bar."""
        self.bar.close()


def _camera_from_args(args) -> CameraModel:
    from plenopiv.resources import check_sensor

    cam = load_camera(args.camera)
    if getattr(args, "image_distance_mm", None) is not None:
        _number("--image-distance-mm", args.image_distance_mm, minimum=0, open_min=True)
        cam = cam.with_image_distance(args.image_distance_mm * 1e-3)
    if getattr(args, "lenslets", None) is not None:
        if min(args.lenslets) < 1:
            raise ConfigError(f"--lenslets {args.lenslets[0]} {args.lenslets[1]}: expected two "
                              "positive lenslet counts ROWS COLS")
        cam = cam.patch(*args.lenslets)
    check_sensor(cam)
    return cam


# ---- argument checks (each subcommand checks its own before any work) ------------------------


def _number(flag: str, value, *, minimum=None, maximum=None, open_min=False, open_max=False,
            unit: str = "") -> float | None:
    """A finite number within bounds, or a ConfigError naming the flag, the value and the
    expected range. None passes (an unset option)."""
    if value is None:
        return None
    v = float(value)
    parts = []
    if minimum is not None:
        parts.append(f"{'>' if open_min else '>='} {minimum:g}")
    if maximum is not None:
        parts.append(f"{'<' if open_max else '<='} {maximum:g}")
    ok = math.isfinite(v)
    if ok and minimum is not None:
        ok = v > minimum if open_min else v >= minimum
    if ok and maximum is not None:
        ok = v < maximum if open_max else v <= maximum
    if not ok:
        rng = " and ".join(parts)
        raise ConfigError(f"{flag} {value!r}: expected a finite number"
                          + (f" {rng}" if rng else "") + (f" ({unit})" if unit else ""))
    return v


def _integer(flag: str, value, *, minimum: int, maximum: int) -> int | None:
    if value is None:
        return None
    if not minimum <= value <= maximum:
        raise ConfigError(f"{flag} {value}: expected an integer from {minimum} to {maximum}")
    return value


#: Largest seed accepted (numpy accepts any non-negative integer; the ray tracer takes 32 bits)
MAX_SEED = 2 ** 32 - 1


def _seed(value) -> int:
    return _integer("--seed", value, minimum=0, maximum=MAX_SEED)


def _input_files(*specs) -> list[str]:
    """The files among the command's inputs (file.h5:/dataset → file.h5; preset names out)."""
    from plenopiv.io import split_dataset_spec

    out = []
    for s in specs:
        if s is None:
            continue
        path, _ = split_dataset_spec(s)
        if path.exists():
            out.append(str(path))
    return out


def _finish(irr, args, rng):
    from plenopiv.synthetic.images import finish_image

    bits = None if args.bit_depth == 0 else args.bit_depth
    return finish_image(irr, blur_px=args.blur_px, noise=args.noise, bit_depth=bits,
                        full_well=args.full_well, read_noise=args.read_noise, rng=rng)


def _check_out(path: str, suffixes: tuple[str, ...], inputs=(), beside=()) -> Path:
    """Check ``--out`` before any work: suffix, not a folder, writable, not an input; and the
    files written beside it (``beside``: suffixes such as ".png") likewise."""
    p = check_output_path(path, suffixes=suffixes, inputs=inputs)
    for suffix in beside:
        check_output_path(p.with_suffix(suffix), inputs=inputs,
                          what=f"{suffix[1:].upper()} written beside --out")
    _remove_stale_temporaries([p, *(p.with_suffix(x) for x in beside)])
    return p


def _remove_stale_temporaries(paths) -> None:
    """Delete the hidden temporaries that a killed earlier run left for these outputs
    (``.NAME.XXXXXXXX.part``, and ``.part.vti`` of the VTK writer)."""
    import contextlib
    import glob

    for p in paths:
        if not p.parent.is_dir():
            continue
        for pattern in (f".{glob.escape(p.name)}.*.part", f".{glob.escape(p.name)}.*.part.*"):
            for t in p.parent.glob(pattern):
                with contextlib.suppress(OSError):
                    t.unlink()


def _image_summary(img) -> dict:
    return {"shape": list(img.shape), "dtype": str(img.dtype), "max": float(img.max()),
            "mean": float(img.mean())}


# ---- simulate ------------------------------------------------------------------------------


def cmd_simulate(args) -> dict:
    """Render a synthetic image (or a pair) and write it."""
    from plenopiv.synthetic import images as S

    _check_simulate_args(args)
    cam = _camera_from_args(args)
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
        img = _finish(irr, args, rng)
        meta = {"plenopiv": __version__, "kind": kind, "camera": cam.to_dict(), **summary}
        write_image(out, img, metadata=meta)
    elif kind in ("particles", "pair"):
        summary.update(_simulate_particles(cam, args, rng))
        return {**summary, "seconds": round(time.perf_counter() - t0, 3)}
    summary.update(out=str(out), **_image_summary(img),
                   seconds=round(time.perf_counter() - t0, 3))
    return summary


def _check_simulate_args(args) -> None:
    """The options of ``simulate``, before the camera is loaded or anything rendered."""
    _seed(args.seed)
    _number("--f-number", args.f_number, minimum=0, open_min=True)
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


def _simulate_particles(cam: CameraModel, args, rng) -> dict:
    from plenopiv.synthetic.images import particle_image
    from plenopiv.synthetic.seeding import random_particles, simulate_pair

    box, n = _seeding(cam, args, rng)
    info = {"n_particles": n, "rays_per_particle": args.rays_per_particle,
            "box_mm": [[v * 1e3 for v in box.x], [v * 1e3 for v in box.y],
                       [v * 1e3 for v in box.z]]}
    quiet = args.quiet or args.json
    config = {"camera": cam.to_dict(), "simulate": {k: v for k, v in vars(args).items()
                                                    if k not in ("func",)}}
    if args.kind == "particles":
        out = _check_out(args.out, (".tif", ".tiff", ".png", ".h5"),
                         inputs=_input_files(args.camera))
        pos = random_particles(box, n, rng)
        bar, tick = _progress_bar(n, "render particles", quiet)
        with bar:
            irr = particle_image(cam, pos, rays_per_particle=args.rays_per_particle,
                                 f_number=args.f_number, seed=args.seed, progress=tick,
                                 **_render_options(args))
        img = _finish(irr, args, rng)
        if out.suffix.lower() == ".h5":
            write_h5(out, {"/image": img, "/truth/position_m": pos},
                     units={"/truth/position_m": "m"}, config=config, kind="synthetic particles")
        else:
            write_image(out, img, metadata={"camera": cam.to_dict(), **info})
        return {**info, "out": str(out), **_image_summary(img)}
    out = _check_out(args.out, (".h5",), inputs=_input_files(args.camera))
    if not args.no_tiff:
        for tag in "AB":
            check_output_path(out.with_name(f"{out.stem}_{tag}.tif"),
                              inputs=_input_files(args.camera), what=f"the {tag} TIFF beside --out")
    flow = _flow_from_args(cam, args, box)
    bar, tick = _progress_bar(2 * n, "render pair", quiet)
    with bar:
        pair = simulate_pair(cam, flow, dt=args.dt, box=box, n_particles=n, rng=rng,
                             rays_per_particle=args.rays_per_particle, f_number=args.f_number,
                             progress=tick)
    ia, ib = _finish(pair.image_a, args, rng), _finish(pair.image_b, args, rng)
    disp = pair.displacement
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
            write_image(p, im, metadata={"camera": cam.to_dict(), "exposure": tag})
            tifs.append(str(p))
    return {**info, "out": str(out), "tiff": tifs, "flow": args.flow, "dt_s": args.dt,
            "max_displacement_mm": float(np.linalg.norm(disp, axis=1).max() * 1e3),
            **_image_summary(ia)}


# ---- calibrate -----------------------------------------------------------------------------


def cmd_calibrate(args) -> dict:
    """Calibrate a camera from its images and write the calibration product."""
    from plenopiv.calibration.pipeline import calibrate
    from plenopiv.io import read_image
    from plenopiv.resources import check_sensor

    _number("--ruler-spacing-mm", args.ruler_spacing_mm, minimum=0, open_min=True, unit="mm")
    _number("--max-missing-fraction", args.max_missing_fraction, minimum=0, maximum=1,
            open_max=True)
    _number("--max-rms-residual-pitch", args.max_rms_residual_pitch, minimum=0, open_min=True,
            maximum=1, unit="fraction of the lenslet pitch")
    if args.focal_point_f_number is not None:
        _number("--focal-point-f-number", args.focal_point_f_number, minimum=0, open_min=True)
    if args.method in ("magnification", "both") and (args.ruler is None or
                                                      args.ruler_spacing_mm is None):
        raise ConfigError(f"--method {args.method} needs --ruler IMG and --ruler-spacing-mm")
    cam = load_camera(args.camera)
    check_sensor(cam)
    inputs = _input_files(args.camera, args.focal_point, args.alignment, args.ruler,
                          args.white)
    out = _check_out(args.out, (".h5",), inputs=inputs,
                     beside=() if args.no_report else (".png",))
    t0 = time.perf_counter()
    progress = _StageBar("calibrate", {"read images": 5, "spots and S_i": 75, "report": 20},
                         args.quiet or args.json)
    progress("read images")
    fp = read_image(args.focal_point)
    al = None if args.alignment is None else read_image(args.alignment)
    ru = None if args.ruler is None else read_image(args.ruler)
    wh = None if args.white is None else read_image(args.white)
    progress("spots and S_i")
    report = calibrate(cam, fp, alignment_image=al, ruler_image=ru, white_image=wh,
                       ruler_spacing=(None if args.ruler_spacing_mm is None
                                      else args.ruler_spacing_mm * 1e-3),
                       ruler_axis=args.ruler_axis, method=args.method,
                       fit_misplacement=not args.no_misplacement,
                       max_missing_fraction=args.max_missing_fraction,
                       max_rms_residual_pitch=args.max_rms_residual_pitch,
                       spot_method=args.spot_method,
                       focal_point_f_number=args.focal_point_f_number)
    progress("report")
    inputs = {"focal_point": args.focal_point, "alignment": args.alignment,
              "ruler": args.ruler, "ruler_spacing_mm": args.ruler_spacing_mm,
              "white": args.white,
              "method": args.method}
    report.calibration.save(out, config={"inputs": inputs, "summary": report.summary()})
    summary = {"command": "calibrate", "out": str(out), **report.summary()}
    if not args.no_report:
        from plenopiv.plots import calibration_report

        png = out.with_suffix(".png")
        calibration_report(report, fp, png)
        summary["report"] = str(png)
    progress.close()
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary


# ---- reconstruct ---------------------------------------------------------------------------


def cmd_reconstruct(args) -> dict:
    """Reconstruct one image into a volume with its particle table."""
    from plenopiv.config import load_experiment
    from plenopiv.io import read_image
    from plenopiv.pipeline import experiment_calibration, reconstruct_volume
    from plenopiv.resources import check_grid

    exp = load_experiment(args.config)
    inputs = _input_files(args.calibration, args.image, args.config)
    out = _check_out(args.out, (".h5",), inputs=inputs,
                     beside=(".png",) if exp.output.png else ())
    cal = experiment_calibration(exp, args.calibration)
    check_grid(exp.volume)
    img = read_image(args.image)
    t0 = time.perf_counter()
    from plenopiv.masks import image_mask

    stages = {"weights": 30, "mart": 60, "particles": 10}
    with _StageBar("reconstruct", stages, args.quiet or args.json) as progress:
        cache = exp.output.weights_cache
        res = reconstruct_volume(cal, img, exp.volume, settings=exp.reconstruction,
                                 particles=exp.particles, progress=progress,
                                 cache_dir=(exp.path(cache) if cache else None),
                                 image_mask=image_mask(exp.mask, cal.camera.sensor.shape,
                                                       exp.base_dir))
    res.save(out, config={**exp.to_dict(), "calibration": str(args.calibration),
                          "image": str(args.image)})
    summary = {"command": "reconstruct", "out": str(out), "shape": list(res.volume.shape),
               "n_particles": len(res.particle_position),
               "depth_correction": res.correction.to_dict(),
               "image_distance_mm": cal.image_distance * 1e3,
               "timings_s": {k: round(v, 3) for k, v in res.timings.items()}}
    if exp.output.png:
        from plenopiv.plots import volume_slices

        png = out.with_suffix(".png")
        volume_slices(res.volume, res.grid.x, res.grid.y, res.grid.z, png,
                      particles=res.particle_position_effective,
                      title=f"{Path(str(args.image)).name}: {len(res.particle_position)} particles")
        summary["png"] = str(png)
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary


# ---- piv -------------------------------------------------------------------------------------


def cmd_piv(args) -> dict:
    """Cross-correlate two volume products into a vector field."""
    from plenopiv.config import MAX_WINDOW_VOX, PIVConfig
    from plenopiv.pipeline import correlate, load_volume, piv_settings
    from plenopiv.piv import MIN_WINDOW_VOX

    _number("--dt", args.dt, minimum=0, open_min=True, unit="seconds between the exposures")
    for w in args.windows or ():
        if min(w) < MIN_WINDOW_VOX or max(w) > MAX_WINDOW_VOX:
            raise ConfigError(f"--windows {' '.join(map(str, w))}: expected three window edges "
                              f"WZ WY WX of {MIN_WINDOW_VOX} to {MAX_WINDOW_VOX} voxels")
    inputs = _input_files(args.volume_a, args.volume_b, args.config)
    beside = (() if args.no_vtk else (".vti",)) + (() if args.no_png else (".png",))
    out = _check_out(args.out, (".h5",), inputs=inputs, beside=beside)
    exp = None if args.config is None else _experiment(args.config)
    cfg = PIVConfig() if exp is None else exp.piv
    if args.windows:
        cfg = cfg.model_copy(update={"windows": [tuple(w) for w in args.windows]})
    if args.replacement:
        cfg = cfg.model_copy(update={"replacement": args.replacement})
    settings = piv_settings(cfg)
    t0 = time.perf_counter()
    va, vb = load_volume(args.volume_a), load_volume(args.volume_b)
    mask = None
    if exp is not None:
        from plenopiv.masks import volume_mask

        mask = volume_mask(exp.mask, va.grid, exp.base_dir)
    # without the calibration and images there is no round trip: correlation statistics only
    with _StageBar("piv", {"piv": 1}, args.quiet or args.json) as bar:
        bar("piv")
        vec = correlate(va, vb, settings, dt=args.dt, mask=mask, progress=lambda info: bar(
            f"piv pass {info['pass']}/{info['passes']}", info["pass"] / info["passes"]))
    files = vec.save(out, config={"piv": cfg.model_dump(), "volume_a": str(args.volume_a),
                                  "volume_b": str(args.volume_b), "dt_s": args.dt},
                     vtk=not args.no_vtk, extra_attrs={"complete": True})
    summary = {"command": "piv", "out": str(out), "shape": list(vec.u.shape),
               "valid_fraction": float(np.mean(vec.valid)), "n_replaced": vec.n_replaced,
               "quantity": "displacement" if args.dt is None else "velocity",
               "uncertainty_method": vec.uncertainty_method,
               "files": [str(f) for f in files]}
    if not args.no_png:
        from plenopiv.plots import vector_slices

        title = f"{Path(args.volume_a).name} -> {Path(args.volume_b).name}"
        summary["png"] = str(vector_slices(vec, out.with_suffix(".png"), title=title))
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary


def cmd_track(args) -> dict:
    """Particle tracks of one pair: ray-bundle positions matched with the PIV predictor."""
    from plenopiv.config import load_experiment
    from plenopiv.io import read_image
    from plenopiv.pipeline import experiment_calibration, load_volume
    from plenopiv.tracking.pair import track_images
    from plenopiv.tracking.products import load_vectors, save_track_products

    out = _check_out(args.out, (".h5",))
    exp = load_experiment(args.config)
    cal = experiment_calibration(exp, args.calibration)
    ia, ib = read_image(args.image_a), read_image(args.image_b)
    t0 = time.perf_counter()
    va = load_volume(args.volume_a) if args.volume_a else None
    vb = load_volume(args.volume_b) if args.volume_b else None
    vec = load_vectors(args.vectors) if args.vectors else None
    tracks, va, vb, vec, timings = track_images(cal, ia, ib, exp, volume_a=va, volume_b=vb,
                                                vectors=vec)
    cfg = {**exp.to_dict(), "calibration": str(args.calibration),
           "image_a": str(args.image_a), "image_b": str(args.image_b)}
    paths = save_track_products(tracks, vec, out, config=cfg, vtk=exp.output.vtk)
    d = tracks.displacement
    return {"command": "track", "out": str(out), "n_tracks": len(tracks),
            "n_particles_a": len(va.particle_position), "n_particles_b": len(vb.particle_position),
            "counts": tracks.counts, "dt_s": tracks.dt,
            "median_uncertainty_m": (np.median(tracks.uncertainty, axis=0).tolist()
                                     if len(tracks) else None),
            "max_displacement_m": np.abs(d).max(axis=0).tolist() if len(d) else None,
            "files": paths, "timings_s": {k: round(v, 3) for k, v in timings.items()},
            "seconds": round(time.perf_counter() - t0, 3)}


def _experiment(path):
    from plenopiv.config import load_experiment

    return load_experiment(path)


# ---- plan ------------------------------------------------------------------------------------


def _box_from_args(args, cam) -> dict | None:
    """A ``[volume]`` table from --x-mm/--y-mm/--z-mm/--voxel-mm (None when none is given)."""
    given = {k: getattr(args, k) for k in ("x_mm", "y_mm", "z_mm", "voxel_mm")}
    if all(v is None for v in given.values()):
        return None
    return {k: (list(v) if k != "voxel_mm" or len(v) > 1 else v[0])
            for k, v in given.items() if v is not None}


def cmd_plan(args) -> dict:
    """Resolution, recommended voxels and windows, size, memory and time of a reconstruction."""
    from plenopiv import planning
    from plenopiv.camera import read_toml
    from plenopiv.config import PIVConfig, ReconstructionSettings, experiment_from_dict
    from plenopiv.volume import volume_from_dict

    path = Path(args.config)
    table = read_toml(path, "config") if path.suffix.lower() == ".toml" else {}
    is_experiment = "volume" in table or "camera" in table
    box = _box_from_args(args, None)
    if is_experiment:
        cfg = dict(table)
        if box is not None:
            volume = dict(cfg.get("volume", {}))
            if "voxel_mm" in box:
                volume.pop("shape", None)
            volume.update(box)
            cfg["volume"] = volume
        exp = experiment_from_dict(cfg, base_dir=path.parent, source=str(path))
        camera, grid = exp.camera, exp.volume
        recon, piv_cfg = exp.reconstruction, exp.piv
        calibration = args.calibration or (exp.path(exp.images.calibration)
                                           if exp.images.calibration else None)
        if calibration is not None and not Path(calibration).exists():
            calibration = args.calibration      # not made yet: the camera's S_i then
    else:
        camera = load_camera(args.config)
        recon, piv_cfg = ReconstructionSettings(), PIVConfig()
        calibration = args.calibration
        grid = None
    if args.f_number is not None:
        recon = recon.model_copy(update={"f_number": args.f_number})
    if args.windows:
        piv_cfg = piv_cfg.model_copy(update={"windows": [tuple(w) for w in args.windows]})
    if args.image_distance_mm is not None:
        camera = camera.with_image_distance(args.image_distance_mm * 1e-3)
    elif calibration is not None:
        from plenopiv.calibration.model import Calibration

        camera = camera.with_image_distance(Calibration.load(calibration).image_distance)
    if grid is None:
        cam = planning.camera_resolution(camera, recon.f_number)
        fx, fy = (0.9 * v * 1e3 for v in cam.field_of_view)
        dz = 4 * cam.depth_cell * 1e3
        vox = [v * 1e3 for v in planning.recommended_voxel(cam)]
        default = {"x_mm": [-fx, fx], "y_mm": [-fy, fy], "z_mm": [-dz, dz], "voxel_mm": vox}
        grid = volume_from_dict({**default, **(box or {})}, source="plan options")
        if args.windows is None:
            piv_cfg = piv_cfg.model_copy(update={
                "windows": list(planning.recommended_windows(cam, grid.voxel))})
    t0 = time.perf_counter()
    if args.no_measure:
        rates = planning.BENCHMARK_RATES
    else:
        with _StageBar("plan", {"measure": 1}, args.quiet or args.json) as bar:
            bar("measure rates on this machine")
            rates = planning.measure_rates(camera, grid, f_number=recon.f_number,
                                           min_lit=recon.min_lit, piv=piv_cfg)
    result = planning.plan(camera, grid, reconstruction=recon, piv=piv_cfg, rates=rates)
    return {"command": "plan", "config": str(args.config),
            "kind": "experiment" if is_experiment else "camera", **result.to_dict(),
            "seconds": round(time.perf_counter() - t0, 3)}


def _print_plan(p: dict) -> None:
    """``plenopiv plan`` for people."""
    def mm(v):
        return _fmt(float(v))

    def box(b):
        return f"[{mm(b[0])}, {mm(b[1])}]"

    vol, rec, cell = p["volume"], p["recommended"], p["resolution_cell_mm"]
    fov = p["field_of_view_mm"]
    vx, vy, vz = vol["voxel_mm"]
    nz, ny, nx = vol["shape"]
    rows = [
        ("camera", f"{p['camera']}, f/{_fmt(p['f_number'])}"),
        ("resolution cell", f"{mm(cell['lateral'])} mm laterally (one lenslet footprint), "
                            f"{mm(cell['depth'])} mm in depth"),
        ("near-focus zone", f"|Z| < {mm(p['near_focus_mm'][1])} mm: a particle there lights "
                            "one lenslet, so depth motion is under-measured"),
        ("field of view", f"x ±{mm(fov['x'][1])} mm, y ±{mm(fov['y'][1])} mm at the focal "
                          "plane"),
        ("volume", f"x {box(vol['x_mm'])}, y {box(vol['y_mm'])}, z {box(vol['z_mm'])} mm; "
                   f"voxel {mm(vx)} x {mm(vy)} x {mm(vz)} mm"),
        ("", f"{nx} x {ny} x {nz} voxels (x, y, z) = {p['n_voxels']:,}"),
        ("PIV windows", " then ".join(str(w) for w in p["windows_vox"])
         + f" voxels (z, y, x), {p['passes']} passes, overlap {_fmt(p['overlap'])}"),
    ]
    last = p["windows_vox"][-1]
    rows.append(("", f"last window {mm(last[2] * vx)} x {mm(last[1] * vy)} x "
                     f"{mm(last[0] * vz)} mm (x, y, z): flow structures smaller than this "
                     "are smoothed"))
    vec = p["vectors_per_pass"]
    rows.append(("", "vectors per pass (z, y, x): " + ", ".join(str(v) for v in vec)
                 + ("" if p["windows_fit"] else "  <- the windows do not fit")))
    rv = rec["voxel_mm"]
    rows.append(("recommended", f"voxel {mm(rv[0])} x {mm(rv[1])} x {mm(rv[2])} mm "
                                "(half a footprint; a quarter of the depth cell), windows "
                                + " then ".join(str(w) for w in rec["windows_vox"])))
    rows.append(("", f"{' x '.join(str(n) for n in rec['shape'][::-1])} voxels (x, y, z); "
                     f"last pass {rec['vectors_last_pass']} vectors (z, y, x); seed about "
                     f"{_fmt(rec['particles_per_lenslet'])} particles per lenslet (the "
                     "validated density)"))
    def count(n):
        return f"{n / 1e9:.3g} billion" if n >= 1e9 else f"{n / 1e6:.3g} million"

    sparse = p["projector"] == "sparse"
    rows.append(("size", f"{count(p['n_rays'])} rays, {count(p['nnz'])} non-zero weights; "
                         + ("explicit (sparse) weights" if sparse else
                            "matrix-free lattice projector (the explicit weights would not "
                            "fit)")))
    mem = p["memory_gb"]
    rows.append(("memory", (f"weights {_fmt(mem['weights'])} GB (a cache file of "
                            f"{_fmt(mem['weights_cache_file'])} GB on disk), " if sparse else "")
                 + f"peak {_fmt(mem['peak'])} GB of this machine's "
                   f"{_fmt(p['available_memory_gb'])} GB"))
    t = p["time_s"]
    rows.append(("time", f"weights {_fmt(t['weights'])} s"
                         + (" (once, then cached)" if sparse else "") + ", one volume "
                         f"{_fmt(t['volume'])} s, PIV {_fmt(t['piv'])} s; a pair "
                         f"{_fmt(t['pair'])} s ({_fmt(t['pair_cached_weights'])} s with cached "
                         "weights)"))
    rows.append(("", f"time model: {p['time_model']}"))
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k.ljust(width)}  {v}")
    for title in ("warnings", "advice"):
        if p[title]:
            print(f"{title}:")
            for line in p[title]:
                print(f"  - {line}")
    if p["advice"] or p["warnings"]:
        print("recommended [volume] and [piv] for this box:")
        for line in rec["toml"].splitlines():
            print(f"  {line}" if line else "")


# ---- validate --------------------------------------------------------------------------------


def cmd_validate(args) -> dict:
    """Studies that reproduce the thesis's figures and validate the whole chain."""
    _seed(args.seed)
    _number("--particles-per-lenslet", args.particles_per_lenslet, minimum=0, open_min=True,
            maximum=100)
    _integer("--lateral-oversampling", args.lateral_oversampling, minimum=1, maximum=16)
    for flag, n in zip(("--lenslets ROWS", "--lenslets COLS"), args.lenslets or (), strict=False):
        _integer(flag, n, minimum=1, maximum=100_000)
    check_output_path(args.out, what="--out", folder=True)
    t0 = time.perf_counter()
    case = args.case
    if case in ("oseen", "hill"):
        from plenopiv.validation.vortex import VortexCase, run_case

        s = run_case(VortexCase(flow=case, camera=args.camera, seed=args.seed,
                                particles_per_lenslet=args.particles_per_lenslet,
                                lenslets=None if args.lenslets is None else tuple(args.lenslets),
                                lateral_oversampling=args.lateral_oversampling,
                                blur_px=args.blur_px,
                                depth_centre=args.depth_centre_mm * 1e-3), args.out)
        out = {"errors": s["errors"], "n_particles": s["n_particles"],
               "grid_shape": s["grid_shape"], "voxel_mm": s["voxel_mm"],
               "timings_s": s["timings_s"], "products": s["products"]}
    elif case == "calibration":
        from plenopiv.validation.calibration_study import run

        out = run(args.out)
    elif case == "letters":
        from plenopiv.validation.letters import find_data_dir, run

        try:
            data = find_data_dir(args.data)
        except FileNotFoundError as exc:
            raise ConfigError(str(exc)) from None
        out = run(args.out, data_dir=data)
    elif case == "depth":
        from plenopiv.validation.depth_study import run

        out = run(args.out)
    elif case == "vortex":
        from plenopiv.validation.vortex_study import run

        out = run(args.out, progress=lambda _msg: None)
    elif case == "fields":
        from plenopiv.validation.field_quality import run

        out = run(args.out)
    elif case == "uncertainty":
        from plenopiv.validation.uncertainty_study import run

        out = run(args.out, progress=lambda _msg: None)
    else:  # argparse restricts the choices
        raise ConfigError(f"validate {case!r}: unknown case")
    return {"command": f"validate {case}", "out": str(args.out), **out,
            "seconds": round(time.perf_counter() - t0, 3)}


# ---- run ---------------------------------------------------------------------------------


def cmd_run(args) -> dict:
    """Many pairs end to end on dask (local processes, SLURM, or a running scheduler)."""
    from plenopiv.batch import (
        BatchInterrupted,
        batch_options,
        check_batch_options,
        discover_pairs,
        run_batch,
    )
    from plenopiv.config import load_experiment
    from plenopiv.errors import ComputationError
    from plenopiv.pipeline import ExperimentPairProcess, experiment_calibration, prepare_weights
    from plenopiv.resources import check_grid

    _integer("--workers", args.workers, minimum=1, maximum=4096)
    exp = load_experiment(args.experiment)
    opts = batch_options(exp.batch.model_dump())
    if args.cluster is not None:
        opts["cluster"] = args.cluster
    if args.workers is not None:
        opts["n_workers"] = args.workers
    check_batch_options(**opts)
    im = exp.images
    if im.calibration is None:
        raise ConfigError(f"{args.experiment}: [images] calibration is not set: expected the "
                          "calibration product (.h5) of plenopiv calibrate")
    if (im.a is None or im.b is None) and im.pairs is None:
        raise ConfigError(f"{args.experiment}: [images] needs a and b (glob patterns of the "
                          "two exposures) or pairs (HDF5 files with /image_a and /image_b)")
    out_dir = exp.path(exp.output.directory)
    check_output_path(out_dir, what="[output] directory", folder=True)
    if im.pairs is not None:
        jobs = discover_pairs(im.pairs, out_dir=out_dir, root=exp.base_dir,
                              output_name="{name}_vectors.h5")
    else:
        jobs = discover_pairs(im.a, im.b, out_dir=out_dir, root=exp.base_dir,
                              output_name="{name}_vectors.h5", pair_by=im.pair_by)
    cal_path = exp.path(im.calibration)
    _check_products_spare_inputs(jobs, [args.experiment, cal_path])
    cal = experiment_calibration(exp, cal_path)
    check_grid(exp.volume)
    jobs = _with_identities(jobs, exp, cal_path)
    # explicit weights go into the weights cache once, before the workers start; each worker
    # then makes its projector once, for all its pairs
    hit, weights_s = prepare_weights(exp, cal)
    process = ExperimentPairProcess(str(Path(args.experiment).resolve()), str(cal_path.resolve()),
                                    str(out_dir))
    head = {"command": "run", "out": str(out_dir), "weights_from_cache": hit}
    try:
        summary = run_batch(jobs, process, resume=args.resume,
                            progress=not (args.quiet or args.json), **opts)
    except BatchInterrupted as exc:
        exc.summary = {**head, **exc.summary}
        raise
    result = {**head, "weights_s": round(weights_s, 3) if not hit else 0.0,
              **summary.to_dict()}
    if summary.failed:
        names = ", ".join(f"{n} ({e})" for n, e in summary.failed[:3])
        more = "" if len(summary.failed) <= 3 else f" and {len(summary.failed) - 3} more"
        err = ComputationError(f"{len(summary.failed)} of {summary.n_jobs} pairs failed: "
                               f"{names}{more}; see {summary.summary_path}")
        err.summary = result
        raise err
    return result


def _check_products_spare_inputs(jobs, others) -> None:
    """No file a pair writes (vectors, volumes, .vti, PNGs) may be one of the batch's inputs
    (an image, the experiment file, the calibration)."""
    from plenopiv.io import split_dataset_spec

    inputs = {split_dataset_spec(p)[0].resolve() for j in jobs for p in (j.image_a, j.image_b)}
    inputs |= {Path(p).resolve() for p in others}
    for j in jobs:
        folder, name = j.output.parent, j.name
        for f in (j.output, folder / f"{name}_volume_A.h5", folder / f"{name}_volume_B.h5",
                  j.output.with_suffix(".vti"), folder / f"{name}_volume_A.png",
                  folder / f"{name}_vectors.png"):
            if f.resolve() in inputs:
                raise ConfigError(f"pair {name!r} would write {str(f)!r}, which is one of the "
                                  "batch's inputs; choose another [output] directory")


def _with_identities(jobs, exp, cal_path):
    """Give each job the identity of what makes its product: the experiment's settings, the
    calibration file and the two images (content hashes); resume recomputes a product made
    from anything else."""
    from dataclasses import replace

    from plenopiv.io import file_identity
    from plenopiv.pipeline import settings_identity

    common = {"settings": settings_identity(exp), "calibration": file_identity(cal_path)}
    return [replace(j, identity={**common, "image_a": file_identity(j.image_a),
                                 "image_b": file_identity(j.image_b)}) for j in jobs]


# ---- demo ----------------------------------------------------------------------------------


def cmd_demo(args) -> dict:
    """The built-in synthetic case end to end: calibration images -> calibration -> a
    Lamb-Oseen vortex pair -> two volumes -> 3-D PIV -> errors against the truth."""
    from plenopiv.validation.vortex import VortexCase, run_case

    _seed(args.seed)
    check_output_path(args.out, what="--out", folder=True)
    stages = {"calibration images": 12, "calibrate": 10, "simulate pair": 6, "weights": 14,
              "volume A": 12, "volume B": 12, "piv": 12, "products": 22}
    with _StageBar("demo", stages, args.quiet or args.json) as progress:
        s = run_case(VortexCase(flow="oseen", seed=args.seed), args.out, progress=progress)
    e = s["errors"]
    return {"command": "demo", "out": str(args.out), "camera": s["case"]["camera"],
            "image_distance_mm": s["calibration"]["image_distance_mm"],
            "n_particles": s["n_particles"], "grid_shape": s["grid_shape"],
            "valid_fraction": e["valid_fraction"], "gain": e["gain"],
            "rms_error_vox": e["rms_vox"], "bias_vox": e["bias_vox"],
            "by_depth": [{k: b[k] for k in ("abs_z_mm", "n_vectors", "gain", "bias_vox",
                                            "rms_vox")} for b in e["by_depth"]],
            "seconds": s["timings_s"]["total_s"], "products": s["products"]}


# ---- parser --------------------------------------------------------------------------------


def _add_common(p: argparse.ArgumentParser):
    p.add_argument("--json", action="store_true", help="print a one-object JSON summary")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_image_options(p: argparse.ArgumentParser):
    p.add_argument("--noise", choices=("none", "poisson"), default="none",
                   help="photon (Poisson) noise, default none")
    p.add_argument("--bit-depth", type=int, choices=(0, 8, 16), default=16,
                   help="integer quantisation; 0 writes float32 irradiance (default 16)")
    p.add_argument("--blur-px", type=float, default=0.0,
                   help="Gaussian blur sigma in pixels (default 0)")
    p.add_argument("--full-well", type=float, default=20000.0,
                   help="electrons at full scale, for photon noise (default 20000)")
    p.add_argument("--read-noise", type=float, default=0.0, help="read noise, counts (default 0)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")


class UsageError(PlenopivError):
    """A command line that argparse rejects (unknown option, missing or malformed value)."""


#: Negative numbers as option values: argparse's own pattern misses ``-1e-3`` and ``-inf``.
_NEGATIVE_NUMBER = re.compile(r"^-(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?$|^-(?:inf|infinity|nan)$",
                              re.IGNORECASE)


class _Parser(argparse.ArgumentParser):
    """argparse with plenopiv's error path: a usage error raises :class:`UsageError` (one
    ``error:`` line, exit 2, JSON with ``--json``) instead of exiting; ``-1e-3`` is a value."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NEGATIVE_NUMBER

    def error(self, message):
        raise UsageError(f"{self.prog}: {message} (see {self.prog} --help)")


def build_parser() -> argparse.ArgumentParser:
    """The ``plenopiv`` argument parser."""
    parser = _Parser(
        prog="plenopiv", description="Tomographic plenoptic PIV: simulate, calibrate, "
        "reconstruct and correlate.")
    parser.add_argument("--version", action="version", version=f"plenopiv {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run the built-in synthetic case end to end")
    demo.add_argument("--out", default="demo_out", help="output folder (default demo_out)")
    demo.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    _add_common(demo)
    demo.set_defaults(func=cmd_demo)

    cal = sub.add_parser("calibrate", help="lenslet centres, focal spots and the image distance")
    cal.add_argument("camera", help="camera TOML file or preset name")
    cal.add_argument("--focal-point", required=True, metavar="IMG",
                     help="focal-point image (white sheet, stopped-down lens)")
    cal.add_argument("--focal-point-f-number", type=float, metavar="N",
                     help="stop of the focal-point image (e.g. 16): fit the spots' centroids "
                          "over it, not their chief rays (they differ through a plate)")
    cal.add_argument("--alignment", metavar="IMG",
                     help="alignment image (collimated light); default: the nominal lattice")
    cal.add_argument("--ruler", metavar="IMG", help="ruler image on the nominal focal plane")
    cal.add_argument("--white", metavar="IMG",
                     help="white image at the working aperture: checks the camera's f_number "
                          "against its micro-image size")
    cal.add_argument("--ruler-spacing-mm", type=float, help="ruler tick spacing (mm)")
    cal.add_argument("--ruler-axis", choices=("x", "y"), default="x",
                     help="direction along which the ticks repeat (default x, along columns)")
    cal.add_argument("--method", choices=("focal-point", "magnification", "both"),
                     default="focal-point", help="which S_i to keep (default focal-point)")
    cal.add_argument("--no-misplacement", action="store_true",
                     help="fit S_i only, not the MLA offset and rotation")
    cal.add_argument("--max-missing-fraction", type=float, default=0.05,
                     help="more missing spots than this fraction of the lattice is an error "
                          "(default 0.05)")
    cal.add_argument("--max-rms-residual-pitch", type=float, default=0.015,
                     help="refuse an image whose spots fit their lattice worse than this "
                          "fraction of the pitch, rms (default 0.015)")
    cal.add_argument("--spot-method", choices=("auto", "window", "centroid", "gaussian"),
                     default="auto", help="spot-centre estimator (default auto: the window "
                     "centroid for focal-point and alignment spots)")
    cal.add_argument("--no-report", action="store_true", help="no PNG report beside --out")
    cal.add_argument("--out", required=True, help="calibration product (.h5)")
    _add_common(cal)
    cal.set_defaults(func=cmd_calibrate)

    rec = sub.add_parser("reconstruct", help="MART volume and particles from one image")
    rec.add_argument("calibration", help="calibration product (.h5) from plenopiv calibrate")
    rec.add_argument("image", help="raw image: TIFF, PNG or file.h5:/dataset")
    rec.add_argument("--config", required=True, help="experiment TOML ([volume], ...)")
    rec.add_argument("--out", required=True, help="volume product (.h5)")
    _add_common(rec)
    rec.set_defaults(func=cmd_reconstruct)

    piv = sub.add_parser("piv", help="3-D cross-correlation of two volume products")
    piv.add_argument("volume_a", help="first volume (.h5 from plenopiv reconstruct)")
    piv.add_argument("volume_b", help="second volume, same grid")
    piv.add_argument("--out", required=True, help="vectors product (.h5); .vti and .png beside")
    piv.add_argument("--dt", type=float, default=None,
                     help="seconds between the exposures: store velocity (m/s)")
    piv.add_argument("--config", help="experiment TOML whose [piv] table to use")
    piv.add_argument("--windows", type=int, nargs=3, action="append", metavar=("WZ", "WY", "WX"),
                     help="window per pass in voxels (repeat for several passes)")
    piv.add_argument("--replacement", choices=("median", "mean", "none"), default=None,
                     help="rejected vectors: replaced by the local median or mean, or left NaN "
                          "(default: [piv] replacement of --config, else median)")
    piv.add_argument("--no-vtk", action="store_true", help="no .vti file for ParaView")
    piv.add_argument("--no-png", action="store_true", help="no PNG of vector slices")
    _add_common(piv)
    piv.set_defaults(func=cmd_piv)

    trk = sub.add_parser("track", help="particle tracks of one pair (ray bundles + PIV predictor)")
    trk.add_argument("calibration", help="calibration product (.h5) from plenopiv calibrate")
    trk.add_argument("image_a", help="first exposure: TIFF, PNG or file.h5:/dataset")
    trk.add_argument("image_b", help="second exposure")
    trk.add_argument("--config", required=True, help="experiment TOML ([volume], [tracking], ...)")
    trk.add_argument("--out", required=True,
                     help="tracks product (.h5); .vtp and _binned.h5 beside it")
    trk.add_argument("--volume-a", help="reuse this volume product of image A (.h5)")
    trk.add_argument("--volume-b", help="reuse this volume product of image B (.h5)")
    trk.add_argument("--vectors", help="reuse this vectors product of the pair (.h5)")
    _add_common(trk)
    trk.set_defaults(func=cmd_track)

    plan = sub.add_parser(
        "plan", help="resolution, recommended voxels and windows, memory and time of a "
                     "reconstruction, before running it")
    plan.add_argument("config", help="experiment TOML (camera + [volume]), or a camera TOML "
                                     "or preset name with the box given by --x-mm ...")
    for axis in ("x", "y", "z"):
        plan.add_argument(f"--{axis}-mm", type=float, nargs=2, metavar=("LO", "HI"),
                          help=f"box along {axis} (mm; replaces the experiment's; default for "
                               "a camera: " + ("90 %% of the field of view)" if axis != "z"
                                               else "±4 depth cells)"))
    plan.add_argument("--voxel-mm", type=float, nargs="+", metavar="MM",
                      help="voxel edge, one value or DX DY DZ (mm; default for a camera: the "
                           "recommended voxel)")
    plan.add_argument("--windows", type=int, nargs=3, action="append", metavar=("WZ", "WY", "WX"),
                      help="PIV window per pass in voxels (repeat for several passes)")
    plan.add_argument("--f-number", type=float, help="aperture of the recording (default: the "
                                                     "camera's or [reconstruction] f_number)")
    plan.add_argument("--image-distance-mm", type=float,
                      help="effective S_i (mm) when the camera file does not give it")
    plan.add_argument("--calibration", metavar="CAL.h5",
                      help="take S_i from this calibration product")
    plan.add_argument("--no-measure", action="store_true",
                      help="estimate times from the benchmark figures instead of timing the "
                           "kernels here (no numba compilation)")
    _add_common(plan)
    plan.set_defaults(func=cmd_plan)

    run = sub.add_parser("run", help="many image pairs end to end (dask batch)")
    run.add_argument("experiment", help="experiment TOML with [images], [batch], [output]")
    run.add_argument("--resume", action=argparse.BooleanOptionalAction, default=True,
                     help="skip pairs whose product is complete (default; --no-resume redoes all)")
    run.add_argument("--cluster", help="local | slurm | tcp://scheduler:8786 (default [batch])")
    run.add_argument("--workers", type=int, help="worker processes (default: [batch] or cores)")
    _add_common(run)
    run.set_defaults(func=cmd_run)

    val = sub.add_parser("validate", help="validation studies (thesis figures, vortex flows)")
    val.add_argument("case", choices=("oseen", "hill", "vortex", "calibration", "depth",
                                      "fields", "letters", "uncertainty"),
                     help="oseen/hill: whole chain on a vortex; vortex: both against flow "
                          "size and voxel; calibration: Figs 3.8, 3.9, 5.5; depth: Tables "
                          "5.1, 5.2; fields: particle-field quality; letters: light field on "
                          "the real plenoptomos image; uncertainty: coverage of the per-vector "
                          "uncertainty on the vortex flows")
    val.add_argument("--out", required=True, help="output folder")
    val.add_argument("--data", metavar="DIR",
                     help="letters: the third-party data folder holding "
                          "plenoptomos_letters_ULF/ (default: $PLENOPIV_DATA, else "
                          "../shared/data beside the current folder or the source tree)")
    val.add_argument("--camera", default="small_m1",
                     help="oseen/hill: camera preset or TOML (default small_m1)")
    val.add_argument("--particles-per-lenslet", type=float, default=0.15,
                     help="oseen/hill: seeding density (default 0.15)")
    val.add_argument("--lenslets", type=int, nargs=2, metavar=("ROWS", "COLS"),
                     help="oseen/hill: run on the central ROWS x COLS lenslets of the camera")
    val.add_argument("--lateral-oversampling", type=int, default=1, metavar="K",
                     help="oseen/hill: lateral voxels per lenslet footprint (default 1)")
    val.add_argument("--blur-px", type=float, default=0.0,
                     help="oseen/hill: Gaussian point spread of the renders, pixels (default 0)")
    val.add_argument("--depth-centre-mm", type=float, default=0.0,
                     help="oseen/hill: Z of the volume's centre, mm (default 0: on the focal "
                          "plane)")
    val.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    _add_common(val)
    val.set_defaults(func=cmd_validate)

    sim = sub.add_parser("simulate", help="render synthetic plenoptic images by ray tracing")
    simsub = sim.add_subparsers(dest="kind", required=True)
    presets = ", ".join(preset_names())
    for kind, helptext in (("focal-point", "white sheet through the stopped-down lens"),
                           ("alignment", "collimated light, main lens removed"),
                           ("ruler", "a ruler with ticks on a plane at a given depth"),
                           ("particles", "random point particles"),
                           ("pair", "a particle image pair moved by a flow, with ground truth")):
        p = simsub.add_parser(kind, help=helptext)
        p.add_argument("camera", help=f"camera TOML file or preset name ({presets})")
        p.add_argument("--out", required=True, help="output file (.tif, .png; .h5 for pairs)")
        p.add_argument("--image-distance-mm", type=float, default=None,
                       help="override [main_lens] image_distance_mm (effective S_i)")
        p.add_argument("--f-number", type=float, default=None,
                       help="stop for this image (default: the camera's f_number)")
        if kind != "pair":
            p.add_argument("--splat", choices=("bilinear", "pixel"), default="bilinear",
                           help="a ray's energy shared by area among the 4 nearest pixel "
                                "centres (default), or all into the pixel it hits")
            p.add_argument("--psf-px", type=float, default=0.0,
                           help="Gaussian point-spread sigma before the pixels integrate, "
                                "pixels (default 0)")
            p.add_argument("--sensor-shift-px", type=float, nargs=2, default=(0.0, 0.0),
                           metavar=("DROW", "DCOL"),
                           help="shift the image content by a (sub-)pixel amount (default 0 0)")
            p.add_argument("--lenslets", type=int, nargs=2, metavar=("ROWS", "COLS"),
                           help="render the central ROWS x COLS lenslets of the camera, on a "
                                "sensor cut to them (odd counts put a lenslet on the axis)")
        _add_image_options(p)
        _add_common(p)
        p.set_defaults(func=cmd_simulate)
        if kind == "ruler":
            p.add_argument("--spacing-mm", type=float, default=1.0, help="tick spacing (mm)")
            p.add_argument("--tick-width-mm", type=float, default=0.15, help="tick width (mm)")
            p.add_argument("--depth-mm", type=float, default=0.0,
                           help="ruler plane depth Z from the focal plane (mm, default 0)")
            p.add_argument("--rays-per-lenslet", type=int, default=2000,
                           help="rays per lenslet footprint (default 2000)")
        if kind in ("particles", "pair"):
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
        if kind == "pair":
            p.add_argument("--flow", choices=("uniform", "oseen", "hill"), default="oseen",
                           help="flow moving the particles (default oseen, axis along Y)")
            p.add_argument("--dt", type=float, default=1e-3, help="time between exposures (s)")
            p.add_argument("--max-displacement-mm", type=float, default=0.5,
                           help="largest particle displacement of the flow (mm, default 0.5)")
            p.add_argument("--no-tiff", action="store_true",
                           help="write only the HDF5 file (no A/B TIFFs beside it)")
    return parser


def _fmt(value) -> str:
    """A value for people: numbers to 4 significant digits, numpy scalars as numbers, lists
    and small dicts on one line."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, bool) or value is None:
        return str(value).lower() if isinstance(value, bool) else "-"
    if isinstance(value, float):
        if not math.isfinite(value):
            return str(value)
        if value != 0 and (abs(value) >= 1e6 or abs(value) < 1e-3):
            return f"{value:.3e}"
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    if isinstance(value, dict):
        return ", ".join(f"{k} {_fmt(v)}" for k, v in value.items())
    return str(value)


def _print_lines(summary: dict, indent: str = "") -> None:
    """``key: value`` lines; a dict of dicts or lists of dicts as an indented block."""
    for k, v in summary.items():
        if isinstance(v, dict) and (any(isinstance(x, (dict, list)) for x in v.values())
                                    or len(_fmt(v)) > 90):
            print(f"{indent}{k}:")
            _print_lines(v, indent + "  ")
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            print(f"{indent}{k}:")
            for x in v:
                print(f"{indent}  - {_fmt(x)}")
        else:
            print(f"{indent}{k}: {_fmt(v)}")


def _print_run(s: dict) -> None:
    """``plenopiv run``: one row per pair, then the totals."""
    rows = [("pair", "status", "valid", "particles A", "time (s)")]
    errors = []
    for r in s.get("results", []):
        res = r.get("result") or {}
        valid = res.get("valid_fraction")
        rows.append((r["name"], r["status"], "-" if valid is None else f"{valid:.0%}",
                     str(res.get("n_particles_a", "-")),
                     f"{r['seconds']:.1f}" if r["status"] == "done" else "-"))
        if r["status"] == "failed":
            errors.append(f"  {r['name']}: {r.get('error_type')}: {r.get('error')}")
    width = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(c.ljust(w) for c, w in zip(row, width, strict=True)).rstrip())
    threads = s.get("threads_per_worker")
    print(f"{s['n_jobs']} pairs: {s['n_done']} done, {s['n_skipped']} skipped, "
          f"{s['n_failed']} failed in {s['seconds']:.1f} s ({s.get('cluster')} cluster, "
          f"{s.get('n_workers') or '?'} workers x {threads or '?'} threads)")
    if errors:
        print("failed:")
        print("\n".join(errors))
    weights = ("from the cache" if s.get("weights_from_cache")
               else f"built in {s.get('weights_s', 0.0):.1f} s")
    print(f"weights: {weights}")
    print(f"products: {s['out']}  (summary: {s.get('summary_path')})")


def _print_human(summary: dict):
    """Print a command's summary for people (``--json`` prints it as it is)."""
    printer = {"run": _print_run, "plan": _print_plan}.get(summary.get("command"))
    if printer is not None:
        printer(summary)
    else:
        _print_lines(summary)


def _command_of(argv: list[str]) -> str | None:
    words = [a for a in argv if not a.startswith("-")]
    if not words:
        return None
    return " ".join(words[:2]) if words[0] == "simulate" and len(words) > 1 else words[0]


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _report_failure(exc: BaseException, status: int, command: str | None, as_json: bool,
                    warned: list[str]) -> int:
    """Print a failure the one way: an ``error:`` line on stderr and, with ``--json``, one
    JSON object holding ``"error"`` on stdout. Return the exit status."""
    msg = _one_line(exc) or type(exc).__name__
    if as_json:
        obj = {**getattr(exc, "summary", {}), "command": command, "error": msg,
               "error_type": type(exc).__name__, "exit_status": status}
        if warned:
            obj["warnings"] = warned
        print(to_json(obj))
    print(f"error: {msg}", file=sys.stderr)
    return status


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``plenopiv`` command; returns the exit status.

    0: done. 1: a computation or a write failed (a full disk, failed pairs of ``run``, an
    unexpected error). 2: bad input, refused before any work. 130: interrupted (Ctrl-C).
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    as_json = "--json" in argv
    command = _command_of(argv)
    warned: list[str] = []

    def show(message, category, filename, lineno, file=None, line=None):
        text = _one_line(message)
        warned.append(text)
        print(f"warning: {text}", file=sys.stderr)

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", PlenopivWarning)
            warnings.showwarning = show
            try:
                args = build_parser().parse_args(argv)
            except SystemExit as exc:          # --help, --version
                return exc.code if isinstance(exc.code, int) else 0
            command = args.command if args.command != "simulate" else f"simulate {args.kind}"
            as_json = bool(getattr(args, "json", as_json))
            summary = args.func(args)
    except PlenopivError as exc:
        return _report_failure(exc, exc.exit_status, command, as_json, warned)
    except KeyboardInterrupt:
        exc = PlenopivError("interrupted (Ctrl-C); products written so far are complete, "
                            "temporaries are removed on the next run")
        return _report_failure(exc, EXIT_INTERRUPTED, command, as_json, warned)
    except OSError as exc:             # a read or write outside plenopiv's own checks
        where = f" ({exc.filename})" if exc.filename else ""
        err = PlenopivError(f"a file operation failed{where}: {type(exc).__name__}: "
                            f"{_one_line(exc.strerror or exc)}")
        return _report_failure(err, EXIT_FAILED, command, as_json, warned)
    except MemoryError as exc:
        err = ResourceError(f"out of memory ({type(exc).__name__}: {_one_line(exc)}): use "
                            "a smaller volume, sensor or batch")
        return _report_failure(err, EXIT_FAILED, command, as_json, warned)
    except Exception as exc:  # noqa: BLE001 - the one error path: no traceback for users
        if os.environ.get("PLENOPIV_TRACEBACK"):
            import traceback

            traceback.print_exc()
        err = PlenopivError(f"unexpected {type(exc).__name__}: {_one_line(exc)} (a bug in "
                            "plenopiv; set PLENOPIV_TRACEBACK=1 to see where)")
        return _report_failure(err, EXIT_FAILED, command, as_json, warned)
    if warned:
        summary = {**summary, "warnings": warned}
    if as_json:
        print(to_json(summary))
    else:
        _print_human(summary)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
