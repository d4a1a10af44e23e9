"""Particle tracking against correlation on Oseen and Hill pairs at 0.05-0.3 particles per
lenslet, and ray-bundle against centroid depths of single particles (thesis §5.1); writes
``tracking.json``, ``tracking.md`` and PNG figures.

    python pipelines/validate_tracking.py --out docs/validation

About 15 minutes on two shared cores; ``--quick`` runs 0.15 particles per lenslet only,
one seed; ``--densities 0.15`` runs the listed densities only (three seeds at 0.15).
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.tracking_report import run
from plenopiv.products.jsonio import dumps

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--quick", action="store_true", help="0.15 particles per lenslet, one seed")
    ap.add_argument("--densities", type=float, nargs="+", default=None,
                    help="particles per lenslet to run (default: the whole sweep)")
    a = ap.parse_args()
    if a.quick:
        summary = run(a.out, densities=(0.15,), extra_seeds=())
    elif a.densities:
        summary = run(a.out, densities=tuple(a.densities))
    else:
        summary = run(a.out)
    print(dumps(summary))
