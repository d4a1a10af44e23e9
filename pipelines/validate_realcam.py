"""The chain on a real recording: an Oseen pair and its calibration on the demo's camera,
ideal and through a real camera (black level, noise, hot pixels, lenslet throughput,
vignetting, glow, brightness, pulse ratio; one at a time and all together), as recorded and
preprocessed; writes JSON, Markdown and PNG.

    python pipelines/validate_realcam.py --out docs/validation

About 7 minutes on two cores for two seeds; ``--effects`` runs only the named effects (with
the ideal case and all of them together), ``--seeds`` the given seeds;
``--calibration-only`` recalibrates the cases of an existing ``realcam.json`` (its S_i, about
4 minutes) and keeps the pair's figures.
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.realcam import EFFECTS, StudyCase
from pipelines.studies.realcam_report import rerun_calibration, run

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--camera-seed", type=int, default=7)
    ap.add_argument("--effects", nargs="+", choices=list(EFFECTS), default=None)
    ap.add_argument("--calibration-only", action="store_true",
                    help="recalibrate the cases of OUT/realcam.json and rewrite its S_i only")
    a = ap.parse_args()
    if a.calibration_only:
        r = rerun_calibration(a.out, setup=StudyCase(camera_seed=a.camera_seed))
        print(f"{len(r['runs'])} seeds recalibrated in {r['calibration_seconds']} s: "
              f"{a.out}/realcam.md")
        sys.exit(0)
    r = run(a.out, setup=StudyCase(camera_seed=a.camera_seed), seeds=a.seeds,
            effects=a.effects)
    print(f"{len(r['runs'])} seeds in {r['seconds']} s: {a.out}/realcam.md")
