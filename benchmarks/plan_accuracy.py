"""How well ``plenopiv plan`` predicts the time and memory of the reconstruction it plans.

Not a unit test. Run ``python benchmarks/plan_accuracy.py [--case small_m1 small_test ...]
[--json]``; each case runs in a fresh process:

1. the plan of the case's box with the defaults and the rates measured in that process
   (:func:`plenopiv.workflow.rates.measure_rates`, as ``plenopiv plan`` does);
2. one reconstruction of a simulated image (0.15 particles per lenslet) on a third of that
   box, to compile the kernels, then on the whole box, timed (wall clock);
3. in another fresh process (the memory a process freed stays resident and would hide a
   second peak), the same reconstruction, and the process's peak resident memory (Linux
   ``VmHWM``: the interpreter and its libraries included, as the plan counts them; the
   kernels load from numba's disk cache).

Printed per case: predicted and measured seconds per volume (the plan's ``reconstruct``:
weights, the recording's check and the volume, as ``plenopiv reconstruct`` runs them) and
GB, and their ratios predicted / measured (the goal: within 0.8-1.2). Both sides run on the
same machine under the same load, since the plan's rates are measured in the same process.

Cases: ``small_m1`` (the demo's camera and box), ``small_test`` (configs/experiments),
``auburn_50mm`` (the 16 MP camera on the demo's box: minutes and several GB), and
``auburn_135mm_aligned`` / ``auburn_135mm_rotated``: the 16 MP camera's whole field of view
and ±26 mm in depth, the volume of ``benchmarks/full_camera.py`` (11 million voxels of
0.26 mm moved off the footprints; the array as made, or turned by 2 mrad: the per-lenslet
projector), 5-10 minutes each.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: case -> (camera preset, experiment file or None: the demo's box, particles per lenslet)
CASES = {
    "small_m1": ("small_m1", None),
    "small_test": ("small_test", ROOT / "configs" / "experiments" / "small_test.toml"),
    "auburn_50mm": ("auburn_50mm", None),
    "auburn_135mm_aligned": ("auburn_135mm", "full_camera:aligned"),
    "auburn_135mm_rotated": ("auburn_135mm", "full_camera:rotated"),
}


def _status_kb(field: str) -> int:
    """A ``/proc/self/status`` field in kB (``VmHWM``: the peak resident memory)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {field}")


def _box(camera, experiment):
    """The case's grid: the experiment's, or the demo's recommended box of the camera."""
    from plenopiv.config.experiment import load_experiment
    from plenopiv.workflow.vortex_case import VortexCase, aligned_grid

    if experiment is not None:
        return load_experiment(experiment).volume
    return aligned_grid(camera, VortexCase())


def _case(name: str):
    """``(calibration, grid)`` of a case: the camera's exact calibration, the case's box."""
    from plenopiv.calibration.model import Calibration
    from plenopiv.camera.model import load_camera

    preset, experiment = CASES[name]
    if isinstance(experiment, str) and experiment.startswith("full_camera:"):
        return _full_camera_case(experiment.split(":")[1])
    cam = load_camera(preset)
    return Calibration.from_camera(cam), _box(cam, experiment)


def _full_camera_case(geometry: str):
    """``(calibration, grid)`` of ``benchmarks/full_camera.py``'s volume on one array."""
    sys.path.insert(0, str(Path(__file__).parent))
    from full_camera import full_case

    args = argparse.Namespace(geometry=geometry, lenslets=None, seed=1, displacement_vox=3.0,
                              grid_offset_vox=(0.37, 0.21), voxel_depth_factor=1.0)
    _cam, cal, _case, grid, _box, _flow = full_case(args)
    return cal, grid


