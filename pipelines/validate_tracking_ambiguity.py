"""Wrong matches against the tracked fraction over the tracking's ratio test, Oseen pairs at
0.1-0.3 particles per lenslet, vortex axis along x and y; writes ``tracking_ambiguity.json``
and ``tracking_ambiguity.md``.

    python pipelines/validate_tracking_ambiguity.py --out docs/validation [--jobs 2] [--quick]

``--quick`` runs 0.15 particles per lenslet only, seed 1, both axes.
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.tracking_ambiguity_report import CASES, run
from plenopiv.products.jsonio import dumps

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="0.15 per lenslet, seed 1, x and y")
    a = ap.parse_args()
    cases = tuple(c for c in CASES if c[0] == 0.15 and c[1] == 1) if a.quick else CASES
    print(dumps(run(a.out, cases=cases, jobs=a.jobs)))
