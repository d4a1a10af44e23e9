"""The vector field before and after its depth component is fitted to continuity, on the
real-camera study's pairs and the CI camera's (Oseen, Hill, turned); writes JSON and Markdown.

    python pipelines/validate_continuity.py --out docs/validation [--work DIR]

About 5 minutes on two cores once compiled (21 pairs, each with the correlation's and the
response's uncertainties).
"""

import argparse
import sys
import tempfile
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.continuity import run

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--work", default=None, help="scratch folder (default: a temporary one)")
    a = ap.parse_args()
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="continuity_"))
    r = run(a.out, work)
    print(f"{sum(len(g) for g in r['groups'].values())} pairs in {r['seconds']} s: "
          f"{a.out}/continuity.md")
