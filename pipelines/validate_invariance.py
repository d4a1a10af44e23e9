"""Invariance of the chain to the camera and the flow's orientation: the demo's Oseen case
with its axis along x, y, z or oblique, off-centre, and the camera varied one property at a
time (f-number, image distance, lattice rotation and offset, hexagonal); writes
``invariance.json`` and ``invariance.md``.

    python pipelines/validate_invariance.py --out docs/validation [--seeds 1 2 3] [--no-focus]

About 10 s to a minute per variation and seed on two cores (a rotated or hexagonal lattice
takes explicit weights, the slowest): 20 minutes for three seeds.
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.invariance import FINDINGS, VARIATIONS, run

COMMAND = "python pipelines/validate_invariance.py --out docs/validation"

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--variations", nargs="+", choices=list(VARIATIONS), default=None)
    ap.add_argument("--no-focus", action="store_true",
                    help="leave out the single particles against depth (about 3 minutes)")
    a = ap.parse_args()
    r = run(a.out, seeds=a.seeds, variations=a.variations, command=COMMAND,
            focus=not a.no_focus, notes=FINDINGS)
    print(f"{len(r['runs'])} runs in {r['seconds']} s: {a.out}/invariance.md")
