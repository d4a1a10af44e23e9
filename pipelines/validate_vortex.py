"""Whole-chain accuracy on vortex flows (Lamb-Oseen, Hill) against the size of the flow and the
lateral voxel, and the sub-voxel response to uniform shifts; writes JSON, Markdown and PNG.

    python pipelines/validate_vortex.py --out docs/validation

About 6 minutes on two cores; ``--quick`` runs the CI camera only (about a minute).
"""

import argparse
import json

from plenopiv.validation.vortex_study import SCALES, run

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--work", default=None, help="folder for every case's products")
    ap.add_argument("--quick", action="store_true", help="the CI camera only, three shifts")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    if a.quick:
        summary = run(a.out, work=a.work, seed=a.seed, scales=SCALES[:1],
                      shifts=(1.0, 1.25, 1.5), oversampled=())
    else:
        summary = run(a.out, work=a.work, seed=a.seed)
    print(json.dumps(summary))
