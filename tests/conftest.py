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
    """A file or folder of the third-party data ../shared/data, or a clear skip when absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not SHARED_DATA.is_dir():
        pytest.skip(f"third-party data folder {SHARED_DATA} not found; these tests need the "
                    "project's shared/ folder beside the repository (see shared/data/README.md)")
    if not path.exists():
        pytest.skip(f"third-party file {path} not found in {SHARED_DATA}")
    return path


@pytest.fixture(scope="session")
def shared_data():
    """The third-party data folder ../shared/data, or a clear skip when it is absent."""
    return shared_data_path()
