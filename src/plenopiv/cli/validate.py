"""``plenopiv validate``: the studies that reproduce the thesis's figures and check the chain.

``oseen`` and ``hill`` run the whole chain from the package
(:mod:`plenopiv.workflow.vortex_case`). The other cases are research studies kept in the
repository's ``pipelines/studies/`` folder, which the installed package does not carry: they
run where that folder can be found (:func:`studies_root`: ``$PLENOPIV_REPO``, else the source
tree the package was imported from, i.e. an editable install of a clone), loaded by file
location (:func:`load_study`); elsewhere they are refused with the script to run instead.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
import time
from pathlib import Path

from plenopiv.cli._common import (
    _add_common,
    _add_example,
    _add_precompile,
    _integer,
    _number,
    _seed,
    check_lenslets,
)
from plenopiv.errors import ConfigError
from plenopiv.products.files import check_output_path

#: The cases kept in the repository: the module of ``pipelines.studies`` whose ``run`` they
#: call, and the script of ``pipelines/`` that runs the same study from a clone.
STUDIES = {"vortex": ("vortex", "validate_vortex.py"),
           "calibration": ("calibration", "validate_calibration.py"),
           "depth": ("depth_report", "validate_depth.py"),
           "fields": ("field_quality_report", "validate_fields.py"),
           "letters": ("letters_report", "validate_letters.py"),
           "uncertainty": ("uncertainty", "validate_uncertainty.py")}


def studies_root() -> Path | None:
    """The repository root holding ``pipelines/studies/``, or None where none is found.

    Looked for under ``$PLENOPIV_REPO`` when it is set, then beside the package's source tree
    (``src/plenopiv/`` of a clone: an editable install); an installed wheel has neither.
    """
    import plenopiv

    candidates = [Path(os.environ["PLENOPIV_REPO"])] if os.environ.get("PLENOPIV_REPO") else []
    candidates.append(Path(plenopiv.__file__).resolve().parents[2])
    for root in candidates:
        if (root / "pipelines" / "studies" / "__init__.py").is_file():
            return root.resolve()
    return None


def load_study(root: Path, module: str):
    """``pipelines.studies.<module>`` of the repository at ``root``, imported by file location.

    The ``pipelines`` package is loaded from ``root/pipelines/__init__.py`` (``sys.path`` is
    left as it is), so the study's own imports of ``pipelines.studies`` resolve in ``root``.

    Raises
    ------
    ConfigError
        When a ``pipelines`` package from another folder is already imported.
    """
    init = root / "pipelines" / "__init__.py"
    pkg = sys.modules.get("pipelines")
    if pkg is None:
        spec = importlib.util.spec_from_file_location(
            "pipelines", init, submodule_search_locations=[str(init.parent)])
        pkg = importlib.util.module_from_spec(spec)
        sys.modules["pipelines"] = pkg
        try:
            spec.loader.exec_module(pkg)
        except BaseException:
            del sys.modules["pipelines"]
            raise
    elif Path(getattr(pkg, "__file__", None) or "").resolve() != init.resolve():
        raise ConfigError(f"a package 'pipelines' from {getattr(pkg, '__file__', None)} is "
                          f"already imported; the studies are in {init.parent}")
    return importlib.import_module(f"pipelines.studies.{module}")


def _study_root(case: str) -> Path:
    """The repository root for ``validate <case>``, or ConfigError naming the script to run."""
    root = studies_root()
    if root is None:
        raise ConfigError(
            f"validate {case} runs a study kept in the repository's pipelines/ folder, which "
            "an installed package does not carry; from a clone of the repository run: python "
            f"pipelines/{STUDIES[case][1]} --out DIR (or set PLENOPIV_REPO to the clone)")
    return root


def add_parser(sub) -> None:
    """Add ``validate`` to the subcommands ``sub``."""
    val = sub.add_parser("validate", help="validation studies (thesis figures, vortex flows)")
    val.add_argument("case", choices=("oseen", "hill", "vortex", "calibration", "depth",
                                      "fields", "letters", "uncertainty"),
                     help="oseen/hill: whole chain on a vortex; vortex: both against flow "
                          "size and voxel; calibration: Figs 3.8, 3.9, 5.5; depth: Tables "
                          "5.1, 5.2; fields: particle-field quality; letters: light field on "
                          "the real plenoptomos image; uncertainty: coverage of the per-vector "
                          "uncertainty on the vortex flows (all but oseen/hill are studies in "
                          "a clone's pipelines/, found beside the source tree or under "
                          "$PLENOPIV_REPO)")
    val.add_argument("--out", required=True, help="output folder")
    val.add_argument("--data", metavar="DIR",
                     help="letters: the third-party data folder holding "
                          "plenoptomos_letters_ULF/ (default: $PLENOPIV_DATA, else "
                          "../shared/data beside the current folder or the repository)")
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
    if args.lenslets is not None and args.case in ("oseen", "hill"):
        from plenopiv.camera.model import load_camera

        check_lenslets(args.lenslets, load_camera(args.camera))
    check_output_path(args.out, what="--out", folder=True)
    case = args.case
    if case in STUDIES:          # refused before any work where the study cannot be found
        root = _study_root(case)
        study = load_study(root, STUDIES[case][0])
    if case == "letters":
        try:
            data = load_study(root, "letters_data").find_data_dir(args.data)
        except FileNotFoundError as exc:
            raise ConfigError(str(exc)) from None
    t0 = time.perf_counter()
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
    elif case == "letters":
        out = study.run(args.out, data_dir=data)
    elif case in ("vortex", "uncertainty"):
        out = study.run(args.out, progress=lambda _msg: None)
    elif case in ("calibration", "depth", "fields"):
        out = study.run(args.out)
    else:  # argparse restricts the choices
        raise ConfigError(f"validate {case!r}: unknown case")
    return {"command": f"validate {case}", "out": str(args.out), **out,
            "seconds": round(time.perf_counter() - t0, 3)}
