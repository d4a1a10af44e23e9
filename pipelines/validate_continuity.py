"""The vector field before and after its depth component is fitted to continuity, on the
real-camera study's pairs and the CI camera's (Oseen, Hill, turned); writes JSON and Markdown.

    python pipelines/validate_continuity.py --out docs/validation [--work DIR]

About 5 minutes on two cores once compiled (21 pairs, each with the correlation's and the
response's uncertainties).
"""

import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.continuity import run
from pipelines.studies.output import pair_study_main

if __name__ == "__main__":
    pair_study_main(__doc__, run, "continuity.md")
