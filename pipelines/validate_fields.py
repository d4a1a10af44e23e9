"""Reconstruction quality of synthetic particle fields (Q, detection, ghosts, position error,
depth elongation) against seeding density, MART variant and iterations; writes JSON, Markdown
and PNG figures.

    python pipelines/validate_fields.py --out docs/validation

About 8 minutes on two cores (peak memory about 5 GB); ``--quick`` runs a 31 × 45-lenslet
camera in about a minute.
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.field_quality_report import run
from plenopiv.products.jsonio import dumps

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--quick", action="store_true",
                    help="31 x 45 lenslets, two densities, no voxel-size study")
    ap.add_argument("--seed", type=int, default=20261122)
    a = ap.parse_args()
    if a.quick:
        summary = run(a.out, rows=31, cols=45, densities=(0.05, 0.3), seed=a.seed,
                      voxel_study=False)
    else:
        summary = run(a.out, seed=a.seed)
    print(dumps(summary))
