"""Where a reconstruction with the per-lenslet projector spends its CPU time.

    python benchmarks/bench_real_lattice.py [--geometry rotated|hexagonal] [--lenslets R C]
                                            [--aligned] [--json]

The case of ``benchmarks/full_camera.py`` (Auburn camera, 20,000 particles at full size or
the same density on a ``--lenslets`` patch, grid moved off the footprints by (0.37, 0.61)
voxels, footprint voxels, MLOS + ``--iterations`` SMART sweeps): the projector is built once
and volume A reconstructed twice (the first builds the line-of-sight mask's refined column
sums, the second is what every later volume costs). Every call of the projector's
``forward``, ``back``, ``back_many`` and fused SMART sweep (``smart_sweeper``) is timed
(CPU seconds, both threads) and labelled by its grid (coarse or the mask's refined one) and
by the fraction of non-zero values it was given; "everything else" is the volume's CPU
time less the projector's calls. The last inputs are then replayed: one forward and one
back on their own, and (``--aligned``) one forward and one back of the axis-aligned array's
separable :class:`~plenopiv.reconstruction.lattice.LatticeProjector` on the same grid in
the same process, which gives the ratio of the two projectors.

Prints a table; with ``--json`` the last line is one JSON object. Not a test. The machine's
load average is printed with each figure: CPU times are the figure on a shared machine.
"""

from __future__ import annotations

import argparse
import collections
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from full_camera import full_case, render_pair  # noqa: E402
from full_camera import parser as full_camera_parser  # noqa: E402

from plenopiv.particles.settings import ParticleSettings
from plenopiv.products.jsonio import dumps
from plenopiv.reconstruction.build import weights_for
from plenopiv.reconstruction.real_lattice import LensletProjector
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.workflow.volume import reconstruct_volume


class CallLog:
    """CPU time of every projector call, by kind; keeps the last SMART sweep's inputs."""

    def __init__(self):
        self.rows = collections.defaultdict(lambda: [0, 0.0, 0.0])
        self.last = {}
        self._orig = {}

    def install(self):
        for name in ("forward", "back", "back_many"):
            orig = getattr(LensletProjector, name, None)
            if orig is None:
                continue
            self._orig[name] = orig
            setattr(LensletProjector, name, self._timed(name, orig))
        orig = getattr(LensletProjector, "smart_sweeper", None)
        if orig is not None:
            self._orig["smart_sweeper"] = orig
            log = self

            def sweeper(proj, *args, **kwargs):
                sweep = orig(proj, *args, **kwargs)
                return lambda volume: log._timed("smart_sweep", lambda _p, v: sweep(v))(
                    proj, volume)
            LensletProjector.smart_sweeper = sweeper

    def uninstall(self):
        for name, orig in self._orig.items():
            setattr(LensletProjector, name, orig)

    def _timed(self, name, orig):
        log = self

        def call(proj, data, *args, **kwargs):
            grid = "coarse" if proj.grid.shape == log.coarse_shape else "refined"
            nonzero = float(np.count_nonzero(data)) / max(np.size(data), 1)
            c0 = time.process_time()
            out = orig(proj, data, *args, **kwargs)
            cpu = time.process_time() - c0
            row = log.rows[(name, grid)]
            row[0] += 1
            row[1] += cpu
            row[2] += nonzero
            if grid == "coarse":
                log.last[name] = (proj, np.array(data, copy=True), args, kwargs)
            return out
        return call

    def total(self) -> float:
        return sum(r[1] for r in self.rows.values())

    def table(self) -> list[dict]:
        return [{"call": k[0], "grid": k[1], "n": r[0], "cpu_s": round(r[1], 3),
                 "cpu_per_call_s": round(r[1] / r[0], 3),
                 "mean_nonzero_fraction": round(r[2] / r[0], 4)}
                for k, r in sorted(self.rows.items())]


