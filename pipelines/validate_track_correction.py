"""The correlation field against the same field corrected by the pair's tracks, on the
real-camera study's pairs and the CI camera's (Oseen, Hill, turned); writes JSON and Markdown.

    python pipelines/validate_track_correction.py --out docs/validation [--work DIR]

About 2 minutes on two cores once compiled (21 pairs, each tracked and corrected with four
priors).
"""

import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.output import pair_study_main
from pipelines.studies.track_correction import run

if __name__ == "__main__":
    pair_study_main(__doc__, run, "track_correction.md")
