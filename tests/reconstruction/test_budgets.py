"""Every memory budget the docs promise is held on every path, before the large allocation.

The promises: ``[reconstruction] max_weights_gb`` bounds the explicit weights and a
matrix-free reconstruction, a larger estimate refused before any work with the figure and
what to change (docs/configuration.md, docs/performance.md); building the light field, the
first large allocation of every reconstruction, is held to it before it starts; the
estimate is an upper bound of what a reconstruction takes; ``--lenslets`` renders a patch of
the camera, never a sensor beyond it; a [volume] grid beyond the memory available is refused
by every verb that reconstructs before it reads its images (docs/cli.md).
"""

from __future__ import annotations

import dataclasses
import itertools
import tracemalloc

import numpy as np
import pytest

import plenopiv.reconstruction.build as build
import plenopiv.reconstruction.geometry as geometry_module
from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.resolution import footprint
from plenopiv.cli import main
from plenopiv.cli.simulate import KINDS
from plenopiv.errors import ReconstructionError
from plenopiv.lightfield.rays import light_field_build_bytes
from plenopiv.reconstruction.choose import choose_reconstruction
from plenopiv.reconstruction.geometry import ProjectionGeometry
from plenopiv.reconstruction.settings import ReconstructionSettings
from small_boxes import box, camera

#: Every path a reconstruction takes to its projector: the lattice (aligned or rotated), the
#: projector asked for and the lateral subdivision.
PATHS = list(itertools.product(("small_test", "small_test+rotated"),
                               ("auto", "sparse", "lattice"), ("auto", 1, 2)))


@pytest.mark.parametrize(("name", "projector", "subdivision"), PATHS)
def test_no_path_runs_over_its_budget(name, projector, subdivision, monkeypatch):
    """For budgets below the light field, between it and the reconstruction's need, just
    below that need and ample: the choice either fits the budget (its estimate and building
    the light field both) or is refused before anything is built, naming the figure and
    max_weights_gb."""
    cam = camera(name)
    cal = Calibration.from_camera(cam)
    grid = box(cam, 1.0)
    free = ReconstructionSettings(projector=projector, lateral_subdivision=subdivision)
    geometry = ProjectionGeometry.for_settings(cal, grid, free)      # one light field
    need = choose_reconstruction(cal, grid, free, geometry=geometry).memory_bytes
    lf = light_field_build_bytes(cal)
    top = max(need, lf)
    refused = 0
    for budget in (0.5 * lf, 0.5 * (lf + top), 0.9 * top, 4 * top):
        s = dataclasses.replace(free, max_weights_gb=budget / 1e9)
        d = choose_reconstruction(cal, grid, s, geometry=geometry)
        if d.refusal is None:
            assert d.memory_bytes <= budget and lf <= budget, (budget, d.reason)
            continue
        refused += 1
        assert "max_weights_gb" in d.refusal and " GB" in d.refusal
        monkeypatch.setattr(build, "matrix_free_projector", _forbidden)
        monkeypatch.setattr(build, "build_weights", _forbidden)
        with pytest.raises(ReconstructionError, match="max_weights_gb"):
            build.weights_for(cal, grid, s, geometry=geometry)
        monkeypatch.undo()
    assert refused >= 1 and d.refusal is None                 # the ample budget fits


def _forbidden(*args, **kwargs):
    raise AssertionError("a projector was built for a refused budget")


def test_the_default_matrix_free_path_is_held_to_max_weights_gb():
    """The defaults on an aligned lattice: the lattice projector on a 3 x 3 subdivision. A
    budget below its estimate (but above the light field) is refused with the figure and
    what to change; it ran over before."""
    cam = camera("small_test")
    cal = Calibration.from_camera(cam)
    b = footprint(cam)
    grid = VolumeGrid.from_bounds((-15 * b, 15 * b), (-15 * b, 15 * b), (-4e-3, 4e-3),
                                  voxel=(b, b, 0.05e-3))
    # on the box's own slices (binned, its working grid would be smaller than the light field)
    d = choose_reconstruction(cal, grid, ReconstructionSettings(depth_binning=1))
    assert (d.projector, d.subdivision) == ("lattice", (3, 3))
    lf = light_field_build_bytes(cal)
    assert d.memory_bytes > lf
    budget = 0.5 * (lf + d.memory_bytes)
    tight = ReconstructionSettings(max_weights_gb=budget / 1e9, depth_binning=1)
    coarser = choose_reconstruction(cal, grid, tight)          # "auto": a coarser subdivision
    assert coarser.refusal is None and coarser.memory_bytes <= budget
    assert coarser.subdivision < (3, 3) and "do not fit" in coarser.fallbacks[0]
    fixed = dataclasses.replace(tight, lateral_subdivision=3)   # no coarser one allowed
    refused = choose_reconstruction(cal, grid, fixed)
    assert refused.refusal is not None
    assert "matrix-free reconstruction" in refused.refusal and "needs ~" in refused.refusal
    assert "use fewer or larger voxels, or raise max_weights_gb" in refused.refusal
    with pytest.raises(ReconstructionError, match="needs ~"):
        build.weights_for(cal, grid, fixed)


