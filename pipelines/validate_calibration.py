"""Reproduce the thesis's synthetic calibration studies (Fig 3.8, Fig 3.9 / Table 5.3,
Fig 5.5) with the project's ray tracer; writes tables and PNG figures.

    python pipelines/validate_calibration.py --out docs/validation
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.calibration import run
from plenopiv.products.jsonio import dumps

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--repeats", type=int, default=20, help="noise realisations per case")
    a = ap.parse_args()
    print(dumps(run(a.out, repeats=a.repeats)))
