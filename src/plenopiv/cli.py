"""The ``plenopiv`` command (DESIGN.md §7). Every subcommand takes ``--json``.

Orchestration only: parse, validate, call the library, write products atomically, report.
Errors that plenopiv raises on purpose are printed as one line (``error: ...``) with exit
status 2; nothing is written when an input is rejected.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from plenopiv import __version__
from plenopiv.camera import CameraModel, load_camera, preset_names
from plenopiv.errors import ConfigError, PlenopivError
from plenopiv.io import to_json, write_h5, write_image

# ---- shared helpers ------------------------------------------------------------------------


def _progress_bar(total: int, desc: str, quiet: bool):
    bar = tqdm(total=total, desc=desc, unit="", disable=quiet or None, leave=False,
               file=sys.stderr, dynamic_ncols=True)
    return bar, (lambda n: bar.update(n))


def _camera_from_args(args) -> CameraModel:
    cam = load_camera(args.camera)
    if getattr(args, "image_distance_mm", None) is not None:
        cam = cam.with_image_distance(args.image_distance_mm * 1e-3)
    return cam


def _finish(irr, args, rng):
    from plenopiv.synthetic.images import finish_image

    bits = None if args.bit_depth == 0 else args.bit_depth
    return finish_image(irr, blur_px=args.blur_px, noise=args.noise, bit_depth=bits,
                        full_well=args.full_well, read_noise=args.read_noise, rng=rng)


def _check_out(path: str, suffixes: tuple[str, ...]) -> Path:
    p = Path(path)
    if p.suffix.lower() not in suffixes:
        raise ConfigError(f"--out {path!r}: expected a file ending in {' or '.join(suffixes)}")
    return p


def _image_summary(img) -> dict:
    return {"shape": list(img.shape), "dtype": str(img.dtype), "max": float(img.max()),
            "mean": float(img.mean())}


# ---- simulate ------------------------------------------------------------------------------


def cmd_simulate(args) -> dict:
    """Render a synthetic image (or a pair) and write it."""
    from plenopiv.synthetic import images as S

    cam = _camera_from_args(args)
    rng = np.random.default_rng(args.seed)
    kind = args.kind
    t0 = time.perf_counter()
    summary: dict = {"command": f"simulate {kind}", "camera": cam.name,
                     "image_distance_mm": cam.image_distance * 1e3}
    if kind in ("focal-point", "alignment", "ruler"):
        out = _check_out(args.out, (".tif", ".tiff", ".png"))
        bar, tick = _progress_bar(cam.microlens_array.count if kind != "ruler" else 32,
                                  f"render {kind}", args.quiet or args.json)
        with bar:
            if kind == "focal-point":
                f_number = args.f_number or cam.main_lens.f_number
                irr = S.focal_point_image(cam, f_number=f_number, progress=tick)
                summary["f_number"] = f_number
            elif kind == "alignment":
                irr = S.alignment_image(cam, progress=tick)
            else:
                ruler = S.Ruler(spacing=args.spacing_mm * 1e-3,
                                tick_width=args.tick_width_mm * 1e-3, depth=args.depth_mm * 1e-3)
                bar.total = None
                irr = S.ruler_image(cam, ruler, f_number=args.f_number, seed=args.seed,
                                    rays_per_lenslet=args.rays_per_lenslet)
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
        out = _check_out(args.out, (".tif", ".tiff", ".png", ".h5"))
        pos = random_particles(box, n, rng)
        bar, tick = _progress_bar(n, "render particles", quiet)
        with bar:
            irr = particle_image(cam, pos, rays_per_particle=args.rays_per_particle,
                                 f_number=args.f_number, seed=args.seed, progress=tick)
        img = _finish(irr, args, rng)
        if out.suffix.lower() == ".h5":
            write_h5(out, {"/image": img, "/truth/position_m": pos},
                     units={"/truth/position_m": "m"}, config=config, kind="synthetic particles")
        else:
            write_image(out, img, metadata={"camera": cam.to_dict(), **info})
        return {**info, "out": str(out), **_image_summary(img)}
    out = _check_out(args.out, (".h5",))
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

    cam = load_camera(args.camera)
    out = _check_out(args.out, (".h5",))
    if args.method in ("magnification", "both") and (args.ruler is None or
                                                      args.ruler_spacing_mm is None):
        raise ConfigError(f"--method {args.method} needs --ruler IMG and --ruler-spacing-mm")
    t0 = time.perf_counter()
    fp = read_image(args.focal_point)
    al = None if args.alignment is None else read_image(args.alignment)
    ru = None if args.ruler is None else read_image(args.ruler)
    report = calibrate(cam, fp, alignment_image=al, ruler_image=ru,
                       ruler_spacing=(None if args.ruler_spacing_mm is None
                                      else args.ruler_spacing_mm * 1e-3),
                       ruler_axis=args.ruler_axis, method=args.method,
                       fit_misplacement=not args.no_misplacement,
                       max_missing_fraction=args.max_missing_fraction)
    inputs = {"focal_point": args.focal_point, "alignment": args.alignment,
              "ruler": args.ruler, "ruler_spacing_mm": args.ruler_spacing_mm,
              "method": args.method}
    report.calibration.save(out, config={"inputs": inputs, "summary": report.summary()})
    summary = {"command": "calibrate", "out": str(out), **report.summary()}
    if not args.no_report:
        from plenopiv.plots import calibration_report

        png = out.with_suffix(".png")
        calibration_report(report, fp, png)
        summary["report"] = str(png)
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary


# ---- reconstruct ---------------------------------------------------------------------------


def cmd_reconstruct(args) -> dict:
    """Reconstruct one image into a volume with its particle table."""
    from plenopiv.config import load_experiment
    from plenopiv.io import read_image
    from plenopiv.pipeline import experiment_calibration, reconstruct_volume

    out = _check_out(args.out, (".h5",))
    exp = load_experiment(args.config)
    cal = experiment_calibration(exp, args.calibration)
    img = read_image(args.image)
    t0 = time.perf_counter()
    bar = tqdm(total=100, desc="reconstruct", disable=args.quiet or args.json or None,
               file=sys.stderr, leave=False)
    with bar:
        def progress(stage, fraction):
            bar.set_description(stage)
            bar.n = int(100 * fraction)
            bar.refresh()
        cache = exp.output.weights_cache
        res = reconstruct_volume(cal, img, exp.volume, settings=exp.reconstruction,
                                 particles=exp.particles, progress=progress,
                                 cache_dir=(exp.path(cache) if cache else None))
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
    from plenopiv.config import PIVConfig
    from plenopiv.pipeline import correlate, load_volume, piv_settings

    out = _check_out(args.out, (".h5",))
    if args.dt is not None and not args.dt > 0:
        raise ConfigError(f"--dt {args.dt}: expected a positive time in seconds")
    t0 = time.perf_counter()
    va, vb = load_volume(args.volume_a), load_volume(args.volume_b)
    cfg = PIVConfig() if args.config is None else _experiment(args.config).piv
    if args.windows:
        cfg = cfg.model_copy(update={"windows": [tuple(w) for w in args.windows]})
    vec = correlate(va, vb, piv_settings(cfg), dt=args.dt)
    files = vec.save(out, config={"piv": cfg.model_dump(), "volume_a": str(args.volume_a),
                                  "volume_b": str(args.volume_b), "dt_s": args.dt},
                     vtk=not args.no_vtk, extra_attrs={"complete": True})
    summary = {"command": "piv", "out": str(out), "shape": list(vec.u.shape),
               "valid_fraction": float(np.mean(vec.valid)), "n_replaced": vec.n_replaced,
               "quantity": "displacement" if args.dt is None else "velocity",
               "files": [str(f) for f in files]}
    if not args.no_png:
        from plenopiv.plots import vector_slices

        summary["png"] = str(vector_slices(vec, out.with_suffix(".png")))
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary


def _experiment(path):
    from plenopiv.config import load_experiment

    return load_experiment(path)


# ---- validate --------------------------------------------------------------------------------


def cmd_validate(args) -> dict:
    """Studies that reproduce the thesis's figures and validate the whole chain."""
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
        from plenopiv.validation.letters import run

        out = run(args.out)
    elif case == "depth":
        from plenopiv.validation.depth_study import run

        out = run(args.out)
    elif case == "vortex":
        from plenopiv.validation.vortex_study import run

        out = run(args.out, progress=lambda _msg: None)
    elif case == "fields":
        from plenopiv.validation.field_quality import run

        out = run(args.out)
    else:  # argparse restricts the choices
        raise ConfigError(f"validate {case!r}: unknown case")
    return {"command": f"validate {case}", "out": str(args.out), **out,
            "seconds": round(time.perf_counter() - t0, 3)}


