"""``plenopiv piv``: 3-D cross-correlation of two volume products into a vectors product."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from plenopiv.cli._common import _add_common, _add_example, _check_out, _input_files, _number
from plenopiv.cli._judgement import JUDGEMENT, report
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
    from plenopiv.errors import ReconstructionError
    from plenopiv.piv import MIN_WINDOW_VOX
    from plenopiv.piv.settings import MAX_WINDOW_VOX, PIVSettings
    from plenopiv.products.hdf5 import product_provenance
    from plenopiv.products.jsonio import dumps
    from plenopiv.products.volume import load_volume
    from plenopiv.settings import as_dict
    from plenopiv.workflow.correlation import correlate, fitted_to_continuity
    from plenopiv.workflow.provenance import check_volume_pair, vectors_provenance

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
    records = {k: product_provenance(path, "volume", ReconstructionError)
               for k, path in (("volume_a", args.volume_a), ("volume_b", args.volume_b))}
    check_volume_pair(args.volume_a, records["volume_a"], args.volume_b, records["volume_b"])
    va, vb = load_volume(args.volume_a), load_volume(args.volume_b)
    settings, judged = _judgement(args.volume_a, exp, settings, changes, va, vb)
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
    vec, continuity = fitted_to_continuity(vec, settings)
    files = vec.save(out, config={"piv": as_dict(settings), "volume_a": str(args.volume_a),
                                  "volume_b": str(args.volume_b), "dt_s": args.dt},
                     vtk=not args.no_vtk,
                     extra_attrs={"complete": True, JUDGEMENT: dumps(judged.record()),
                                  "continuity": dumps(continuity)},
                     provenance=vectors_provenance(args.volume_a, args.volume_b,
                                                   piv=settings, dt=args.dt,
                                                   sources=records))
    summary = {"command": "piv", "out": str(out), "shape": list(vec.u.shape),
               "valid_fraction": float(np.mean(vec.valid)), "n_replaced": vec.n_replaced,
               "quantity": "displacement" if args.dt is None else "velocity",
               "uncertainty_method": vec.uncertainty_method, JUDGEMENT: judged.record(),
               "continuity": continuity,
               "files": [str(f) for f in files]}
    if not args.no_png:
        from plenopiv.products.figures import vector_slices

        title = f"{Path(args.volume_a).name} -> {Path(args.volume_b).name}"
        summary["png"] = str(vector_slices(vec, out.with_suffix(".png"), title=title))
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary


def _judgement(volume_a, exp, settings, changes: dict, va, vb):
    """``(settings with the unset ones chosen, Judgement)`` of the PIV of two volumes, said.

    The camera's resolution and the reconstruction's subdivision come from volume A's
    ``judgement`` attribute (``plenopiv reconstruct``), else from ``--config``'s camera where
    it knows its image distance; without either only the windows against the box are judged.
    Given: ``--config``'s ``[piv]`` keys and the options (``changes``).
    """
    import json

    from plenopiv.products.volume import volume_attribute
    from plenopiv.workflow.judgement import (
        Camera,
        Judgement,
        camera_resolution,
        choose_unset,
        given_settings,
        judge,
    )

    cam, sub, kz = None, None, None
    recorded = volume_attribute(volume_a, JUDGEMENT)
    if recorded:
        rec = json.loads(recorded)
        cam = None if rec.get("camera") is None else Camera.from_dict(rec["camera"])
        sub = None if rec.get("lateral_subdivision") is None else tuple(
            rec["lateral_subdivision"])
        kz = rec.get("depth_binning")
    elif exp is not None:
        try:
            cam = camera_resolution(exp.camera, exp.reconstruction.f_number)
        except ConfigError:             # the camera file gives no image distance
            cam = None
    given = frozenset() if exp is None else (given_settings(exp) or frozenset())
    settings, chosen = choose_unset(cam, va.grid, settings,
                                    given | {f"piv.{k}" for k in changes})
    n = 0.5 * (len(va.particle_position) + len(vb.particle_position))
    found = judge(cam, va.grid, None, settings, subdivision=sub, n_particles=n)
    judged = Judgement(cam, va.grid, chosen + found, sub, n, depth_binning=kz)
    report(judged.findings)
    return settings, judged
