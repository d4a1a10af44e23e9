"""Solver study: SMART against FISTA, SIRT and clipped CGLS on the same weights and images;
writes solvers.json and the tables of docs/validation/solvers.md.

    python pipelines/validate_solvers.py --out docs/validation

About 20 minutes on two cores for a 21 x 31-lenslet patch, four densities, three seeds;
``--quick`` runs 15 x 21 lenslets, two densities, two seeds.
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.solvers import DENSITIES, equal_cost_study, hybrid_study, study, tables
from plenopiv.products.jsonio import dumps

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--equal-cost", action="store_true",
                    help="SMART and FISTA (with the L1 term) at 40 iterations instead")
    ap.add_argument("--hybrid", action="store_true",
                    help="FISTA as the first guess of SMART, against the default, instead")
    ap.add_argument("--seeds", type=int, nargs="+", default=[20261206, 7, 11])
    ap.add_argument("--lenslets", type=int, nargs=2, default=None, metavar=("ROWS", "COLS"),
                    help="the patch's size (default 21 x 31; 15 x 21 with --quick)")
    ap.add_argument("--camera", default="auburn_50mm",
                    help="preset the patch is cut from (auburn_135mm: the 16 MP camera's "
                         "optics; its results go to solvers_auburn_135mm.json and so on)")
    ap.add_argument("--subdivision", default="1",
                    help="lateral voxels of a footprint / N, scored on them (results go to "
                         "solvers_sub2.json and so on), or \"auto\": footprint voxels "
                         "reconstructed on the working grid the defaults choose and scored "
                         "as returned (solvers_auto.json)")
    a = ap.parse_args()
    if a.subdivision != "auto":
        a.subdivision = int(a.subdivision)
    rows, cols = a.lenslets or ((15, 21) if a.quick else (21, 31))
    densities = (0.1, 0.3) if a.quick else DENSITIES
    seeds = a.seeds[:2] if a.quick else a.seeds
    ap_run = {"equal_cost": equal_cost_study, "hybrid": hybrid_study}
    run = next((ap_run[k] for k in ap_run if getattr(a, k)), study)
    result = run(rows, cols, seeds, densities=densities, preset=a.camera,
                 subdivision=a.subdivision)
    name = "solvers_equal_cost" if a.equal_cost else "solvers_hybrid" if a.hybrid else "solvers"
    if a.camera != "auburn_50mm":
        name += f"_{a.camera}"
    if a.subdivision == "auto":
        name += "_auto"
    elif a.subdivision > 1:
        name += f"_sub{a.subdivision}"
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(dumps(result))
    (out / f"{name}_tables.md").write_text(tables(result))
    print(tables(result))
