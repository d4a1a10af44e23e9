"""``plenopiv track``: particle tracks of one pair (ray bundles matched with the PIV predictor)."""

from __future__ import annotations

import time

import numpy as np

from plenopiv.cli._common import _add_common, _add_example, _check_out, _input_files
from plenopiv.cli._judgement import JUDGEMENT, experiment_judgement, report
from plenopiv.products.files import check_output_path


def add_parser(sub) -> None:
    """Add ``track`` to the subcommands ``sub``."""
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
    _add_example(trk, "plenopiv track cal.h5 image_A.tif image_B.tif --config experiment.toml "
                      "--out tracks.h5")
    trk.set_defaults(func=cmd_track)


def cmd_track(args) -> dict:
    """Particle tracks of one pair: ray-bundle positions matched with the PIV predictor."""
    from plenopiv.config.experiment import load_experiment
    from plenopiv.products.images import read_image
    from plenopiv.products.jsonio import dumps
    from plenopiv.products.tracks import save_track_products
    from plenopiv.products.vectors import load_vectors
    from plenopiv.products.volume import load_volume
    from plenopiv.resources import check_grid
    from plenopiv.workflow.experiment import experiment_calibration
    from plenopiv.workflow.preprocess import ATTRIBUTE, ImagePreparation
    from plenopiv.workflow.provenance import tracks_provenance
    from plenopiv.workflow.tracking import track_images

    exp = load_experiment(args.config)
    out = _check_outputs(args, exp.output.vtk)
    check_grid(exp.volume)
    cal = experiment_calibration(exp, args.calibration)
    exp, judged = experiment_judgement(exp, cal, purpose="tracking")
    ImagePreparation.refuse_batch_background(exp)
    inputs, sources = _check_reused(args, exp)
    ia, ib = read_image(args.image_a), read_image(args.image_b)
    t0 = time.perf_counter()
    va = load_volume(args.volume_a) if args.volume_a else None
    vb = load_volume(args.volume_b) if args.volume_b else None
    vec = load_vectors(args.vectors) if args.vectors else None
    tracks, va, vb, vec, timings, pre = track_images(
        cal, ia, ib, exp, volume_a=va, volume_b=vb, vectors=vec,
        names=(f"image {str(args.image_a)!r}", f"image {str(args.image_b)!r}"))
    cfg = {**exp.to_dict(), "calibration": str(args.calibration),
           "image_a": str(args.image_a), "image_b": str(args.image_b)}
    judged, seeding = judged.with_seeding(
        0.5 * (len(va.particle_position) + len(vb.particle_position)), purpose="tracking")
    report([seeding])
    paths = save_track_products(tracks, vec, out, config=cfg, vtk=exp.output.vtk,
                                extra_attrs={ATTRIBUTE: dumps(pre),
                                             JUDGEMENT: dumps(judged.record())},
                                provenance=tracks_provenance(exp, inputs=inputs,
                                                             sources=sources, record=pre))
    d = tracks.displacement
    return {"command": "track", "out": str(out), "n_tracks": len(tracks),
            "n_particles_a": len(va.particle_position), "n_particles_b": len(vb.particle_position),
            "counts": tracks.counts, "dt_s": tracks.dt,
            "median_uncertainty_m": (np.median(tracks.uncertainty, axis=0).tolist()
                                     if len(tracks) else None),
            "max_displacement_m": np.abs(d).max(axis=0).tolist() if len(d) else None,
            "files": paths, "timings_s": {k: round(v, 3) for k, v in timings.items()},
            "preprocess": pre, JUDGEMENT: judged.record(),
            "seconds": round(time.perf_counter() - t0, 3)}


def _check_outputs(args, vtk: bool):
    """Check ``--out`` and what is written beside it; none may be an input, each is locked.

    Beside it: ``.vtp``, ``_binned.h5`` and its ``.vti`` (the last with ``[output] vtk``).
    """
    inputs = _input_files(args.calibration, args.image_a, args.image_b, args.config,
                          args.volume_a, args.volume_b, args.vectors)
    out = _check_out(args.out, (".h5",), inputs=inputs, beside=(".vtp",) if vtk else ())
    binned = out.with_name(out.stem + "_binned.h5")
    for path in (binned, *((binned.with_suffix(".vti"),) if vtk else ())):
        check_output_path(path, inputs=inputs, what=f"{path.name} written beside --out")
    return out


def _check_reused(args, exp) -> tuple[dict, dict]:
    """The content hashes of the inputs and the records of the products reused.

    ``--volume-a``, ``--volume-b`` and ``--vectors`` must be of this pair's images and
    calibration (:func:`plenopiv.workflow.provenance.check_track_products`).
    """
    from plenopiv.errors import ReconstructionError
    from plenopiv.products.files import file_identity
    from plenopiv.products.hdf5 import product_provenance
    from plenopiv.workflow.provenance import check_track_products, settings_hashes

    inputs = {"image_a": file_identity(args.image_a), "image_b": file_identity(args.image_b),
              "calibration": file_identity(args.calibration)}
    given = {}
    for role, path, kind in (("volume_a", args.volume_a, "volume"),
                             ("volume_b", args.volume_b, "volume"),
                             ("vectors", args.vectors, "vectors")):
        if path:
            given[role] = (path, product_provenance(path, kind, ReconstructionError))
            inputs[role] = file_identity(path)
    check_track_products(given, images=((inputs["image_a"], str(args.image_a)),
                                        (inputs["image_b"], str(args.image_b))),
                         calibration=(inputs["calibration"], str(args.calibration)),
                         settings=settings_hashes(exp))
    return inputs, {role: record for role, (_, record) in given.items()}
