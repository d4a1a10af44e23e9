"""``plenopiv run``: many image pairs end to end on dask (local processes, SLURM, a scheduler)."""

from __future__ import annotations

import argparse
from pathlib import Path

from plenopiv.cli._common import _add_common, _add_example, _integer
from plenopiv.cli._judgement import JUDGEMENT, experiment_judgement
from plenopiv.errors import ConfigError
from plenopiv.products.files import check_output_path


def add_parser(sub) -> None:
    """Add ``run`` to the subcommands ``sub``."""
    run = sub.add_parser("run", help="many image pairs end to end (dask batch)")
    run.add_argument("experiment", help="experiment TOML with [images], [batch], [output]")
    run.add_argument("--resume", action=argparse.BooleanOptionalAction, default=True,
                     help="skip pairs whose product is complete (default; --no-resume redoes all)")
    run.add_argument("--cluster", help="local | slurm | tcp://scheduler:8786 (default [batch])")
    run.add_argument("--workers", type=int, help="worker processes (default: [batch] or cores)")
    _add_common(run)
    _add_example(run, "plenopiv run experiment.toml --workers 4")
    run.set_defaults(func=cmd_run)


def cmd_run(args) -> dict:
    """Many pairs end to end on dask (local processes, SLURM, or a running scheduler).

    The output folder is locked first (one batch per folder); a stop (Ctrl-C, SIGTERM) while
    the batch prepares writes its summary too, every pair not started ``interrupted``.
    """
    from plenopiv.batch import check_batch_options, stopped_before_start
    from plenopiv.batch.cluster import batch_options
    from plenopiv.config.experiment import load_experiment

    _integer("--workers", args.workers, minimum=1, maximum=4096)
    exp = load_experiment(args.experiment)
    opts = batch_options(exp.batch.model_dump())
    if args.cluster is not None:
        opts["cluster"] = args.cluster
    if args.workers is not None:
        opts["n_workers"] = args.workers
    check_batch_options(**opts)
    im = exp.images
    if im.calibration is None:
        raise ConfigError(f"{args.experiment}: [images] calibration is not set: expected the "
                          "calibration product (.h5) of plenopiv calibrate")
    if (im.a is None or im.b is None) and im.pairs is None:
        raise ConfigError(f"{args.experiment}: [images] needs a and b (glob patterns of the "
                          "two exposures) or pairs (HDF5 files with /image_a and /image_b)")
    out_dir = exp.path(exp.output.directory)
    check_output_path(out_dir, what="[output] directory", folder=True)
    jobs = batch_jobs(exp)
    try:
        return _prepare_and_run(args, exp, jobs, out_dir, opts)
    except KeyboardInterrupt as stop:        # stopped before the pairs started
        raise stopped_before_start(jobs, stop, resume=args.resume) from None


def _prepare_and_run(args, exp, jobs, out_dir, opts) -> dict:
    """What the pairs share (calibration, background, weights, response), then the batch."""
    from plenopiv.batch import BatchInterrupted, pending_jobs, run_batch
    from plenopiv.errors import ComputationError
    from plenopiv.resources import check_grid
    from plenopiv.workflow.experiment import experiment_calibration
    from plenopiv.workflow.worker import ExperimentPairProcess, prepare_response, prepare_weights

    cal_path = exp.path(exp.images.calibration)
    _check_products_spare_inputs(jobs, [args.experiment, cal_path])
    cal = experiment_calibration(exp, cal_path)
    # the settings judged before any pair (each worker chooses the unset ones the same way)
    exp, judged = experiment_judgement(exp, cal)
    check_grid(exp.volume)
    background, n_background = _batch_background(exp, jobs, cal, out_dir)
    jobs = with_identities(jobs, exp, cal_path, background)
    # explicit weights go into the weights cache once, before the workers start; each worker
    # then makes its projector once, for all its pairs
    hit, weights_s = prepare_weights(exp, cal)
    # the chain's response, once per experiment, before the pairs fan out to the workers
    response, response_info = None, None
    if pending_jobs(jobs, resume=args.resume):
        estimate = {}
        response = prepare_response(exp, cal, announce=lambda weights: _announce_response(
            exp, cal, weights, estimate, quiet=args.quiet or args.json))
        if response is not None:
            response_info = {**response.summary(), **estimate}
    process = ExperimentPairProcess(str(Path(args.experiment).resolve()), str(cal_path.resolve()),
                                    str(out_dir), response=response,
                                    background=None if background is None else str(background),
                                    background_images=n_background)
    head = {"command": "run", "out": str(out_dir), "weights_from_cache": hit,
            "response": response_info, JUDGEMENT: judged.record()}
    try:
        summary = run_batch(jobs, process, resume=args.resume,
                            progress=not (args.quiet or args.json), **opts)
    except BatchInterrupted as exc:
        exc.summary = {**head, **exc.summary}
        raise
    result = {**head, "weights_s": round(weights_s, 3) if not hit else 0.0,
              **summary.to_dict()}
    _repeat_pair_warnings(summary)
    if summary.failed:
        names = ", ".join(f"{n} ({e})" for n, e in summary.failed[:3])
        more = "" if len(summary.failed) <= 3 else f" and {len(summary.failed) - 3} more"
        err = ComputationError(f"{len(summary.failed)} of {summary.n_jobs} pairs failed: "
                               f"{names}{more}; see {summary.summary_path}")
        err.summary = result
        raise err
    return result


