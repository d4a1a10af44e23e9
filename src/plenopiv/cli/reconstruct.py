"""``plenopiv reconstruct``: MART volume and particles from one image."""

from __future__ import annotations

import time
from pathlib import Path

from plenopiv.cli._common import _add_common, _add_example, _check_out, _input_files
from plenopiv.cli._judgement import JUDGEMENT, experiment_judgement, report
from plenopiv.cli._progress import _StageBar


def add_parser(sub) -> None:
    """Add ``reconstruct`` to the subcommands ``sub``."""
    rec = sub.add_parser("reconstruct", help="MART volume and particles from one image")
    rec.add_argument("calibration", help="calibration product (.h5) from plenopiv calibrate")
    rec.add_argument("image", help="raw image: TIFF, PNG or file.h5:/dataset")
    rec.add_argument("--config", required=True, help="experiment TOML ([volume], ...)")
    rec.add_argument("--out", required=True, help="volume product (.h5)")
    _add_common(rec)
    _add_example(rec, "plenopiv reconstruct cal.h5 image_A.tif --config experiment.toml --out "
                      "vol_a.h5")
    rec.set_defaults(func=cmd_reconstruct)


def cmd_reconstruct(args) -> dict:
    """Reconstruct one image into a volume with its particle table."""
    from plenopiv.config.experiment import load_experiment
    from plenopiv.products.files import file_identity
    from plenopiv.products.images import read_image
    from plenopiv.products.jsonio import dumps
    from plenopiv.resources import check_grid
    from plenopiv.workflow.experiment import experiment_calibration
    from plenopiv.workflow.preprocess import ATTRIBUTE, ImagePreparation, union
    from plenopiv.workflow.provenance import volume_provenance
    from plenopiv.workflow.volume import reconstruct_volume

    exp = load_experiment(args.config)
    inputs = _input_files(args.calibration, args.image, args.config)
    out = _check_out(args.out, (".h5",), inputs=inputs,
                     beside=(".png",) if exp.output.png else ())
    cal = experiment_calibration(exp, args.calibration)
    exp, judged = experiment_judgement(exp, cal)
    check_grid(exp.volume)
    ImagePreparation.refuse_batch_background(exp)
    img = read_image(args.image)
    t0 = time.perf_counter()
    from plenopiv.workflow.masks import image_mask

    preparation = ImagePreparation(exp, cal)
    prepared = preparation.image(img, name=f"image {str(args.image)!r}")
    record = preparation.record({"image": prepared.figures})
    stages = {"weights": 30, "mart": 60, "particles": 10}
    with _StageBar("reconstruct", stages, args.quiet or args.json) as progress:
        cache = exp.output.weights_cache
        res = reconstruct_volume(cal, prepared.image, exp.volume, settings=exp.reconstruction,
                                 particles=exp.particles, progress=progress,
                                 cache_dir=(exp.path(cache) if cache else None),
                                 image_mask=union(image_mask(exp.mask, cal.camera.sensor.shape,
                                                             exp.base_dir), prepared.mask),
                                 checked=True)
    judged, seeding = judged.with_seeding(len(res.particle_position), piv=exp.piv)
    report([seeding])
    res.save(out, config={**exp.to_dict(), "calibration": str(args.calibration),
                          "image": str(args.image)},
             extra_attrs={ATTRIBUTE: dumps(record), JUDGEMENT: dumps(judged.record())},
             provenance=volume_provenance(exp, image=file_identity(args.image),
                                          calibration=file_identity(args.calibration),
                                          record=record))
    summary = {"command": "reconstruct", "out": str(out), "shape": list(res.volume.shape),
               "n_particles": len(res.particle_position),
               "depth_correction": res.correction.to_dict(),
               "image_distance_mm": cal.image_distance * 1e3, "preprocess": record,
               JUDGEMENT: judged.record(),
               "timings_s": {k: round(v, 3) for k, v in res.timings.items()}}
    if exp.output.png:
        from plenopiv.products.figures import volume_slices

        png = out.with_suffix(".png")
        volume_slices(res.volume, res.grid.x, res.grid.y, res.grid.z, png,
                      particles=res.particle_position_effective,
                      title=f"{Path(str(args.image)).name}: {len(res.particle_position)} particles")
        summary["png"] = str(png)
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary
