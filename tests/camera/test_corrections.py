"""Depth corrections: factors per camera, exact inverse, particle tables."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plenopiv.camera.corrections import DepthCorrection
from plenopiv.camera.model import ExternalInterface, Substrate
from plenopiv.errors import ConfigError


def test_factors_per_camera(small_camera):
    assert DepthCorrection.for_camera(small_camera).scale == 1.0
    water = small_camera.replace(external_interface=ExternalInterface(1.33, 1.0, 0.04))
    assert DepthCorrection.for_camera(water).external == pytest.approx(1.33)
    mla = dataclasses.replace(small_camera.microlens_array, substrate=Substrate(6.3e-3, 1.46))
    physical = small_camera.replace(microlens_array=mla)
    thesis = small_camera.replace(microlens_array=dataclasses.replace(mla, back_side="thesis"))
    assert DepthCorrection.for_camera(physical).internal == 1.0        # S_i,eff covers it
    assert DepthCorrection.for_camera(thesis).internal == pytest.approx(1 / 1.46)
    assert DepthCorrection.for_camera(physical, internal="plate").internal == \
        pytest.approx(1 / 1.46)
    with pytest.raises(ConfigError, match="internal correction"):
        DepthCorrection.for_camera(physical, internal="yes")


@settings(max_examples=50, deadline=None)
@given(st.floats(0.5, 2.0), st.floats(0.5, 2.0),
       st.lists(st.floats(-0.02, 0.02), min_size=1, max_size=20))
def test_correction_then_inverse_is_identity(ext, internal, depths):
    c = DepthCorrection(ext, internal)
    z = np.array(depths)
    assert np.allclose(c.effective(c.depth(z)), z, rtol=1e-12, atol=1e-18)


def test_points_keep_lateral_coordinates():
    c = DepthCorrection(1.33)
    p = np.array([[1e-3, -2e-3, 3e-3]])
    q = c.points(p)
    assert q[0, :2] == pytest.approx(p[0, :2]) and q[0, 2] == pytest.approx(3.99e-3)
    assert p[0, 2] == 3e-3                      # input not modified
    with pytest.raises(ConfigError):
        DepthCorrection(0.0)
