"""``plenopiv plan``: resolution, recommended voxels and windows, memory and time, before a run."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from plenopiv.cli._common import _add_common, _add_example, _number
from plenopiv.cli._output import _fmt
from plenopiv.cli._progress import _StageBar
from plenopiv.errors import ConfigError


def add_parser(sub) -> None:
    """Add ``plan`` to the subcommands ``sub``."""
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
    plan.add_argument("--seeding", type=float, metavar="PPL",
                      help="the seeding expected, particles per lenslet: judged against the "
                           "seeding the chain was validated at")
    plan.add_argument("--no-measure", action="store_true",
                      help="estimate times from the benchmark figures instead of timing the "
                           "kernels here (no numba compilation)")
    _add_common(plan)
    _add_example(plan, "plenopiv plan experiment.toml")
    plan.set_defaults(func=cmd_plan)


def _box_from_args(args, cam) -> dict | None:
    """A ``[volume]`` table from --x-mm/--y-mm/--z-mm/--voxel-mm (None when none is given)."""
    given = {k: getattr(args, k) for k in ("x_mm", "y_mm", "z_mm", "voxel_mm")}
    if all(v is None for v in given.values()):
        return None
    return {k: (list(v) if k != "voxel_mm" or len(v) > 1 else v[0])
            for k, v in given.items() if v is not None}


def _config_table(path: Path) -> dict:
    """The TOML table of ``plan``'s argument; {} for a camera named by a preset name.

    A missing ``NAME.toml`` of a preset (the old ``configs/cameras/NAME.toml``) is left to
    :func:`~plenopiv.camera.model.load_camera`, whose error names the preset to use.
    """
    from plenopiv.camera.model import preset_names, read_toml

    if path.suffix.lower() != ".toml" or (not path.exists() and path.stem in preset_names()):
        return {}
    return read_toml(path, "config")


def cmd_plan(args) -> dict:
    """Resolution, recommended voxels and windows, size, memory and time of a reconstruction."""
    from plenopiv.camera.grid import volume_from_dict
    from plenopiv.camera.model import load_camera
    from plenopiv.config.experiment import experiment_from_dict
    from plenopiv.piv.settings import PIVSettings
    from plenopiv.reconstruction.settings import ReconstructionSettings
    from plenopiv.workflow import planning
    from plenopiv.workflow import rates as rates_module
    from plenopiv.workflow.judgement import choose_unset, given_settings

    path = Path(args.config)
    table = _config_table(path)
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
        given = given_settings(exp)
        recon, piv_cfg, tracking = exp.reconstruction, exp.piv, exp.tracking
        calibration = args.calibration or (exp.path(exp.images.calibration)
                                           if exp.images.calibration else None)
        if calibration is not None and not Path(calibration).exists():
            calibration = args.calibration      # not made yet: the camera's S_i then
    else:
        camera = load_camera(args.config)
        recon, piv_cfg, tracking = ReconstructionSettings(), PIVSettings(), None
        calibration = args.calibration
        grid, given = None, frozenset()
    if args.f_number is not None:
        recon = dataclasses.replace(recon, f_number=args.f_number)
    if args.windows:
        piv_cfg = dataclasses.replace(piv_cfg, windows=tuple(tuple(w) for w in args.windows))
    cal = None
    if args.image_distance_mm is not None:
        camera = camera.with_image_distance(args.image_distance_mm * 1e-3,
                                            origin="--image-distance-mm")
    elif calibration is not None:
        from plenopiv.workflow.experiment import calibration_for_camera

        cal = calibration_for_camera(calibration, camera, whose=f"the camera of {str(path)!r}")
        camera = cal.camera
    if grid is None:
        cam = planning.camera_resolution(camera, recon.f_number)
        fx, fy = (0.9 * v * 1e3 for v in cam.field_of_view)
        dz = 4 * cam.depth_cell * 1e3
        vox = [v * 1e3 for v in planning.recommended_voxel(cam)]
        default = {"x_mm": [-fx, fx], "y_mm": [-fy, fy], "z_mm": [-dz, dz], "voxel_mm": vox}
        grid = volume_from_dict({**default, **(box or {})}, source="plan options")
    if args.windows:
        given = (given or frozenset()) | {"piv.windows"}
    try:
        resolution = planning.camera_resolution(camera, recon.f_number)
    except ConfigError:          # no image distance: plan() says what to give
        resolution = None
    piv_cfg, chosen = choose_unset(resolution, grid, piv_cfg, given)
    _number("--seeding", args.seeding, minimum=0, open_min=True, unit="particles per lenslet")
    t0 = time.perf_counter()
    if args.no_measure:
        rates = rates_module.BENCHMARK_RATES
    else:
        with _StageBar("plan", {"measure": 1}, args.quiet or args.json) as bar:
            bar("measure rates on this machine")
            rates = rates_module.measure_rates(camera, grid, piv=piv_cfg,
                                               reconstruction=recon)
    result = planning.plan(camera, grid, reconstruction=recon, piv=piv_cfg, rates=rates,
                           calibration=cal, seeding=args.seeding, chosen=chosen,
                           tracking=tracking)
    return {"command": "plan", "config": str(args.config),
            "kind": "experiment" if is_experiment else "camera", **result.to_dict(),
            "seconds": round(time.perf_counter() - t0, 3)}


def print_summary(p: dict) -> None:
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
    rows += _decision_rows(p, count)
    mem = p["memory_gb"]
    rows.append(("memory", (f"weights {_fmt(mem['weights'])} GB (a cache file of "
                            f"{_fmt(mem['weights_cache_file'])} GB on disk), " if sparse else
                            f"projector {_fmt(mem['projector'])} GB, ")
                 + f"peak {_fmt(mem['peak'])} GB of this machine's "
                   f"{_fmt(p['available_memory_gb'])} GB"))
    t = p["time_s"]
    rows.append(("time", f"weights {_fmt(t['weights'])} s"
                         + (" (once, then cached)" if sparse else "") + ", one volume "
                         f"{_fmt(t['volume'])} s"
                         + (f" (the first {_fmt(t['first_volume'])} s more)"
                            if t["first_volume"] > 0 else "")
                         + ", the recording's check "
                         f"{_fmt(t['recording_check'])} s, PIV {_fmt(t['piv'])} s, "
                         f"the pair's tracks {_fmt(t.get('track', 0.0))} s; "
                         f"plenopiv reconstruct {_fmt(t['reconstruct'])} s, a pair "
                         f"{_fmt(t['pair'])} s ({_fmt(t['pair_cached_weights'])} s with cached "
                         "weights)"))
    if p.get("response_s"):
        rows.append(("response", f"the chain's response, once per experiment before its pairs "
                                 f"([piv] uncertainty = \"response\"): about "
                                 f"{_fmt(p['response_s'])} s (none when cached)"))
    rows.append(("", f"time model: {p['time_model']}"))
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k.ljust(width)}  {v}")
    chosen = [f["text"] for f in p["judgement"]["findings"] if f["severity"] == "chosen"]
    for title, lines in (("chosen", chosen), ("warnings", p["warnings"]),
                         ("advice", p["advice"])):
        if lines:
            print(f"{title}:")
            for line in lines:
                print(f"  - {line}")
    if p["advice"] or p["warnings"]:
        print("recommended [volume] and [piv] for this box:")
        for line in rec["toml"].splitlines():
            print(f"  {line}" if line else "")


_PROJECTOR_NAMES = {"sparse": "explicit (sparse) weights",
                    "lattice": "matrix-free lattice projector",
                    "lenslet": "matrix-free per-lenslet projector"}


def _decision_rows(p: dict, count) -> list[tuple[str, str]]:
    """The reconstruction's decision (``p["decision"]``) and the size, as summary rows."""
    d = p["decision"]
    ky, kx = d["lateral_subdivision"]
    nz, ny, nx = d["working_shape"]
    kz = d.get("depth_binning", 1)
    binned = f", {kz} depth slices merged" if kz > 1 else ""
    return [("projector", f"{_PROJECTOR_NAMES[d['projector']]}, lateral subdivision "
                          f"{ky} x {kx}{binned}: {nx} x {ny} x {nz} working voxels (x, y, z), "
                          f"~{_fmt(d['memory_gb'])} GB (what plenopiv reconstruct runs)"),
            ("", f"why: {d['reason']}"),
            ("size", f"{count(p['n_rays'])} rays; explicit weights on the working grid "
                     + ("hold " if d["projector"] == "sparse" else "would hold ")
                     + f"{count(p['nnz'])} non-zeros")]
