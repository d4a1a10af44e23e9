"""``plenopiv piv``: 3-D cross-correlation of two volume products into a vectors product."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from plenopiv.cli._common import _add_common, _add_example, _check_out, _input_files, _number
from plenopiv.cli._progress import _StageBar
from plenopiv.errors import ConfigError


def add_parser(sub) -> None:
    """Add ``piv`` to the subcommands ``sub``."""
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
    _add_example(piv, "plenopiv piv vol_a.h5 vol_b.h5 --out vectors.h5 --dt 1e-3")
    piv.set_defaults(func=cmd_piv)


def cmd_piv(args) -> dict:
    """Cross-correlate two volume products into a vector field."""
    from plenopiv.config.experiment import load_experiment
    from plenopiv.piv import MIN_WINDOW_VOX
    from plenopiv.piv.settings import MAX_WINDOW_VOX, PIVSettings
    from plenopiv.products.volume import load_volume
    from plenopiv.settings import as_dict
    from plenopiv.workflow.pair import correlate

    _number("--dt", args.dt, minimum=0, open_min=True, unit="seconds between the exposures")
    for w in args.windows or ():
        if min(w) < MIN_WINDOW_VOX or max(w) > MAX_WINDOW_VOX:
            raise ConfigError(f"--windows {' '.join(map(str, w))}: expected three window edges "
                              f"WZ WY WX of {MIN_WINDOW_VOX} to {MAX_WINDOW_VOX} voxels")
    inputs = _input_files(args.volume_a, args.volume_b, args.config)
    beside = (() if args.no_vtk else (".vti",)) + (() if args.no_png else (".png",))
    out = _check_out(args.out, (".h5",), inputs=inputs, beside=beside)
    exp = None if args.config is None else load_experiment(args.config)
    cfg = PIVSettings() if exp is None else exp.piv
    changes = {}
    if args.windows:
        changes["windows"] = tuple(tuple(w) for w in args.windows)
    if args.replacement:
        changes["replacement"] = args.replacement
    try:
        settings = dataclasses.replace(cfg, **changes)
    except ValueError as exc:
        raise ConfigError(f"[piv] with the options given: {exc}") from None
    t0 = time.perf_counter()
    va, vb = load_volume(args.volume_a), load_volume(args.volume_b)
    mask = None
    if exp is not None:
        from plenopiv.workflow.masks import volume_mask

        mask = volume_mask(exp.mask, va.grid, exp.base_dir)
    # without the calibration and images there is no round trip: correlation statistics only
    with _StageBar("piv", {"piv": 1}, args.quiet or args.json) as bar:
        bar("piv")
        vec = correlate(va, vb, settings, dt=args.dt, mask=mask, progress=lambda info: bar(
            f"piv pass {info['pass']}/{info['passes']}", info["pass"] / info["passes"]),
            names=(f"volume {str(args.volume_a)!r}", f"volume {str(args.volume_b)!r}"))
    files = vec.save(out, config={"piv": as_dict(settings), "volume_a": str(args.volume_a),
                                  "volume_b": str(args.volume_b), "dt_s": args.dt},
                     vtk=not args.no_vtk, extra_attrs={"complete": True})
    summary = {"command": "piv", "out": str(out), "shape": list(vec.u.shape),
               "valid_fraction": float(np.mean(vec.valid)), "n_replaced": vec.n_replaced,
               "quantity": "displacement" if args.dt is None else "velocity",
               "uncertainty_method": vec.uncertainty_method,
               "files": [str(f) for f in files]}
    if not args.no_png:
        from plenopiv.products.figures import vector_slices

        title = f"{Path(args.volume_a).name} -> {Path(args.volume_b).name}"
        summary["png"] = str(vector_slices(vec, out.with_suffix(".png"), title=title))
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary
