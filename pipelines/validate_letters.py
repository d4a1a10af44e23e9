"""Light field on the real plenoptomos letters image: calibration from the white image,
perspective views, parallax and a focus sweep over alpha; writes PNG figures, JSON and Markdown.

    python pipelines/validate_letters.py --out docs/validation

``--data`` names the data folder (default ../shared/data/plenoptomos_letters_ULF).
"""

import argparse
import json
from pathlib import Path

from plenopiv.validation.letters import DATA_NAME, run

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared"
                                          / "data" / DATA_NAME),
                    help="folder holding the letters_ULF_M1 images and .ini")
    a = ap.parse_args()
    print(json.dumps(run(a.out, data_dir=a.data)))