# ---- run ---------------------------------------------------------------------------------


def cmd_run(args) -> dict:
    """Many pairs end to end on dask (local processes, SLURM, or a running scheduler)."""
    from plenopiv.batch import batch_options, discover_pairs, run_batch
    from plenopiv.config import load_experiment
    from plenopiv.pipeline import ExperimentPairProcess, experiment_calibration, weights_for

    exp = load_experiment(args.experiment)
    im = exp.images
    if im.calibration is None:
        raise ConfigError(f"{args.experiment}: [images] calibration is not set: expected the "
                          "calibration product (.h5) of plenopiv calibrate")
    if (im.a is None or im.b is None) and im.pairs is None:
        raise ConfigError(f"{args.experiment}: [images] needs a and b (glob patterns of the "
                          "two exposures) or pairs (HDF5 files with /image_a and /image_b)")
    out_dir = exp.path(exp.output.directory)
    if im.pairs is not None:
        jobs = discover_pairs(im.pairs, out_dir=out_dir, root=exp.base_dir,
                              output_name="{name}_vectors.h5")
    else:
        jobs = discover_pairs(im.a, im.b, out_dir=out_dir, root=exp.base_dir,
                              output_name="{name}_vectors.h5")
    cal_path = exp.path(im.calibration)
    cal = experiment_calibration(exp, cal_path)
    # build (or find) the weights once, before the workers start: they load them from disk
    t0 = time.perf_counter()
    cache = exp.output.weights_cache
    _, hit = weights_for(cal, exp.volume, exp.reconstruction,
                         cache_dir=exp.path(cache) if cache else None)
    opts = batch_options(exp.batch.model_dump())
    if args.cluster is not None:
        opts["cluster"] = args.cluster
    if args.workers is not None:
        opts["n_workers"] = args.workers
    process = ExperimentPairProcess(str(Path(args.experiment).resolve()), str(cal_path.resolve()),
                                    str(out_dir))
    summary = run_batch(jobs, process, resume=args.resume,
                        progress=not (args.quiet or args.json), **opts)
    return {"command": "run", "out": str(out_dir), "weights_from_cache": hit,
            "weights_s": round(time.perf_counter() - t0, 3) if not hit else 0.0,
            **summary.to_dict()}


