"""Shared fixtures: seeded generators, the small test camera, the third-party data folder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from plenopiv.camera import load_camera

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


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


def shared_data_path(*parts) -> Path:
    """A file or folder of the third-party data ../shared/data.

    The data are never copied into the repository. Their known answers (spot centres, the
    real camera's lattice) are what these tests check, so a missing folder or file is a
    failure that names the path and what is expected there, never a silent skip.
    """
    if not SHARED_DATA.is_dir():
        pytest.fail(f"third-party data folder {SHARED_DATA} not found; these tests need the "
                    "project's shared/ folder beside the repository (see shared/data/README.md)")
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.fail(f"third-party file {path} not found in {SHARED_DATA}: the data folder is "
                    "incomplete")
    return path


@pytest.fixture(scope="session")
def shared_data():
    """The third-party data folder ../shared/data; a clear failure when it is absent."""
    return shared_data_path()