def test_the_light_field_is_not_built_for_a_budget_it_exceeds(monkeypatch):
    cam = camera("small_test")
    cal = Calibration.from_camera(cam)

    def forbidden(*args, **kwargs):
        raise AssertionError("the light field was built")

    monkeypatch.setattr(geometry_module, "light_field", forbidden)
    s = ReconstructionSettings(max_weights_gb=0.5 * light_field_build_bytes(cal) / 1e9)
    with pytest.raises(ReconstructionError, match=r"building the light field of the 700 × "
                                                   r"1040-pixel sensor needs ~0\.\d+ GB"):
        build.weights_for(cal, box(cam, 1.0), s)


def test_the_estimate_bounds_what_a_default_reconstruction_takes(rng):
    """The traced peak of a whole default reconstruction (light field, lattice projector,
    line of sight, SMART, merge, particles) stays below the larger of the two estimates the
    budget is checked against."""
    from plenopiv.synthetic.flows import Uniform
    from plenopiv.synthetic.seeding import SeedingBox, simulate_pair
    from plenopiv.workflow.volume import reconstruct_volume

    cam = camera("small_m1")
    cal = Calibration.from_camera(cam)
    grid = box(cam, 1.0, half=12)
    settings = ReconstructionSettings(lattice_check="off")
    d = choose_reconstruction(cal, grid, settings)
    b = grid.bounds
    pair = simulate_pair(cam, Uniform((0.0, 0.0, 0.0)), dt=1e-3,
                         box=SeedingBox(tuple(b[0]), tuple(b[1]), tuple(b[2])),
                         n_particles=100, rng=rng, rays_per_particle=128)
    image = np.asarray(pair.image_a, float)
    tracemalloc.start()
    try:
        reconstruct_volume(cal, image, grid, settings=settings)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak <= max(d.memory_bytes, light_field_build_bytes(cal))


@pytest.mark.parametrize("kind", [k for k, _ in KINDS if k != "pair"])
def test_lenslets_beyond_the_camera_are_refused_before_rendering(kind, tmp_path, capsys):
    """``simulate --lenslets 1000 1000`` of a 41 x 61 camera rendered a 574 MB image."""
    for lenslets in (("1000", "1000"), ("42", "5"), ("5", "62"), ("0", "5")):
        assert main(["simulate", kind, "small_test", "--lenslets", *lenslets,
                     "--out", str(tmp_path / "x.tif")]) == 2
        err = capsys.readouterr().err
        assert f"--lenslets {lenslets[0]} {lenslets[1]}: expected a patch of the camera, 1 to " \
               "41 rows and 1 to 61 columns" in err
    assert main(["validate", "oseen", "--lenslets", "42", "61", "--out",
                 str(tmp_path / "val")]) == 2
    assert "1 to 41 rows" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("verb", ["reconstruct", "track", "run"])
def test_a_volume_beyond_the_memory_is_refused_by_every_verb_that_reconstructs(
        verb, tmp_path, monkeypatch, capsys):
    """Before any image is read (the reader is made to fail)."""
    import plenopiv.products.images as images
    from plenopiv.resources import available_memory

    monkeypatch.setattr(images, "read_image", _forbidden)
    Calibration.from_camera(camera("small_m1")).save(tmp_path / "cal.h5")
    side = int((available_memory() / 32) ** (1 / 3)) + 100      # 32 bytes per voxel
    (tmp_path / "exp.toml").write_text(
        'camera = "small_m1"\n[volume]\nx_mm = [-1, 1]\ny_mm = [-1, 1]\nz_mm = [-1, 1]\n'
        f'shape = [{side}, {side}, {side}]\n[images]\na = "*_A.tif"\nb = "*_B.tif"\n'
        'calibration = "cal.h5"\n')
    for name in ("p_A.tif", "p_B.tif"):
        (tmp_path / name).write_bytes(b"")
    args = {"reconstruct": ["reconstruct", "cal.h5", "p_A.tif", "--config", "exp.toml",
                            "--out", "v.h5"],
            "track": ["track", "cal.h5", "p_A.tif", "p_B.tif", "--config", "exp.toml",
                      "--out", "t.h5"],
            "run": ["run", "exp.toml"]}[verb]
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    err = capsys.readouterr().err
    # beyond 2^31 voxels where the machine has that much memory; beyond the memory here
    assert "voxels" in err and ("needs about" in err or "expected at most" in err), err
