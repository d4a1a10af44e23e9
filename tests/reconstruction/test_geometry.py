"""The projection geometry: one light field per reconstruction, and a one-way module walk."""

from __future__ import annotations

import collections
import graphlib
import sys

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ReconstructionError
from plenopiv.lightfield import light_field
from plenopiv.reconstruction import sightline
from plenopiv.reconstruction.build import cached_weights, weights_for
from plenopiv.reconstruction.geometry import ProjectionGeometry, weights_key
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.synthetic.images import particle_image
from plenopiv.workflow.volume import reconstruct_volume

LIGHT_FIELD = ("plenopiv.lightfield.rays", "light_field")


@pytest.fixture(scope="module")
def case(small_camera):
    """Two particles in a 16 × 8 × 8 grid of 0.25 mm voxels (two footprints) of the test camera."""
    cal = Calibration.from_camera(small_camera)
    grid = VolumeGrid.from_bounds((-1e-3, 1e-3), (-1e-3, 1e-3), (-2e-3, 2e-3), voxel=0.25e-3)
    img = particle_image(small_camera, [(0.0, 0.0, 0.0), (0.3e-3, -0.2e-3, 1e-3)],
                         rays_per_particle=20000)
    return cal, grid, img


def _module(frame) -> str:
    """The frame's module; a method inherited from a base class counts as its object's class's
    (``self.forward`` called by a base-class helper is the object calling itself)."""
    name = frame.f_globals.get("__name__", "")
    owner = type(frame.f_locals.get("self", None)).__module__
    return owner if name.startswith("plenopiv") and owner.startswith("plenopiv") else name


def record_calls(fn):
    """Run ``fn()`` under ``sys.setprofile``.

    Returns the calls per (module, function) and the caller-module -> callee-module edges
    among plenopiv's modules (a callee's caller is the nearest plenopiv frame below it).
    """
    calls, edges = collections.Counter(), collections.Counter()

    def profile(frame, event, _arg):
        if event != "call" or not _module(frame).startswith("plenopiv"):
            return
        callee = _module(frame)
        calls[(callee, frame.f_code.co_name)] += 1
        back = frame.f_back
        while back is not None and not _module(back).startswith("plenopiv"):
            back = back.f_back
        if back is not None and _module(back) != callee:
            edges[(_module(back), callee)] += 1

    sys.setprofile(profile)
    try:
        fn()
    finally:
        sys.setprofile(None)
    return calls, edges


def module_order(edges) -> list[str]:
    """The modules in call order (callers first); graphlib.CycleError if a module calls back."""
    callees = collections.defaultdict(set)
    for a, b in edges:
        callees[b].add(a)            # b runs after a: a is b's predecessor
        callees.setdefault(a, set())
    return list(graphlib.TopologicalSorter(callees).static_order())


@pytest.fixture(scope="module")
def rotated_case(small_camera, case):
    """The same image through a lenslet array rotated by 2 mrad: the per-lenslet projector."""
    import dataclasses

    mla = dataclasses.replace(small_camera.microlens_array, rotation=2e-3, offset=(3e-6, -2e-6))
    return (Calibration.from_camera(small_camera.replace(microlens_array=mla)), *case[1:])


@pytest.mark.parametrize("method, lattice", [("smart", "aligned"), ("mart", "aligned"),
                                             ("smart", "rotated")])
def test_one_reconstruction_builds_one_light_field_and_walks_its_modules_one_way(
        case, rotated_case, method, lattice):
    """SMART (subdivided, matrix-free lattice projector), row-action MART (explicit weights)
    and SMART on a rotated array (matrix-free per-lenslet projector): the light field is built
    once, and no plenopiv module calls back into a module that called it (the caller -> callee
    graph of modules is acyclic)."""
    cal, grid, img = case if lattice == "aligned" else rotated_case
    settings = ReconstructionSettings(method=method,
                                      projector="lattice" if lattice == "rotated" else "auto")
    sightline._CACHE.clear()         # the refined projectors of an earlier test would hide a call
    calls, edges = record_calls(lambda: reconstruct_volume(cal, img, grid, settings=settings))
    edge_text = "\n".join(f"  {a} -> {b} ({n})" for (a, b), n in sorted(edges.items()))
    try:
        order = module_order(edges)
    except graphlib.CycleError as exc:
        pytest.fail(f"modules call back upstream, cycle {exc.args[1]}; edges:\n{edge_text}")
    assert calls[LIGHT_FIELD] == 1, (f"light_field built {calls[LIGHT_FIELD]} times; module "
                                     f"order {order}")
    assert order[0] == "plenopiv.workflow.volume", f"module order {order}"
    modules = ["plenopiv.workflow.volume", "plenopiv.reconstruction.build",
               "plenopiv.reconstruction.choose", "plenopiv.reconstruction.geometry",
               "plenopiv.lightfield.rays"]
    flow = [m for m in order if m in modules]
    assert flow == sorted(flow, key=modules.index), f"module order {order}"


def test_given_weights_lend_their_light_field_to_the_line_of_sight(case):
    """Weights from weights_for carry their geometry, whose light field was built for them:
    reconstructing with those weights builds none."""
    cal, grid, img = case
    settings = ReconstructionSettings(method="mart")
    weights, _ = weights_for(cal, grid, settings)
    assert weights.geometry is not None and weights.geometry.grid == weights.grid
    sightline._CACHE.clear()
    calls, _ = record_calls(lambda: reconstruct_volume(cal, img, grid, settings=settings,
                                                       weights=weights))
    assert calls[LIGHT_FIELD] == 0


def test_geometry_on_another_grid_shares_the_light_field_and_keys_its_grid(case):
    cal, grid, _ = case
    geo = ProjectionGeometry(cal, grid, None, 0.5)
    fine = VolumeGrid.from_bounds((-1e-3, 1e-3), (-1e-3, 1e-3), (-2e-3, 2e-3), voxel=0.125e-3)
    other = geo.on_grid(fine)
    calls, _ = record_calls(lambda: (geo.light_field, other.light_field, other.separable_axes))
    assert calls[LIGHT_FIELD] == 1
    assert other.light_field is geo.light_field and other.grid == fine
    assert geo.on_grid(grid) is geo
    reference = light_field(cal)
    np.testing.assert_array_equal(geo.light_field.pixel, reference.pixel)
    np.testing.assert_array_equal(geo.light_field.u, reference.u)
    assert geo.key() == weights_key(cal, grid, f_number=None, min_lit=0.5, min_weight=1e-7)
    assert other.key() != geo.key()
    assert geo.separable_axes is not None          # the test camera's lattice is axis-aligned


def test_geometry_refuses_a_grid_out_of_view(case):
    cal, _, _ = case
    far = VolumeGrid.from_bounds((0.5, 0.501), (-1e-3, 1e-3), (-1e-3, 1e-3), voxel=0.25e-3)
    with pytest.raises(ReconstructionError, match="outside the field of view"):
        ProjectionGeometry(cal, far).check_in_view()


def test_cached_weights_refuse_a_geometry_of_other_rays(case):
    cal, grid, _ = case
    with pytest.raises(ValueError, match="another calibration, f_number or min_lit"):
        cached_weights(cal, grid, cache_dir=None, min_lit=0.9,
                       geometry=ProjectionGeometry(cal, grid, None, 0.5))
