"""Reproduce the thesis's depth study (§5.1-5.2: Table 5.1, Table 5.2, Figs 5.2-5.4) with the
project's ray tracer and reconstruction; writes tables (JSON, Markdown) and PNG figures.

    python pipelines/validate_depth.py --out docs/validation

About 15 minutes on two cores (5 cases × 21 depths, a few seconds per reconstruction).
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.depth_report import run
from plenopiv.products.jsonio import dumps

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--rays", type=int, default=20000, help="ray-tracer samples per particle")
    ap.add_argument("--no-diagnostics", action="store_true",
                    help='skip the "thesis" back side with the default light-field aperture')
    a = ap.parse_args()

    def progress(case, seconds):
        print(f"{case}: {seconds:.0f} s", file=sys.stderr, flush=True)

    print(dumps(run(a.out, rays_per_particle=a.rays, diagnostics=not a.no_diagnostics,
                         progress=progress)))
