"""``plenopiv validate``: the studies that reproduce the thesis's figures and check the chain."""

from __future__ import annotations

import time

from plenopiv.cli._common import (
    _add_common,
    _add_example,
    _add_precompile,
    _integer,
    _number,
    _seed,
)
from plenopiv.errors import ConfigError
from plenopiv.products.files import check_output_path


def add_parser(sub) -> None:
    """Add ``validate`` to the subcommands ``sub``."""
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
    _add_precompile(val, "the oseen/hill case")
    _add_common(val)
    _add_example(val, "plenopiv validate oseen --out validation_oseen")
    val.set_defaults(func=cmd_validate)


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
        from plenopiv.workflow.vortex_case import VortexCase, run_case

        s = run_case(VortexCase(flow=case, camera=args.camera, seed=args.seed,
                                particles_per_lenslet=args.particles_per_lenslet,
                                lenslets=None if args.lenslets is None else tuple(args.lenslets),
                                lateral_oversampling=args.lateral_oversampling,
                                blur_px=args.blur_px,
                                depth_centre=args.depth_centre_mm * 1e-3), args.out,
                     precompile=args.precompile)
        out = {"errors": s["errors"], "n_particles": s["n_particles"],
               "grid_shape": s["grid_shape"], "voxel_mm": s["voxel_mm"],
               "timings_s": s["timings_s"], "products": s["products"]}
    elif case == "calibration":
        from plenopiv.validation.calibration_study import run

        out = run(args.out)
    elif case == "letters":
        from plenopiv.validation.letters import run
        from plenopiv.validation.letters_data import find_data_dir

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
