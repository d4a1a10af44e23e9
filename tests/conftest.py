"""Shared fixtures: seeded generators, the small test camera, the third-party data folder.

The repository root goes on ``sys.path`` here, so that the validation studies, which live in
``pipelines/studies/`` and are not installed, import as ``pipelines.studies`` from a plain
clone; the tests that exercise them carry the ``study`` marker.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

from plenopiv.camera.model import load_camera

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
SHARED_DATA = Path(os.environ.get("PLENOPIV_DATA") or REPO.parent / "shared" / "data")


@pytest.fixture
def rng():
    """A seeded generator: every test is deterministic."""
    return np.random.default_rng(20261122)


@pytest.fixture(scope="session")
def small_camera():
    """The 41 × 61-lenslet test camera (135 mm lens, S_i = 200 mm, no substrate)."""
    return load_camera("small_test")


@pytest.fixture(scope="session")
def auburn_camera():
    """The full Auburn camera with the 135 mm lens (193 × 287 lenslets)."""
    return load_camera("auburn_135mm")


#: Where each third-party data set comes from (for the skip message).
DATA_SOURCES = (
    "plenoptomos_letters_ULF/ from https://github.com/cicwi/plenoptomos (examples/data: "
    "letters_ULF_M1*.png, letters_ULF_M1.ini); plenopticam_spots/ from "
    "https://github.com/hahnec/plenopticam (plenopticam/scripts/metrics/calibration: b, c, d "
    ".png and .txt)")


def shared_data_path(*parts) -> Path:
    """A file or folder of the third-party data ../shared/data (or ``$PLENOPIV_DATA``).

    The data are never copied into the repository. A missing folder or file is a failure
    that names it and how to get the data: the tests' known answers (measured lattices of
    real lenslet arrays) would otherwise go unchecked.
    """
    if not SHARED_DATA.is_dir():
        pytest.fail(f"third-party data folder {SHARED_DATA} not found (a clone without the "
                    "project's shared/ folder beside it): put the data there, or point "
                    f"PLENOPIV_DATA at a folder holding them; sources: {DATA_SOURCES}")
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.fail(f"third-party file {path} not found in {SHARED_DATA}: the data folder is "
                    "incomplete")
    return path


@pytest.fixture(scope="session")
def shared_data():
    """The third-party data folder ../shared/data; a clear failure when it is absent."""
    return shared_data_path()