def _announce_response(exp, cal, weights, estimate: dict, *, quiet: bool) -> None:
    """Estimate the response's measurement (into ``estimate``) and say it is starting.

    The estimate is :func:`plenopiv.workflow.planning.plan`'s, on the light field the
    ``weights`` were built from.
    """
    import sys

    from plenopiv.workflow import planning

    seconds = planning.plan(cal.camera, exp.volume, reconstruction=exp.reconstruction,
                            piv=exp.piv, calibration=cal, geometry=weights.geometry).response_s
    estimate["estimate_s"] = round(seconds, 1)
    if not quiet:
        print(f"measuring the chain's response: once per experiment, about {seconds:.0f} s "
              "([piv] uncertainty = \"response\"; the pairs start after it)", file=sys.stderr,
              flush=True)


#: Warnings of a batch's pairs repeated at the command line; the others are counted.
SHOWN_PAIR_WARNINGS = 5


def _repeat_pair_warnings(summary) -> None:
    """Repeat the warnings the pairs got in the workers as this command's own.

    Their images' checks and preprocessing, their seeding, the weights' fallbacks on a
    worker's first pair: the first :data:`SHOWN_PAIR_WARNINGS`, then one line counting the
    rest; every one stays in ``batch_summary.json`` (``results[].result.warnings``).
    """
    import warnings

    from plenopiv.errors import PlenopivWarning

    said = [(r.name, w) for r in summary.results if r.result
            for w in r.result.get("warnings", ())]
    for name, w in said[:SHOWN_PAIR_WARNINGS]:
        warnings.warn(f"pair {name}: {w}", PlenopivWarning, stacklevel=3)
    if len(said) > SHOWN_PAIR_WARNINGS:
        warnings.warn(f"{len(said) - SHOWN_PAIR_WARNINGS} more warnings about the batch's "
                      f"pairs; see {summary.summary_path} (results[].result.warnings)",
                      PlenopivWarning, stacklevel=3)


def _check_products_spare_inputs(jobs, others) -> None:
    """Refuse a batch in which a file a pair writes is one of the batch's inputs.

    The files a pair writes (vectors, volumes, .vti, PNGs) may not be an image, the experiment
    file or the calibration.
    """
    from plenopiv.products.files import split_dataset_spec

    inputs = {split_dataset_spec(p)[0].resolve() for j in jobs for p in (j.image_a, j.image_b)}
    inputs |= {Path(p).resolve() for p in others}
    for j in jobs:
        folder, name = j.output.parent, j.name
        for f in (j.output, folder / f"{name}_volume_A.h5", folder / f"{name}_volume_B.h5",
                  j.output.with_suffix(".vti"), folder / f"{name}_volume_A.png",
                  folder / f"{name}_vectors.png"):
            if f.resolve() in inputs:
                raise ConfigError(f"pair {name!r} would write {str(f)!r}, which is one of the "
                                  "batch's inputs; choose another [output] directory")


def _batch_background(exp, jobs, calibration, out_dir):
    """The batch's background of ``[preprocess] background = "minimum"`` or ``"mean"``.

    Formed once over every image of the batch (both exposures of each pair) before the pairs
    fan out, and written as ``OUT/background_KIND.tif`` (float32 counts) for the workers;
    returns ``(its path, the number of images)``, or ``(None, 0)``. The ``[preprocess]``
    files are read and checked here either way, so that a bad dark or white is refused
    before any pair runs.
    """
    import numpy as np

    from plenopiv.products.images import write_image
    from plenopiv.workflow.preprocess import ImagePreparation, form_batch_background

    pre = exp.preprocess
    if pre is None:
        return None, 0
    kind = pre.background_kind
    background, n, path = None, 0, None
    if kind in ("minimum", "mean"):
        specs = [s for j in jobs for s in (j.image_a, j.image_b)]
        background, n = form_batch_background(specs, kind)
    ImagePreparation(exp, calibration, batch_background=background)
    if background is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        path = write_image(out_dir / f"background_{kind}.tif", background.astype(np.float32),
                           metadata={"product": "batch background", "kind": kind,
                                     "images": n})
    return path, n


