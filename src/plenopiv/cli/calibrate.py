"""``plenopiv calibrate``: lenslet centres, focal spots and the image distance from images."""

from __future__ import annotations

import time

from plenopiv.cli._common import _add_common, _add_example, _check_out, _input_files, _number
from plenopiv.cli._progress import _StageBar
from plenopiv.errors import ConfigError


def add_parser(sub) -> None:
    """Add ``calibrate`` to the subcommands ``sub``."""
    cal = sub.add_parser("calibrate", help="lenslet centres, focal spots and the image distance")
    cal.add_argument("camera", help="camera TOML file or preset name")
    cal.add_argument("--focal-point", required=True, metavar="IMG",
                     help="focal-point image (white sheet, stopped-down lens)")
    cal.add_argument("--focal-point-f-number", type=float, metavar="N",
                     help="stop of the focal-point image (e.g. 16): fit the spots' centroids "
                          "over it, not their chief rays (they differ through a plate), and "
                          "measure the sensor's point spread from the spots' size")
    cal.add_argument("--alignment", metavar="IMG",
                     help="alignment image (collimated light); default: the nominal lattice")
    cal.add_argument("--ruler", metavar="IMG", help="ruler image on the nominal focal plane")
    cal.add_argument("--white", metavar="IMG",
                     help="white image at the working aperture: the focal-point and alignment "
                          "images are divided by it (lenslet throughput and the micro-images' "
                          "vignetting, which bias S_i), and the camera's f_number is checked "
                          "against its micro-image size; without it the vignetting cannot be "
                          "seen in the calibration images and nothing warns of it (+0.12 mm "
                          "of S_i at 20 %% light lost at the rims on the demo camera)")
    cal.add_argument("--dark", metavar="PATH",
                     help="dark frame or stack (TIFF, multi-page TIFF, PNG, file.h5:/path 2-D "
                          "or 3-D): its mean is subtracted from every calibration image and its "
                          "hot pixels are repaired before spot detection; without it each "
                          "image's black level and its column and row pattern are estimated "
                          "from its gaps, the focal-point image's hot pixels found by shape "
                          "and repaired in the alignment image, and what the alignment "
                          "lattice then carries into S_i warned about beyond 3 times the "
                          "fit's standard deviation")
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
    cal.add_argument("--max-rms-residual-pitch", type=float, default=None,
                     help="refuse an image whose spots fit their lattice worse than this "
                          "fraction of the pitch, rms (default: no limit; an image whose "
                          "spots sit on no lattice is refused whatever its residual)")
    cal.add_argument("--spot-method", choices=("auto", "window", "shape", "centroid",
                                                "gaussian"),
                     default="auto", help="spot-centre estimator (default auto: the window "
                     "centroid for focal-point and alignment spots)")
    cal.add_argument("--no-report", action="store_true", help="no PNG report beside --out")
    cal.add_argument("--out", required=True, help="calibration product (.h5)")
    _add_common(cal)
    _add_example(cal, "plenopiv calibrate camera.toml --focal-point fp.tif --alignment al.tif "
                      "--out cal.h5")
    cal.set_defaults(func=cmd_calibrate)


def cmd_calibrate(args) -> dict:
    """Calibrate a camera from its images and write the calibration product."""
    from plenopiv.calibration.calibrate import calibrate
    from plenopiv.camera.model import load_camera
    from plenopiv.products.images import read_image
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
                          args.white, args.dark)
    out = _check_out(args.out, (".h5",), inputs=inputs,
                     beside=() if args.no_report else (".png",))
    t0 = time.perf_counter()
    progress = _StageBar("calibrate", {"read images": 5, "spots and S_i": 75, "report": 20},
                         args.quiet or args.json)
    progress("read images")
    dark = dark_record = None
    if args.dark is not None:
        from plenopiv.workflow.preprocess import calibration_dark

        dark, dark_record = calibration_dark(args.dark, cam.sensor.shape)

    def read(spec):
        return None if spec is None else read_image(spec)

    fp, al, ru, wh = (read(s) for s in (args.focal_point, args.alignment, args.ruler,
                                        args.white))
    progress("spots and S_i")
    report = calibrate(cam, fp, alignment_image=al, ruler_image=ru, white_image=wh, dark=dark,
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
              "white": args.white, "dark": args.dark,
              "method": args.method}
    report.calibration.save(out, config={"inputs": inputs, "summary": report.summary()},
                            provenance=_provenance(args, cam, inputs))
    summary = {"command": "calibrate", "out": str(out), **report.summary()}
    if dark_record is not None:
        summary["dark"] = dark_record
    if not args.no_report:
        from plenopiv.products.figures import calibration_report

        png = out.with_suffix(".png")
        calibration_report(report, fp, png)
        summary["report"] = str(png)
    progress.close()
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    return summary


def _provenance(args, camera, inputs: dict) -> dict:
    """What made the calibration: its images (content hashes), camera and options."""
    from plenopiv.products.files import file_identity
    from plenopiv.products.provenance import json_hash, make_provenance

    files = {k: file_identity(v) for k, v in inputs.items()
             if k in ("focal_point", "alignment", "ruler", "white", "dark") and v is not None}
    options = {k: v for k, v in vars(args).items()
               if k not in ("func", "out", "json", "quiet", "camera", "focal_point",
                            "alignment", "ruler", "white", "dark", "no_report")
               and isinstance(v, (str, int, float, bool, list, tuple, type(None)))}
    return make_provenance("calibration", inputs=files,
                           settings={"camera": json_hash(camera.to_dict()),
                                     "calibrate": json_hash(options)})
