"""``plenopiv demo``: the built-in synthetic case end to end."""

from __future__ import annotations

from plenopiv.cli._common import _add_common, _add_example, _add_precompile, _seed
from plenopiv.cli._progress import _StageBar
from plenopiv.products.files import check_output_path

#: Test displacements of the demo's response uncertainty (a run's default is 3, five test
#: pairs): the same measurement of the chain's response with one test pair instead of five,
#: which saves eight of the demo's twelve reconstructions.
DEMO_RESPONSE_DISPLACEMENTS = 1


def add_parser(sub) -> None:
    """Add ``demo`` to the subcommands ``sub``."""
    demo = sub.add_parser(
        "demo", help="run the built-in synthetic case end to end",
        description="Run the built-in synthetic case end to end (calibration, a Lamb-Oseen "
        "vortex pair, two volumes, 3-D PIV) and print its errors against the truth. The "
        "response uncertainty uses one test displacement ([piv] response_displacements = "
        "1; a run's default is 3, eight test pairs).")
    demo.add_argument("--out", default="demo_out", help="output folder (default demo_out)")
    demo.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    _add_precompile(demo, "the demo")
    _add_common(demo)
    _add_example(demo, "plenopiv demo --out demo_out")
    demo.set_defaults(func=cmd_demo)


def cmd_demo(args) -> dict:
    """The built-in synthetic case end to end, with its errors against the truth.

    Calibration images -> calibration -> a Lamb-Oseen vortex pair -> two volumes -> 3-D PIV
    corrected by the particle tracks -> errors against the truth.
    """
    from plenopiv.workflow.vortex_case import VortexCase, run_case

    _seed(args.seed)
    check_output_path(args.out, what="--out", folder=True)
    stages = {"calibration images": 12, "calibrate": 10, "simulate pair": 6, "weights": 14,
              "volume A": 12, "volume B": 12, "response": 10, "piv": 2, "tracks": 4,
              "products": 22}
    with _StageBar("demo", stages, args.quiet or args.json) as progress:
        s = run_case(VortexCase(flow="oseen", seed=args.seed,
                                response_displacements=DEMO_RESPONSE_DISPLACEMENTS),
                     args.out, progress=progress, precompile=args.precompile)
    e = s["errors"]
    return {"command": "demo", "out": str(args.out), "camera": s["case"]["camera"],
            "image_distance_mm": s["calibration"]["image_distance_mm"],
            "n_particles": s["n_particles"], "grid_shape": s["grid_shape"],
            "valid_fraction": e["valid_fraction"], "gain": e["gain"],
            "rms_error_vox": e["rms_vox"], "bias_vox": e["bias_vox"],
            "by_depth": [{k: b[k] for k in ("abs_z_mm", "n_vectors", "gain", "bias_vox",
                                            "rms_vox")} for b in e["by_depth"]],
            "uncertainty": (f"response, {DEMO_RESPONSE_DISPLACEMENTS} test displacement "
                            "(a run's default: 3)"),
            "accuracy": s["accuracy"], "seconds": s["timings_s"]["total_s"],
            "stage_seconds": {k.removesuffix("_s"): v for k, v in s["timings_s"].items()},
            "products": s["products"]}


def print_summary(s: dict) -> None:
    """``plenopiv demo``: the run's lines, then its accuracy as ``plenopiv compare`` prints it."""
    from plenopiv.cli._output import _print_lines
    from plenopiv.cli.compare import accuracy_lines

    _print_lines({k: v for k, v in s.items() if k != "accuracy"})
    acc = s.get("accuracy")
    if acc:
        vox = " x ".join(f"{v * 1e3:.4g}" for v in acc["voxel_m"])
        print(f"accuracy against the truth (voxel {vox} mm; as plenopiv compare prints it):")
        for line in accuracy_lines(acc):
            print(f"  {line}")
