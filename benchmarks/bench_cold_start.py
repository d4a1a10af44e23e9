"""Benchmark: the cost of the first ``plenopiv demo`` on a machine (numba compilation).

Runs ``plenopiv demo`` twice in child processes that share one new, empty cache folder
(``PLENOPIV_CACHE_DIR``; ``NUMBA_CACHE_DIR`` is removed from their environment so that the
package's own choice applies): the first run ("cold") compiles every numba kernel the demo
uses and writes it to the cache (the reconstruction's and the PIV's in two background
processes while it calibrates, :mod:`plenopiv.workflow.precompile`), the second ("warm") loads them.
The baseline, in the same run: a cold demo in a third, empty cache folder with
``--no-precompile`` (every kernel compiled in the demo's own process, one after another).
For each it prints the wall time, the CPU time of the child and its descendants (user +
sys, ``getrusage(RUSAGE_CHILDREN)``), the load average when it started, the demo's rms error
and its own wall time per stage (calibration, the pair's two reconstructions, the PIV with
the response uncertainty's test pairs); then the ratios cold/warm, the first-run cost
(cold - warm) and cold against the baseline. On a shared machine wall times are
inflated by the other work, CPU times much less: compare CPU times, and read wall times next
to the load average.

The honest "fresh machine" figure needs a fresh environment too (no ``__pycache__`` of the
dependencies, no OS file cache): install into a new venv and point ``--plenopiv`` at it::

    python -m venv /tmp/v && /tmp/v/bin/pip install .
    python benchmarks/bench_cold_start.py --plenopiv /tmp/v/bin/plenopiv

Usage::

    python benchmarks/bench_cold_start.py [--plenopiv PATH] [--runs 2] [--keep] [--no-baseline]

``--plenopiv`` defaults to ``python -m plenopiv.cli`` of this interpreter; ``--runs`` counts
the cold run (2: cold then warm); ``--keep`` keeps the cache and output folders;
``--no-baseline`` skips the baseline.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time


def run_once(command: list[str], env: dict[str, str], out: str, options=()) -> dict:
    """One demo in a child process: exit status, wall s, load average, its output."""
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen([*command, "demo", "--out", out, "--json", "--quiet", *options],
                            env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stdout, stderr = proc.communicate()
    wall = time.perf_counter() - t0
    return {"returncode": proc.returncode, "wall_s": wall, "load": load,
            "stdout": stdout, "stderr": stderr}


def measure(command: list[str], runs: int, keep: bool, options=()) -> list[dict]:
    """``runs`` demos sharing one empty cache folder; a list of figures per run."""
    base = tempfile.mkdtemp(prefix="plenopiv_cold_")
    env = dict(os.environ, PLENOPIV_CACHE_DIR=os.path.join(base, "cache"))
    env.pop("NUMBA_CACHE_DIR", None)
    results = []
    try:
        for k in range(runs):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            r = run_once(command, env, os.path.join(base, f"demo_{k}"), options)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            r["user_s"] = after.ru_utime - before.ru_utime
            r["sys_s"] = after.ru_stime - before.ru_stime
            r["cpu_s"] = r["user_s"] + r["sys_s"]
            r["maxrss_mb"] = after.ru_maxrss / 1024.0      # the largest child so far (Linux: kB)
            if r["returncode"] != 0:
                raise SystemExit(f"demo failed (exit {r['returncode']}):\n{r['stderr'][-2000:]}")
            summary = json.loads(r["stdout"])
            r["summary"] = {key: summary.get(key) for key in ("valid_fraction", "rms_error_vox",
                                                              "bias_vox", "seconds",
                                                              "stage_seconds")}
            results.append(r)
    finally:
        if keep:
            print(f"kept {base}")
        else:
            shutil.rmtree(base, ignore_errors=True)
    return results


def _row(name: str, r: dict) -> str:
    rms = " ".join(f"{v:.3f}" for v in r["summary"]["rms_error_vox"])
    stages = r["summary"].get("stage_seconds") or {}
    per_stage = ", ".join(f"{key} {stages[key]:.1f}" for key in
                          ("calibrate", "simulate", "reconstruct", "piv", "total")
                          if key in stages)
    return (f"{name:<9} {r['wall_s']:8.1f} {r['cpu_s']:8.1f} {r['user_s']:8.1f} "
            f"{r['sys_s']:7.1f} {r['load']:6.1f} {rms:>24}   {per_stage}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plenopiv", default=None,
                        help="the plenopiv command to time (default: python -m plenopiv.cli)")
    parser.add_argument("--runs", type=int, default=2, help="runs, the cold one included")
    parser.add_argument("--keep", action="store_true", help="keep the cache and outputs")
    parser.add_argument("--no-baseline", dest="baseline", action="store_false",
                        help="skip the cold run with --no-precompile")
    args = parser.parse_args()
    command = [args.plenopiv] if args.plenopiv else [sys.executable, "-m", "plenopiv.cli"]
    results = measure(command, max(args.runs, 1), args.keep)
    baseline = measure(command, 1, args.keep, ("--no-precompile",)) if args.baseline else []
    print(f"cores {os.cpu_count()}; command {' '.join(command)}")
    print(f"{'run':<9} {'wall s':>8} {'CPU s':>8} {'user s':>8} {'sys s':>7} "
          f"{'load':>6} {'rms error (vox, z y x)':>24}   demo's wall s per stage")
    for k, r in enumerate(results):
        print(_row("cold" if k == 0 else f"warm{k}" if len(results) > 2 else "warm", r))
    for r in baseline:
        print(_row("cold, 1 p", r))
    if len(results) > 1:
        cold, warm = results[0], results[1]
        print(f"cold/warm: wall {cold['wall_s'] / warm['wall_s']:.2f}, "
              f"CPU {cold['cpu_s'] / warm['cpu_s']:.2f}; "
              f"first-run cost (cold - warm): CPU {cold['cpu_s'] - warm['cpu_s']:.1f} s, "
              f"wall {cold['wall_s'] - warm['wall_s']:.1f} s")
    if baseline:
        print(f"cold with background compilation / cold in one process ('cold, 1 p', "
              f"--no-precompile): wall {results[0]['wall_s'] / baseline[0]['wall_s']:.2f}, "
              f"CPU {results[0]['cpu_s'] / baseline[0]['cpu_s']:.2f}")


if __name__ == "__main__":
    main()
