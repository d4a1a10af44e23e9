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
per-pair work (:class:`plenopiv.pipeline.ExperimentPairProcess`) on one worker and prints each
pair's time: the first pair of a worker loads the experiment, the calibration and builds its
projector (and compiles the kernels), the later ones reuse them.
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from plenopiv.batch import PairJob, mark_complete, run_batch
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


def pipeline_pairs(n_pairs: int, folder: Path) -> list[dict]:
    """Per-pair times of ``plenopiv run``'s work on real pairs, in the order they ran.

    ``n_pairs`` simulated pairs of the small camera (30 particles, 3 mm deep), the default
    reconstruction (SMART on a laterally subdivided grid: the matrix-free projector, never
    cached on disk), no weights cache; one worker, one thread. Each row: the pair's wall time
    in the process and its reconstruction time (``reconstruct_s``, projector included).
    """
    from plenopiv.calibration.model import Calibration
    from plenopiv.camera import load_camera
    from plenopiv.cli import main as cli
    from plenopiv.pipeline import ExperimentPairProcess

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
    jobs = [PairJob(f"run_{i + 1}", f"{folder}/pairs/run_{i + 1}.h5:/image_a",
                    f"{folder}/pairs/run_{i + 1}.h5:/image_b",
                    folder / "out" / f"run_{i + 1}_vectors.h5") for i in range(n_pairs)]
    (folder / "out").mkdir()
    process = ExperimentPairProcess(str(folder / "exp.toml"), str(folder / "cal.h5"),
                                    str(folder / "out"))
    s = run_batch(jobs, process, n_workers=1, threads_per_worker=1, resume=False,
                  progress=False)
    if s.failed:
        raise SystemExit(f"pairs failed: {s.failed}")
    done = sorted(s.results, key=lambda r: r.start)
    return [{"pair": r.name, "seconds": r.seconds,
             "reconstruct_s": r.result.get("reconstruct_s")} for r in done]


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
    args = ap.parse_args()
    if args.pipeline:
        with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
            rows = pipeline_pairs(args.pipeline, Path(tmp))
        for r in rows:
            print(f"{r['pair']:>8} {r['seconds']:7.2f} s in the pair, reconstruct "
                  f"{r['reconstruct_s']:6.2f} s")
        later = [r["seconds"] for r in rows[1:]]
        if later:
            print(f"first pair {rows[0]['seconds']:.2f} s; later pairs "
                  f"{np.mean(later):.2f} s on average (load {os.getloadavg()[0]:.1f})")
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
