"""Throughput of plenopiv.batch: the same CPU-bound jobs on 1 and on 2 worker processes.

Run: ``python benchmarks/bench_batch.py [--jobs 8] [--seconds 1.0] [--workers 1 2]``

Each job does about ``--seconds`` of single-threaded NumPy FFT work (forward and inverse 3-D
FFTs of a 64³ float64 volume, repeated; the repeat count is calibrated once in this process),
then writes a tiny product and marks it complete, as a real ``process`` must. Every worker
runs one job at a time with its numba/BLAS/OpenMP threads pinned to 1 by ``run_batch``.

Two figures per worker count:

- jobs/s (compute): jobs divided by the span from the first job's start to the last job's
  end, measured on the workers. This is the batch's steady-state throughput.
- jobs/s (wall): jobs divided by the whole ``run_batch`` call, cluster start and stop
  included (a fixed few seconds, which a real batch of hundreds of pairs amortises).

- busy: the summed job times divided by the span, i.e. how many workers were running a job
  on average. It shows the batch machinery's overhead whatever else the machine does: close
  to the worker count means the workers were never left waiting.

The ratio of the compute throughputs (2 workers / 1 worker) is the parallel efficiency on two
cores: 2.0 is perfect; the goal is at least 1.8. Other work on the machine lowers it: the
1-minute load average before each run is printed (``load``); trust figures taken with load
well below 1. Nothing is asserted; figures are printed.

``--pipeline N`` instead runs N simulated pairs of the small camera through ``plenopiv run``'s
per-pair work (:class:`plenopiv.workflow.worker.ExperimentPairProcess`) on one worker and prints
each pair's time: the first pair of a worker loads the experiment, the calibration and builds its
projector (and compiles the kernels), the later ones reuse them.

``--camera auburn_135mm`` runs the pairs on the full-size benchmark camera instead (3280 × 4904
px, the 287 × 193 × 201-voxel volume of ``benchmarks/full_camera.py`` moved off the footprints
by (0.37, 0.21) voxels, its 20,000-particle Lamb-Oseen pair, rendered once and cached in
``benchmarks/_cache/``; every job reads that same pair, so every pair does the same work),
``--lateral-subdivision`` (default 1: the footprint voxels), its PIV (32³ then 16³ voxels, 3
passes, 50 % overlap) with ``uncertainty = "correlation"``. ``--no-reuse`` makes every pair
start from nothing in the same worker process (the experiment, the calibration and the
projector loaded and built again: what each pair cost before the worker kept them);
``--compare`` runs the pairs with reuse and then without, in one table. Each row: the pair's
wall time in the worker, its CPU time (the worker process, all threads) and its
reconstruction time (projector build included).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from plenopiv.batch import run_batch
from plenopiv.batch.jobs import PairJob, mark_complete
from plenopiv.products.hdf5 import write_h5

SHAPE = (64, 64, 64)


def fft_round(volume: np.ndarray) -> float:
    """One unit of work: forward and inverse FFT, returns a checksum."""
    return float(np.fft.ifftn(np.fft.fftn(volume)).real[0, 0, 0])


def fft_job(job: PairJob, *, repeats: int) -> dict:
    """About ``repeats`` units of FFT work, then a tiny complete product."""
    rng = np.random.default_rng(abs(hash(job.name)) % 2**32)
    vol = rng.standard_normal(SHAPE)
    t0 = time.process_time()
    acc = 0.0
    for _ in range(repeats):
        acc += fft_round(vol)
    cpu = time.process_time() - t0
    write_h5(job.output, {"/checksum": np.array([acc])}, kind="benchmark")
    mark_complete(job.output)
    return {"cpu_s": cpu, "pid": os.getpid()}


def calibrate(seconds: float) -> tuple[int, float]:
    """Repeats of :func:`fft_round` that take about ``seconds`` here (single thread)."""
    vol = np.random.default_rng(0).standard_normal(SHAPE)
    fft_round(vol)
    n, t = 1, 0.0
    while t < 0.2:
        t0 = time.perf_counter()
        for _ in range(n):
            fft_round(vol)
        t = time.perf_counter() - t0
        n *= 2
    per = t / (n // 2)
    return max(1, math.ceil(seconds / per)), per


def run(n_workers: int, n_jobs: int, repeats: int, folder: Path) -> dict:
    jobs = [PairJob(f"job_{i:03d}", "unused_a", "unused_b", folder / f"job_{i:03d}.h5")
            for i in range(n_jobs)]
    process = functools.partial(fft_job, repeats=repeats)
    load = os.getloadavg()[0]
    s = run_batch(jobs, process, n_workers=n_workers, threads_per_worker=1, resume=False,
                  progress=False)
    if s.failed:
        raise SystemExit(f"benchmark jobs failed: {s.failed}")
    starts = [r.start for r in s.results]
    ends = [r.end for r in s.results]
    span = max(ends) - min(starts)
    per_job = [r.seconds for r in s.results]
    return {"workers": n_workers, "load": load, "wall_s": s.seconds, "span_s": span,
            "jobs_per_s_compute": n_jobs / span, "jobs_per_s_wall": n_jobs / s.seconds,
            "job_s_mean": float(np.mean(per_job)), "busy": float(np.sum(per_job)) / span,
            "cpu_s_mean": float(np.mean([r.result["cpu_s"] for r in s.results])),
            "pids": len({r.pid for r in s.results})}


@dataclasses.dataclass(frozen=True)
class TimedPairProcess:
    """``plenopiv run``'s per-pair work, timed in the worker (wall and CPU seconds).

    ``reuse=False`` drops the worker's kept :class:`plenopiv.workflow.pair.PairProcessor` before
    every pair, so that each pair loads the experiment and the calibration and builds the
    projector again, as every pair did before the worker kept them.
    """

    process: object
    reuse: bool = True

    def __call__(self, job) -> dict:
        from plenopiv import pipeline

        if not self.reuse:
            pipeline.drop_worker_processor()
        t0, c0 = time.perf_counter(), time.process_time()
        out = self.process(job)
        return {**out, "pair_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}


def small_camera_case(n_pairs: int, folder: Path) -> None:
    """Calibration, ``n_pairs`` simulated pairs and the experiment of the small camera."""
    from plenopiv.calibration.model import Calibration
    from plenopiv.camera.model import load_camera
    from plenopiv.cli import main as cli

    Calibration.from_camera(load_camera("small_m1")).save(folder / "cal.h5")
    (folder / "pairs").mkdir()
    for i in range(n_pairs):
        cli(["simulate", "pair", "small_m1", "--n-particles", "30", "--rays-per-particle",
             "256", "--depth-mm", "-1.5", "1.5", "--fill", "0.4", "--seed", str(i + 1),
             "--no-tiff", "--quiet", "--out", str(folder / "pairs" / f"run_{i + 1}.h5")])
    (folder / "exp.toml").write_text(
        'camera = "small_m1"\n[volume]\nx_mm = [-1.0625, 1.0625]\ny_mm = [-1.0625, 1.0625]\n'
        'z_mm = [-1.5, 1.5]\nvoxel_mm = 0.125\n[piv]\nwindows = [[12, 12, 12]]\npasses = 2\n'
        '[images]\npairs = "pairs/*.h5"\ncalibration = "cal.h5"\ndt_s = 1e-3\n'
        '[output]\ndirectory = "out"\npng = false\nvtk = false\n')


def full_camera_case(n_pairs: int, folder: Path, lateral_subdivision: str) -> None:
    """Calibration, pairs and experiment of the full-size benchmark camera (auburn_135mm).

    The pair, grid and PIV of ``benchmarks/full_camera.py`` (its default arguments, the
    aligned lenslet array); every one of the ``n_pairs`` jobs reads the same pair.
    """
    import types

    sys.path.insert(0, str(Path(__file__).parent))
    import full_camera as fc

    from plenopiv.products.hdf5 import write_h5

    args = types.SimpleNamespace(geometry="aligned", lenslets=None, seed=1,
                                 displacement_vox=3.0, grid_offset_vox=(0.37, 0.21))
    cam, cal, case, grid, box, flow = fc.full_case(args)
    ia, ib, _, _, _ = fc.render_pair(cam, flow, case, box, 20000, 2048)
    cal.save(folder / "cal.h5")
    (folder / "pairs").mkdir()
    write_h5(folder / "pairs" / "pair.h5", {"/image_a": np.asarray(ia, np.float32),
                                            "/image_b": np.asarray(ib, np.float32)},
             kind="benchmark", compress=False)
    for i in range(n_pairs):
        os.link(folder / "pairs" / "pair.h5", folder / "pairs" / f"run_{i + 1}.h5")
    g = grid.to_dict()
    sub = lateral_subdivision if lateral_subdivision == "auto" else int(lateral_subdivision)
    (folder / "exp.toml").write_text(
        f'camera = "auburn_135mm"\n[volume]\nx_mm = {g["x_mm"]}\ny_mm = {g["y_mm"]}\n'
        f'z_mm = {g["z_mm"]}\nshape = {g["shape"]}\n'
        f'[reconstruction]\niterations = 5\nlateral_subdivision = {sub!r}\n'
        '[piv]\nwindows = [[32, 32, 32], [16, 16, 16]]\noverlap = 0.5\npasses = 3\n'
        'uncertainty = "correlation"\n'
        f'[images]\npairs = "pairs/*.h5"\ncalibration = "cal.h5"\ndt_s = {case.dt}\n'
        '[output]\ndirectory = "out"\npng = false\nvtk = false\n'.replace("'", '"'))


def pipeline_pairs(n_pairs: int, folder: Path, *, camera: str = "small_m1",
                   reuse=(True,), threads: int = 1,
                   lateral_subdivision: str = "1") -> dict:
    """Per-pair times of ``plenopiv run``'s work on real pairs, in the order they ran.

    ``camera="small_m1"``: ``n_pairs`` simulated pairs of the small camera (30 particles,
    3 mm deep), the default reconstruction (SMART on a laterally subdivided grid: the
    matrix-free projector, never cached on disk), no weights cache. ``"auburn_135mm"``: the
    full-size case of :func:`full_camera_case`. One worker of ``threads`` threads, a fresh
    worker process per entry of ``reuse``. Returns ``{reuse: rows}``; each row: the pair's
    wall and CPU time in the worker and its reconstruction time (``reconstruct_s``, projector
    included).
    """
    from plenopiv.workflow.worker import ExperimentPairProcess

    if camera == "small_m1":
        small_camera_case(n_pairs, folder)
    else:
        full_camera_case(n_pairs, folder, lateral_subdivision)
    out = {}
    for keep in reuse:
        tag = "reuse" if keep else "no_reuse"
        jobs = [PairJob(f"run_{i + 1}", f"{folder}/pairs/run_{i + 1}.h5:/image_a",
                        f"{folder}/pairs/run_{i + 1}.h5:/image_b",
                        folder / tag / f"run_{i + 1}_vectors.h5") for i in range(n_pairs)]
        (folder / tag).mkdir()
        process = TimedPairProcess(ExperimentPairProcess(
            str(folder / "exp.toml"), str(folder / "cal.h5"), str(folder / tag)), keep)
        s = run_batch(jobs, process, n_workers=1, threads_per_worker=threads, resume=False,
                      progress=False)
        if s.failed:
            raise SystemExit(f"pairs failed: {s.failed}")
        done = sorted(s.results, key=lambda r: r.start)
        out[keep] = [{"pair": r.name, "seconds": r.result["pair_s"], "cpu_s": r.result["cpu_s"],
                      "reconstruct_s": r.result.get("reconstruct_s"),
                      "piv_s": r.result.get("piv_s")} for r in done]
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=8, help="jobs per batch (default 8)")
    ap.add_argument("--seconds", type=float, default=1.0,
                    help="work per job, seconds of one core (default 1.0)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2],
                    help="worker counts to compare (default 1 2)")
    ap.add_argument("--pipeline", type=int, metavar="N_PAIRS",
                    help="instead: per-pair times of N_PAIRS real pairs through plenopiv "
                         "run's per-pair work on one worker (first pair and later ones)")
    ap.add_argument("--camera", choices=["small_m1", "auburn_135mm"], default="small_m1",
                    help="with --pipeline: the small camera (default) or the full-size "
                         "benchmark camera (16 MP, the pair of benchmarks/full_camera.py)")
    ap.add_argument("--lateral-subdivision", default="1",
                    help="with --camera auburn_135mm: [reconstruction] lateral_subdivision "
                         "(default 1, the footprint voxels; 'auto' for the library default)")
    ap.add_argument("--threads", type=int, default=1,
                    help="with --pipeline: threads of the one worker (default 1)")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--no-reuse", action="store_true",
                      help="with --pipeline: every pair loads the experiment and the "
                           "calibration and builds the projector again (the before)")
    mode.add_argument("--compare", action="store_true",
                      help="with --pipeline: the pairs with reuse, then without, one table")
    args = ap.parse_args()
    if args.pipeline:
        reuse = (True, False) if args.compare else ((False,) if args.no_reuse else (True,))
        print(f"{args.pipeline} pairs, camera {args.camera}, one worker of {args.threads} "
              f"thread(s), load {os.getloadavg()[0]:.1f}", flush=True)
        with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
            runs = pipeline_pairs(args.pipeline, Path(tmp), camera=args.camera, reuse=reuse,
                                  threads=args.threads,
                                  lateral_subdivision=args.lateral_subdivision)
        for keep, rows in runs.items():
            tag = "with reuse" if keep else "no reuse"
            for r in rows:
                print(f"{tag:>10} {r['pair']:>8} {r['seconds']:8.2f} s in the pair "
                      f"(cpu {r['cpu_s']:8.2f} s), reconstruct {r['reconstruct_s']:7.2f} s, "
                      f"piv {r['piv_s']:6.2f} s")
            later = rows[1:]
            if later:
                print(f"{tag:>10}: first pair {rows[0]['seconds']:.2f} s (cpu "
                      f"{rows[0]['cpu_s']:.2f} s); later pairs "
                      f"{np.mean([r['seconds'] for r in later]):.2f} s (cpu "
                      f"{np.mean([r['cpu_s'] for r in later]):.2f} s) on average "
                      f"(load {os.getloadavg()[0]:.1f})", flush=True)
        return

    repeats, per = calibrate(args.seconds)
    print(f"cores: {len(os.sched_getaffinity(0))}; job = {repeats} × fftn+ifftn of "
          f"{SHAPE} float64 ({per * 1e3:.1f} ms each, ≈ {repeats * per:.2f} s)")
    print(f"{'workers':>7} {'load':>5} {'jobs':>5} {'wall s':>7} {'span s':>7} {'job s':>6} "
          f"{'cpu s':>6} {'procs':>5} {'busy':>5} {'jobs/s compute':>15} {'jobs/s wall':>12}")
    rows = {}
    with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
        for w in args.workers:
            r = run(w, args.jobs, repeats, Path(tmp) / f"w{w}")
            rows[w] = r
            print(f"{w:>7} {r['load']:>5.2f} {args.jobs:>5} {r['wall_s']:>7.2f} "
                  f"{r['span_s']:>7.2f} {r['job_s_mean']:>6.2f} {r['cpu_s_mean']:>6.2f} "
                  f"{r['pids']:>5} {r['busy']:>5.2f} "
                  f"{r['jobs_per_s_compute']:>15.3f} {r['jobs_per_s_wall']:>12.3f}")
    if 1 in rows and len(rows) > 1:
        for w, r in rows.items():
            if w == 1:
                continue
            print(f"speed-up {w} workers / 1 worker: compute "
                  f"{r['jobs_per_s_compute'] / rows[1]['jobs_per_s_compute']:.2f}×, wall "
                  f"{r['jobs_per_s_wall'] / rows[1]['jobs_per_s_wall']:.2f}× (goal ≥ 1.8×)")


if __name__ == "__main__":
    main()