def batch_jobs(exp) -> list:
    """The pairs of an experiment's ``[images]`` table, their products in ``[output]``."""
    from plenopiv.batch.jobs import discover_pairs

    im, out_dir = exp.images, exp.path(exp.output.directory)
    if im.pairs is not None:
        return discover_pairs(im.pairs, out_dir=out_dir, root=exp.base_dir,
                              output_name="{name}_vectors.h5")
    return discover_pairs(im.a, im.b, out_dir=out_dir, root=exp.base_dir,
                          output_name="{name}_vectors.h5", pair_by=im.pair_by)


def with_identities(jobs, exp, cal_path, background=None):
    """Give each job the identity of what makes its product, and its companion files.

    The identity holds the experiment's settings, the calibration file and the two images
    (content hashes), with a ``[preprocess]`` table its dark, white and background (content
    hashes; the batch's own background, ``background``, too), and with ``[mask]`` files
    their content hashes; resume recomputes a product made from anything else, or one whose
    volumes or side products (:func:`_companions`) are missing.
    """
    from dataclasses import replace

    from plenopiv.products.files import file_identity
    from plenopiv.workflow.experiment import settings_identity
    from plenopiv.workflow.provenance import mask_inputs

    common = {"settings": settings_identity(exp), "calibration": file_identity(cal_path)}
    pre = exp.preprocess
    if pre is not None:
        files = {"dark": pre.dark, "white": pre.white, "background": pre.background_path}
        ids = {k: file_identity(exp.path(v)) for k, v in files.items() if v is not None}
        if background is not None:
            ids["background"] = file_identity(background)
        common["preprocess"] = ids
    masks = mask_inputs(exp)
    if masks:
        common["mask"] = masks
    return [replace(j, identity={**common, "image_a": file_identity(j.image_a),
                                 "image_b": file_identity(j.image_b)},
                    companions=_companions(j, exp)) for j in jobs]


def _companions(job, exp) -> tuple:
    """The files a pair writes beside its vectors product (``plenopiv.workflow.worker``)."""
    folder, name = job.output.parent, job.name
    out = [folder / f"{name}_volume_A.h5", folder / f"{name}_volume_B.h5"]
    if exp.output.vtk:
        out.append(job.output.with_suffix(".vti"))
    if exp.output.png:
        out += [folder / f"{name}_volume_A.png", folder / f"{name}_vectors.png"]
    if exp.tracking.enabled:
        out += [folder / f"{name}_tracks.h5", folder / f"{name}_tracks_binned.h5"]
        if exp.output.vtk:
            out += [folder / f"{name}_tracks.vtp", folder / f"{name}_tracks_binned.vti"]
    return tuple(out)


def print_summary(s: dict) -> None:
    """``plenopiv run``: one row per pair, then the totals."""
    rows = [("pair", "status", "valid", "particles A", "time (s)")]
    errors = []
    for r in s.get("results", []):
        res = r.get("result") or {}
        valid = res.get("valid_fraction")
        rows.append((r["name"], r["status"], "-" if valid is None else f"{valid:.0%}",
                     str(res.get("n_particles_a", "-")),
                     f"{r['seconds']:.1f}" if r["status"] == "done" else "-"))
        if r["status"] == "failed":
            errors.append(f"  {r['name']}: {r.get('error_type')}: {r.get('error')}")
    width = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(c.ljust(w) for c, w in zip(row, width, strict=True)).rstrip())
    threads = s.get("threads_per_worker")
    print(f"{s['n_jobs']} pairs: {s['n_done']} done, {s['n_skipped']} skipped, "
          f"{s['n_failed']} failed in {s['seconds']:.1f} s ({s.get('cluster')} cluster, "
          f"{s.get('n_workers') or '?'} workers x {threads or '?'} threads)")
    if errors:
        print("failed:")
        print("\n".join(errors))
    weights = ("from the cache" if s.get("weights_from_cache")
               else f"built in {s.get('weights_s', 0.0):.1f} s")
    print(f"weights: {weights}")
    r = s.get("response")
    if r:
        how = ("from the cache" if r.get("from_cache") else
               f"measured once in {r['seconds']:.1f} s"
               + (f" (estimated {r['estimate_s']:.0f} s)" if "estimate_s" in r else ""))
        print(f"response: {how}, {r['n_particles']} particles per test pair, shared by every "
              "pair")
    print(f"products: {s['out']}  (summary: {s.get('summary_path')})")
