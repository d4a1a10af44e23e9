"""One decision of the working grid and projector: ``plenopiv plan`` reports what
``plenopiv reconstruct`` builds (:func:`plenopiv.reconstruction.choose.choose_reconstruction`)."""

from __future__ import annotations

import itertools

import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.resolution import footprint
from plenopiv.errors import ReconstructionError
from plenopiv.lightfield.rays import light_field_build_bytes
from plenopiv.reconstruction.build import weights_for
from plenopiv.reconstruction.choose import choose_reconstruction, subdivided_grid
from plenopiv.reconstruction.lattice import LatticeProjector
from plenopiv.reconstruction.projector import SparseProjector
from plenopiv.reconstruction.real_lattice import LensletProjector
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.workflow import planning
from small_boxes import box, camera

KINDS = {SparseProjector: "sparse", LatticeProjector: "lattice", LensletProjector: "lenslet"}


def built(cal, grid, settings):
    """``(projector kind, working grid)`` of what a reconstruction builds, or its refusal."""
    try:
        w, _ = weights_for(cal, grid, settings)
    except ReconstructionError as exc:
        return "refused", str(exc)
    return KINDS[type(w.projector)], w.grid


def planned(cam, grid, settings):
    """``(projector kind, working grid)`` that ``plenopiv plan`` reports, or its refusal."""
    d = planning.plan(cam, grid, reconstruction=settings).decision
    if d.refusal is not None:
        return "refused", d.refusal
    return d.projector, d.grid


@pytest.mark.parametrize(("name", "voxel"), [("small_test", 1.0), ("small_test", 0.5),
                                              ("small_m1", 1.0), ("small_m1", 0.5)])
def test_plan_reports_the_projector_and_grid_the_reconstruction_builds(name, voxel):
    """Voxels of one and of half a footprint; subdivision auto, 1 and 2; projector auto,
    sparse and lattice: plan's decision is the reconstruction's, every combination."""
    cam = camera(name)
    cal = Calibration.from_camera(cam)
    grid = box(cam, voxel)
    seen = set()
    for k, projector in itertools.product(("auto", 1, 2), ("auto", "sparse", "lattice")):
        s = ReconstructionSettings(lateral_subdivision=k, projector=projector)
        got = built(cal, grid, s)
        assert planned(cam, grid, s) == got, (k, projector)
        d = choose_reconstruction(cal, grid, s)
        assert d.working_shape == got[1].shape and d.memory_bytes > 0
        seen.add((got[0], got[1].shape[1] // grid.shape[1]))
    # the combinations reach both projectors and more than one subdivision
    assert {kind for kind, _ in seen} == {"sparse", "lattice"}
    assert len({sub for _, sub in seen}) >= 2


def test_auto_subdivision_of_footprint_voxels_is_the_lattice_projector_on_a_third():
    """The case plan got wrong: footprint voxels, defaults. The reconstruction runs the
    lattice projector on a 3 x 3 subdivided grid; plan said explicit weights on the volume's
    grid, with their memory."""
    cam = camera("small_test")
    grid = box(cam, 1.0)
    p = planning.plan(cam, grid)
    d = p.decision
    assert (d.projector, d.subdivision, d.depth_binning) == ("lattice", (3, 3), 3)
    assert d.grid == subdivided_grid(grid, 3, 3, 3)
    assert p.projector == "lattice" and p.memory["weights"] == 0.0
    assert p.memory["projector"] == d.memory_bytes
    assert "3 x 3 subdivided" in d.reason
    out = p.to_dict()
    assert out["lateral_subdivision"] == [3, 3]
    assert out["depth_binning"] == 3
    assert out["working_shape"] == [-(-grid.shape[0] // 3), 3 * grid.shape[1],
                                    3 * grid.shape[2]]
    assert out["decision"]["memory_bytes"] == pytest.approx(d.memory_bytes)
    assert out["memory_gb"]["projector"] == pytest.approx(d.memory_bytes / 1e9)


def deep_box(cam):
    """30 x 20 footprint voxels, 48 slices of a footprint: explicit weights far larger than
    the matrix-free projector's arrays."""
    b = footprint(cam)
    return VolumeGrid.from_bounds((-15 * b, 15 * b), (-10 * b, 10 * b), (-24 * b, 24 * b),
                                  voxel=b)


@pytest.mark.parametrize("name", ["small_test", "small_test+rotated"])
def test_budgets_methods_and_lattices_decide_alike(name):
    """Row-action MART; a budget between the matrix-free and the explicit estimates, and
    half of that; a rotated lattice (the per-lenslet projector): the same decision,
    refusals included (the deep box on its own slices: binned, its weights would be small)."""
    cam = camera(name)
    cal = Calibration.from_camera(cam)
    deep = deep_box(cam)
    free = choose_reconstruction(cal, deep, ReconstructionSettings(
        lateral_subdivision=1, projector="lattice", depth_binning=1))
    explicit = choose_reconstruction(cal, deep, ReconstructionSettings(
        lateral_subdivision=1, projector="sparse", depth_binning=1))
    assert 2 * free.memory_bytes < explicit.memory_bytes
    # building the light field comes first and has its own peak: a budget must hold it too
    tight = 1.01 * max(free.memory_bytes, light_field_build_bytes(cal)) / 1e9
    assert tight < explicit.memory_bytes / 1e9
    cases = [(box(cam, 1.0), dict(method="mart")),
             (box(cam, 1.0), dict(method="mart", lateral_subdivision=2)),
             (deep, dict(projector="lattice", lateral_subdivision=1, depth_binning=1)),
             (deep, dict(max_weights_gb=tight, lateral_subdivision=1, depth_binning=1)),
             (deep, dict(max_weights_gb=tight, projector="sparse", lateral_subdivision=1,
                         depth_binning=1)),
             (deep, dict(max_weights_gb=0.5 * tight, lateral_subdivision=1,
                         depth_binning=1))]
    kinds = []
    for grid, case in cases:
        s = ReconstructionSettings(**case)
        got = built(cal, grid, s)
        assert planned(cam, grid, s) == got, case
        kinds.append(got[0])
    matrix_free = "lenslet" if name.endswith("rotated") else "lattice"
    assert kinds == ["sparse", "sparse", matrix_free, matrix_free, "refused", "refused"]


def test_auto_subdivision_falls_back_where_nothing_fits():
    """A rotated lattice whose 3 x 3 subdivision fits nothing: the decision and the
    reconstruction both take a coarser subdivision, and the reconstruction warns why."""
    cam = camera("small_test+rotated")
    cal = Calibration.from_camera(cam)
    b = footprint(cam)
    # slices an eighth of a footprint deep: a budget between the two subdivisions' needs
    # holds building the light field too
    deep = VolumeGrid.from_bounds((-15 * b, 15 * b), (-10 * b, 10 * b), (-24 * b, 24 * b),
                                  voxel=(b, b, b / 8))
    # (on its own slices: binned, the working grid would be small)
    need = [choose_reconstruction(cal, deep, ReconstructionSettings(
        lateral_subdivision=k, projector="lattice", depth_binning=1)).memory_bytes
        for k in (2, 3)]
    assert sum(need) / 2 > light_field_build_bytes(cal)
    s = ReconstructionSettings(projector="lattice", max_weights_gb=sum(need) / 2e9,
                               depth_binning=1)
    d = choose_reconstruction(cal, deep, s)
    assert d.refusal is None and d.subdivision == (2, 2) and len(d.fallbacks) == 1
    assert "finer ones do not fit" in d.reason
    with pytest.warns(UserWarning, match="do not fit"):
        got = built(cal, deep, s)
    assert got == ("lenslet", d.grid) == planned(cam, deep, s)
