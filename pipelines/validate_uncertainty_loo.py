"""Coverage of the per-vector uncertainty on cases left out of its development (orientation,
seeding, noise, camera), with each term of the model removed in turn; writes JSON and Markdown.

    python pipelines/validate_uncertainty_loo.py --out docs/validation

About a minute per case on two idle cores (22 cases with ``--development``); ``--reuse``
evaluates the saved chains again.
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.uncertainty_loo import CASES, DEVELOPMENT, run
from plenopiv.products.jsonio import dumps

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--work", default=None, help="folder for every case's products")
    ap.add_argument("--reuse", action="store_true", help="evaluate the saved chains again")
    ap.add_argument("--cases", default=None, help="comma-separated indices of CASES")
    ap.add_argument("--development", action="store_true",
                    help="the development cases too (pipelines.studies.uncertainty.CASES)")
    ap.add_argument("--before", default=None,
                    help="uncertainty_loo.json of the same chains under an earlier model")
    a = ap.parse_args()
    cases = CASES if a.cases is None else [CASES[int(i)] for i in a.cases.split(",")]
    cases = list(cases) + (list(DEVELOPMENT) if a.development else [])
    print(dumps(run(a.out, work=a.work, cases=cases, reuse=a.reuse, before=a.before)))
