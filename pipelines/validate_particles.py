"""Volume particles under noise: detection rates against the threshold and the sub-voxel
estimators' bias and rms, on Gaussian blobs and reconstructed volumes against the truth;
writes ``particle_noise.json`` and ``particle_noise.md``.

    python pipelines/validate_particles.py --out docs/validation

About two minutes on two shared cores.
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.particle_noise import run
from plenopiv.products.jsonio import dumps

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--cache", default=None, help="weight cache folder (default: none)")
    a = ap.parse_args()
    print(dumps(run(a.out, cache_dir=a.cache)))
