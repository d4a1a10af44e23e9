"""The vortex case varied one property at a time: camera, flow axis and centre, grid.

Every property a case can vary (:attr:`VortexCase.camera_changes`, ``flow_axis``,
``centre_offset``, ``voxel_lateral_factor``, ``grid_shift``) changes that property alone, and
the defaults leave the preset, the flow and the grid of the demo and the studies as they were.
The study that runs them is docs/validation/invariance.md.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.model import load_camera
from plenopiv.camera.resolution import footprint
from plenopiv.workflow.vortex_case import (
    VortexCase,
    aligned_grid,
    case_camera,
    case_flow,
    vortex_axis,
)

#: Each camera property a case varies, a value other than the preset's, and where the camera
#: keeps it.
CAMERA_CHANGES = {
    "f_number": (2.8, lambda c: c.main_lens.f_number),
    "image_distance": (105e-3, lambda c: c.main_lens.image_distance),
    "lattice_rotation": (1.5e-3, lambda c: c.microlens_array.rotation),
    "lattice_offset": ((4e-6, -3e-6), lambda c: c.microlens_array.offset),
    "lattice": ("hexagonal", lambda c: c.microlens_array.grid),
}
AXES = {"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1), "oblique": (1.0, 1.0, 1.0)}


def _grid(case):
    return aligned_grid(Calibration.from_camera(case_camera(case)).effective_camera, case)


def test_the_defaults_keep_the_preset_the_flow_and_the_grid():
    case = VortexCase()
    assert case.camera_changes == {}
    assert case_camera(case) == load_camera(case.camera)
    flow = case_flow(case, _grid(case))
    assert flow.axis == (0.0, 1.0, 0.0) and flow.centre == (0.0, 0.0, 0.0)
    grid = _grid(case)
    b = footprint(case_camera(case))
    np.testing.assert_allclose(grid.voxel, (b, b, b))
    # a voxel centre on the optical axis and on the focal plane
    np.testing.assert_allclose(np.asarray(grid.origin) / b % 1.0, 0.0, atol=1e-9)
    assert case_flow(VortexCase(flow="hill"), grid).axis == (1.0, 0.0, 0.0)


@pytest.mark.parametrize("name", list(CAMERA_CHANGES))
def test_each_camera_change_sets_its_property_alone(name):
    value, read = CAMERA_CHANGES[name]
    preset = load_camera("small_m1")
    cam = case_camera(VortexCase(**{name: value}))
    assert read(cam) == value and read(preset) != value
    # everything else as in the preset
    back = dataclasses.replace(VortexCase(), **{name: None})
    assert case_camera(back) == preset
    changed = {k for k, v in cam.to_dict().items() if v != preset.to_dict()[k]}
    assert changed <= {"main_lens", "microlens_array"}
    for section in ("main_lens", "microlens_array"):
        a, b = cam.to_dict()[section], preset.to_dict()[section]
        assert len({k for k in a if a[k] != b.get(k)}) <= 1


@pytest.mark.parametrize("axis", list(AXES))
def test_the_flow_turns_about_its_axis_and_moves_with_its_centre(axis):
    offset = (0.31e-3, -0.23e-3, 0.17e-3)
    case = VortexCase(flow_axis=AXES[axis] if axis == "oblique" else axis,
                      centre_offset=offset)
    grid = _grid(case)
    flow = case_flow(case, grid)
    a = np.asarray(vortex_axis(case.flow_axis))
    np.testing.assert_allclose(np.linalg.norm(a), 1.0)
    np.testing.assert_allclose(flow.centre, offset)
    rng = np.random.default_rng(3)
    pts = rng.uniform(-2e-3, 2e-3, (200, 3))
    vel = flow(pts)
    np.testing.assert_allclose(vel @ a, 0.0, atol=1e-12)   # no motion along the axis
    # at rest on the axis through the moved centre, moving off it
    on_axis = np.asarray(offset) + np.outer([-1e-3, 0.0, 1e-3], a)
    np.testing.assert_allclose(flow(on_axis), 0.0, atol=1e-12)
    assert np.abs(flow(np.asarray(offset)[None] + 1e-3 * np.cross(a, [0.6, 0.8, 0.0])
                       / np.linalg.norm(np.cross(a, [0.6, 0.8, 0.0])))).max() > 0


@pytest.mark.parametrize("bad", [dict(flow_axis="w"), dict(flow_axis=(0, 0, 0)),
                                 dict(flow_axis=(1, 0)), dict(centre_offset=(0, 0)),
                                 dict(grid_shift=(0.5,)), dict(voxel_lateral_factor=0.0)])
def test_bad_variations_are_refused(bad):
    with pytest.raises(ValueError):
        VortexCase(**bad)


@pytest.mark.parametrize("factor, shift", [(1.1, (0.0, 0.0, 0.0)), (1.0, (0.5, -0.25, 0.5)),
                                           (0.9, (0.3, 0.3, 0.0))])
def test_the_grid_scales_and_moves_off_the_footprints(factor, shift):
    case = VortexCase(voxel_lateral_factor=factor, grid_shift=shift)
    grid, ref = _grid(case), _grid(VortexCase())
    b = footprint(case_camera(case))
    np.testing.assert_allclose(grid.voxel, (factor * b, factor * b, b))
    # the centre of the box moved by the shift, in voxels
    centre = np.asarray(grid.origin) + 0.5 * (np.asarray(grid.shape[::-1]) - 1) * grid.voxel
    ref_centre = np.asarray(ref.origin) + 0.5 * (np.asarray(ref.shape[::-1]) - 1) * ref.voxel
    np.testing.assert_allclose(centre - ref_centre, np.asarray(shift) * grid.voxel, atol=1e-12)