def plan_and_time(name: str, image_path: Path) -> dict:
    """Plan the case, simulate its image (saved to ``image_path``), time its reconstruction."""
    import numpy as np

    from plenopiv.camera.grid import VolumeGrid
    from plenopiv.synthetic.flows import Uniform
    from plenopiv.synthetic.seeding import SeedingBox, simulate_pair
    from plenopiv.workflow import planning, rates
    from plenopiv.workflow.judgement import camera_resolution, lenslets_in_box
    from plenopiv.workflow.volume import reconstruct_volume

    cal, grid = _case(name)
    cam = cal.camera
    from plenopiv.reconstruction.settings import ReconstructionSettings

    t0 = time.perf_counter()
    measured = rates.measure_rates(cam, grid, reconstruction=ReconstructionSettings())
    plan_s = time.perf_counter() - t0
    p = planning.plan(cam, grid, rates=measured)
    b = grid.bounds
    n = int(round(0.15 * lenslets_in_box(camera_resolution(cam), grid)))
    pair = simulate_pair(cam, Uniform((0.0, 0.0, 0.0)), dt=1e-3,
                         box=SeedingBox(tuple(b[0]), tuple(b[1]), tuple(b[2])),
                         n_particles=n, rng=np.random.default_rng(1), rays_per_particle=1024)
    image = np.asarray(pair.image_a, float)
    np.save(image_path, image)
    third = VolumeGrid.from_bounds(*(tuple(lo + (hi - lo) * f for f in (1 / 3, 2 / 3))
                                      for lo, hi in b), voxel=grid.voxel)
    reconstruct_volume(cal, image, third)
    t0 = time.perf_counter()
    reconstruct_volume(cal, image, grid)
    seconds = time.perf_counter() - t0
    predicted_s = p.time["reconstruct"]
    predicted_gb = max(p.memory["reconstruct_peak"], p.memory["weights_build_peak"]) / 1e9
    return {"case": name, "shape": list(grid.shape), "particles": n,
            "projector": p.decision.projector, "time_model": p.time_model,
            "predicted_s": predicted_s, "measured_s": seconds,
            "time_ratio": predicted_s / seconds, "predicted_gb": predicted_gb,
            "rates_s": plan_s, "rehearsed": measured.rehearsal is not None,
            "predicted_stages_s": p.time}


def peak_memory(name: str, image_path: Path) -> dict:
    """The peak resident memory of a process that reconstructs the case, GB."""
    import numpy as np

    from plenopiv.workflow.volume import reconstruct_volume

    cal, grid = _case(name)
    image = np.load(image_path)
    reconstruct_volume(cal, image, grid)
    return {"measured_gb": _status_kb("VmHWM") * 1024 / 1e9}


def _child(role: str, name: str, image_path: Path) -> dict:
    """Run ``role`` ("time" or "memory") of a case in a fresh process; its figures."""
    run = subprocess.run([sys.executable, __file__, "--child", role, name, str(image_path)],
                         capture_output=True, text=True)
    if run.returncode != 0:
        raise RuntimeError(f"the {role} run of {name} failed:\n{run.stderr[-3000:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


def run_case(name: str) -> dict:
    """The figures of one case: planned, timed, and its memory in a fresh process."""
    with tempfile.TemporaryDirectory() as tmp:
        image_path = Path(tmp) / "image.npy"
        row = _child("time", name, image_path)
        row.update(_child("memory", name, image_path))
    row["memory_ratio"] = row["predicted_gb"] / row["measured_gb"]
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", nargs="+", choices=sorted(CASES),
                        default=["small_m1", "small_test"])
    parser.add_argument("--json", action="store_true", help="one JSON object per case")
    parser.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        from plenopiv.resources import own_process_memory

        own_process_memory()            # the process set up as the plenopiv command sets it
        role, name, image_path = args.child
        work = plan_and_time if role == "time" else peak_memory
        print(json.dumps(work(name, Path(image_path))))
        return 0
    for name in args.case:
        row = run_case(name)
        if args.json:
            print(json.dumps(row))
            continue
        print(f"{name}: {row['shape']} voxels, {row['particles']} particles, "
              f"{row['projector']} projector ({row['time_model']})")
        print(f"  time   predicted {row['predicted_s']:8.2f} s  measured "
              f"{row['measured_s']:8.2f} s  ratio {row['time_ratio']:.2f}")
        print(f"  memory predicted {row['predicted_gb']:8.3f} GB measured "
              f"{row['measured_gb']:8.3f} GB ratio {row['memory_ratio']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