# ---- demo ----------------------------------------------------------------------------------


def cmd_demo(args) -> dict:
    """The built-in synthetic case end to end: calibration images -> calibration -> a
    Lamb-Oseen vortex pair -> two volumes -> 3-D PIV -> errors against the truth."""
    from plenopiv.validation.vortex import VortexCase, run_case

    bar = tqdm(total=100, desc="demo", disable=args.quiet or args.json or None,
               file=sys.stderr, leave=False)
    with bar:
        def progress(stage, fraction):
            bar.set_description(f"demo: {stage}")
            bar.n = int(100 * fraction)
            bar.refresh()
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


def build_parser() -> argparse.ArgumentParser:
    """The ``plenopiv`` argument parser."""
    parser = argparse.ArgumentParser(
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
    cal.add_argument("--alignment", metavar="IMG",
                     help="alignment image (collimated light); default: the nominal lattice")
    cal.add_argument("--ruler", metavar="IMG", help="ruler image on the nominal focal plane")
    cal.add_argument("--ruler-spacing-mm", type=float, help="ruler tick spacing (mm)")
    cal.add_argument("--ruler-axis", choices=("x", "y"), default="x",
                     help="direction along which the ticks repeat (default x, along columns)")
    cal.add_argument("--method", choices=("focal-point", "magnification", "both"),
                     default="focal-point", help="which S_i to keep (default focal-point)")
    cal.add_argument("--no-misplacement", action="store_true",
                     help="fit S_i only, not the MLA offset and rotation")
    cal.add_argument("--max-missing-fraction", type=float, default=0.25,
                     help="more missing focal spots than this is an error (default 0.25)")
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
    piv.add_argument("--no-vtk", action="store_true", help="no .vti file for ParaView")
    piv.add_argument("--no-png", action="store_true", help="no PNG of vector slices")
    _add_common(piv)
    piv.set_defaults(func=cmd_piv)

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
                                      "fields", "letters"),
                     help="oseen/hill: whole chain on a vortex; vortex: both against flow "
                          "size and voxel; calibration: Figs 3.8, 3.9, 5.5; depth: Tables "
                          "5.1, 5.2; fields: particle-field quality; letters: light field on "
                          "the real plenoptomos image")
    val.add_argument("--out", required=True, help="output folder")
    val.add_argument("--camera", default="small_m1", help="camera for oseen/hill")
    val.add_argument("--particles-per-lenslet", type=float, default=0.15)
    val.add_argument("--lenslets", type=int, nargs=2, metavar=("ROWS", "COLS"),
                     help="oseen/hill: run on the central ROWS x COLS lenslets of the camera")
    val.add_argument("--lateral-oversampling", type=int, default=1, metavar="K",
                     help="oseen/hill: lateral voxels per lenslet footprint (default 1)")
    val.add_argument("--blur-px", type=float, default=0.0,
                     help="oseen/hill: Gaussian point spread of the renders, pixels (default 0)")
    val.add_argument("--depth-centre-mm", type=float, default=0.0,
                     help="oseen/hill: Z of the volume's centre, mm (default 0: on the focal "
                          "plane)")
    val.add_argument("--seed", type=int, default=1)
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


def _print_human(summary: dict):
    for k, v in summary.items():
        print(f"{k}: {v}")


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``plenopiv`` command."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        summary = args.func(args)
    except PlenopivError as exc:
        if getattr(args, "json", False):
            print(json.dumps({"command": args.command, "error": str(exc),
                              "error_type": type(exc).__name__}))
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(to_json(summary))
    else:
        _print_human(summary)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
