"""Whole-chain accuracy on vortex flows (Lamb-Oseen, Hill) and uniform shifts, the depth
component measured at its true size: gains, biases and rms by distance from the focal plane,
each cause of a flattened w on its own; writes JSON, Markdown and PNG.

    python pipelines/validate_vortex.py --out docs/validation

About 40 minutes on two cores; ``--series causes depth_shifts`` runs only those series on the
41 x 61 CI camera (a few minutes); ``--series depth_response`` how single particles follow
their depth near the focal plane (33 reconstructions).
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.vortex import run
from plenopiv.products.jsonio import dumps

SERIES = ("depth_response", "causes", "flows", "depth_shifts", "lateral_shifts")

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--work", default=None, help="folder for every case's products")
    ap.add_argument("--series", nargs="+", choices=SERIES, default=list(SERIES))
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    print(dumps(run(a.out, work=a.work, seed=a.seed, series=tuple(a.series))))
