"""Pure helpers of the vortex study's near-focus depth response (no reconstruction)."""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.studies.vortex import (
    FROZEN_RESPONSE,
    RESPONSE_BANDS_MM,
    column_depth,
    response_by_band,
)

pytestmark = pytest.mark.study


def test_column_depth_is_the_intensity_weighted_depth_of_the_column():
    vol = np.zeros((30, 5, 5), np.float32)
    vol[12, 2, 2] = 1.0
    vol[15, 1, 3] = 3.0                  # inside the 3 x 3 column about (2, 2)
    vol[14, 0, 0] = 100.0                # outside it
    assert column_depth(vol, (2, 2, 13)) == (12 * 1 + 15 * 3) / 4
    assert np.isnan(column_depth(np.zeros_like(vol), (2, 2, 13)))
    # cut at the volume's face: the column starts at index 0
    vol0 = np.zeros((30, 5, 5), np.float32)
    vol0[1, 2, 2] = 2.0
    assert column_depth(vol0, (2, 2, 3)) == 1.0


def test_response_by_band_separates_frozen_and_moving_particles():
    # two particles: one follows its depth exactly, one keeps a fixed reconstructed depth
    # within 0.25 mm of focus and follows beyond it
    depth_vox = 0.125e-3
    z_mm = np.arange(-1.0, 1.0001, 0.0625)
    true_vox = z_mm / 0.125
    follows = np.zeros_like(z_mm)
    frozen = np.where(np.abs(z_mm) <= 0.25, -true_vox, 0.0)   # reconstructed depth 0 there
    bands = response_by_band(z_mm, depth_vox, np.stack([follows, frozen], axis=1))
    assert [b["abs_z_mm"] for b in bands] == [list(b) for b in RESPONSE_BANDS_MM]
    near = bands[0]
    assert near["frozen_share"] == 0.5 and near["median"] == 0.5
    assert abs(near["mean"] - 0.5) < 1e-9
    for far in bands[2:]:
        assert far["frozen_share"] == 0.0 and abs(far["mean"] - 1.0) < 1e-9
    assert FROZEN_RESPONSE < 0.5
