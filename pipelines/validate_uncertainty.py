"""Coverage of the per-vector uncertainty (share of true errors within ±2σ, per component) on
the vortex validations: Oseen and Hill, two lateral voxels, two seedings, two camera patches,
two seeds, and two configurations on six seeds each; writes JSON, Markdown and a figure.

    python pipelines/validate_uncertainty.py --out docs/validation

About 14 minutes on two idle cores (ten cases, then nine more realisations).
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.uncertainty import CASES, run
from plenopiv.products.jsonio import dumps

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--work", default=None, help="folder for every case's products")
    ap.add_argument("--quick", action="store_true",
                    help="the two footprint-voxel CI cases, no realisations")
    a = ap.parse_args()
    summary = run(a.out, work=a.work, cases=CASES[:2] if a.quick else CASES,
                  **({"realisations": ()} if a.quick else {}))
    print(dumps(summary))
