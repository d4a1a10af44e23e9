"""Merged particles split by their rays: detection, ghosts and position error with the split
off and on, at four densities, three held-out seeds and two brightness spreads; writes JSON
and Markdown.

    python pipelines/validate_merged.py --out docs/validation

About 2 minutes on two cores.
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.merged_particles import run

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    a = ap.parse_args()
    summary = run(a.out)
    print(f"{len(summary['fields'])} fields in {summary['seconds']} s: {a.out}/merged_particles.md")
