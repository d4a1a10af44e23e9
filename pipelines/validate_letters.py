"""Light field on the real plenoptomos letters image: calibration from the white image,
perspective views, parallax and a focus sweep over alpha; writes PNG figures, JSON and Markdown.

    python pipelines/validate_letters.py --out docs/validation

``--data`` names the third-party data folder holding plenoptomos_letters_ULF/ (default:
$PLENOPIV_DATA, else ../shared/data beside the current folder or the repository).
"""

import argparse
import sys
from pathlib import Path

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies.letters_data import find_data_dir
from pipelines.studies.letters_report import run
from plenopiv.products.jsonio import dumps

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/validation")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared"
                                          / "data"),
                    help="third-party data folder holding plenoptomos_letters_ULF/")
    a = ap.parse_args()
    print(dumps(run(a.out, data_dir=find_data_dir(a.data))))
