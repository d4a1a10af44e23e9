"""Particle tracking against correlation on Oseen and Hill pairs at 0.05-0.3 particles per
lenslet, and ray-bundle against centroid depths of single particles (thesis §5.1); writes
``tracking.json``, ``tracking.md`` and PNG figures.

    python pipelines/validate_tracking.py --out docs/validation

About 15 minutes on two shared cores; ``--quick`` runs 0.15 particles per lenslet only.
"""

import argparse
import json

from plenopiv.validation.tracking_report import run

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--quick", action="store_true", help="0.15 particles per lenslet, one seed")
    a = ap.parse_args()
    if a.quick:
        summary = run(a.out, densities=(0.15,), extra_seeds=())
    else:
        summary = run(a.out)
    print(json.dumps(summary))