def cpu_of(fn, repeat=2) -> float:
    """Smallest CPU time of ``repeat`` calls, seconds."""
    best = float("inf")
    for _ in range(repeat):
        c0 = time.process_time()
        fn()
        best = min(best, time.process_time() - c0)
    return best


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--geometry", choices=("rotated", "hexagonal"), default="rotated")
    p.add_argument("--lenslets", type=int, nargs=2, default=None, metavar=("ROWS", "COLS"))
    p.add_argument("--particles", type=int, default=20000)
    p.add_argument("--iterations", type=int, default=5)
    p.add_argument("--aligned", action="store_true",
                   help="also time the aligned array's separable lattice projector")
    p.add_argument("--json", action="store_true")
    own = p.parse_args(argv)
    # the case of full_camera.py with its defaults, the grid moved off the footprints
    args = full_camera_parser().parse_args(["--grid-offset-vox", "0.37", "0.61"])
    vars(args).update(vars(own))
    if args.lenslets:
        args.particles = int(round(args.particles * args.lenslets[0] * args.lenslets[1]
                                   / (193 * 287)))
    cam, cal, case, grid, box, flow = full_case(args)
    settings = ReconstructionSettings(iterations=args.iterations, projector="lattice",
                                      lateral_subdivision=1)
    out: dict = {"geometry": args.geometry, "lenslets": args.lenslets,
                 "grid_shape": list(grid.shape), "particles": args.particles}
    c0 = time.process_time()
    w, _ = weights_for(cal, grid, settings)
    _ = w.normalised
    out["weights_cpu_s"] = round(time.process_time() - c0, 2)
    ia, _ib, _pa, _pb, _ = render_pair(cam, flow, case, box, args.particles, args.rays)
    log = CallLog()
    log.coarse_shape = w.grid.shape
    log.install()
    for run in ("first", "second"):
        log.rows.clear()
        c0 = time.process_time()
        vol = reconstruct_volume(cal, ia, grid, settings=settings,
                                 particles=ParticleSettings(), weights=w)
        cpu = time.process_time() - c0
        out[run] = {"cpu_s": round(cpu, 2), "projector_cpu_s": round(log.total(), 2),
                    "other_cpu_s": round(cpu - log.total(), 2), "calls": log.table(),
                    "occupied_fraction": round(float(np.mean(vol.volume > 0)), 4),
                    "load": round(os.getloadavg()[0], 1)}
        print(f"volume ({run}): {cpu:.1f} s CPU, projector {log.total():.1f} s, "
              f"load {os.getloadavg()[0]:.1f}", file=sys.stderr)
        for row in out[run]["calls"]:
            print(f"  {row['call']:<12s} {row['grid']:<8s} n={row['n']:2d}  "
                  f"{row['cpu_s']:8.2f} s  ({row['cpu_per_call_s']:.3f} s/call, non-zero "
                  f"{row['mean_nonzero_fraction']:.3f})", file=sys.stderr)
    log.uninstall()
    replay = {}
    if "forward" in log.last:
        proj, vol_in, a, k = log.last["forward"]
        replay["forward_cpu_s"] = round(cpu_of(lambda: proj.forward(vol_in)), 3)
        replay["volume_nonzero_fraction"] = round(float(np.mean(vol_in != 0)), 4)
    if "back" in log.last:
        proj, img, a, k = log.last["back"]
        replay["back_cpu_s"] = round(cpu_of(lambda: proj.back(img, *a, **k)), 3)
        replay["back_full_cpu_s"] = round(cpu_of(lambda: proj.back(img)), 3)
        replay["image_nonzero_fraction"] = round(float(np.mean(img != 0)), 4)
    out["replay"] = replay
    print(f"replay: {replay}", file=sys.stderr)
    if args.aligned and "forward" in log.last:
        vol_in = log.last["forward"][1]
        del w, log
        args.geometry = "aligned"
        cam, cal, case, grid_a, box, flow = full_case(args)
        wa, _ = weights_for(cal, grid, settings)
        pa = wa.normalised[0]
        img = np.asarray(pa.forward(vol_in))
        f = cpu_of(lambda: pa.forward(vol_in))
        b = cpu_of(lambda: pa.back(img))
        out["aligned"] = {"projector": type(pa).__name__, "forward_cpu_s": round(f, 3),
                          "back_cpu_s": round(b, 3)}
        for key in ("forward", "back"):
            if f"{key}_cpu_s" in replay:
                out["aligned"][f"{key}_ratio"] = round(replay[f"{key}_cpu_s"]
                                                       / out["aligned"][f"{key}_cpu_s"], 2)
        print(f"aligned: {out['aligned']}", file=sys.stderr)
    if args.json:
        print(dumps(out))
    return out


if __name__ == "__main__":
    main()
