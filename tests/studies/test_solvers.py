"""The solver study (pipelines/studies/solvers.py) on a patch of any preset camera."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from pipelines.studies.field_quality import footprint, study_setup
from pipelines.studies.solvers import (
    PAIR_SHIFT_VOX,
    SOLVERS,
    TUNED,
    fields,
    pair_error,
    run_solver,
    second_exposure,
    study,
)
from plenopiv.camera.model import load_camera
from plenopiv.reconstruction.build import weights_for
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.subdivision import working_factors


@pytest.mark.parametrize("preset", ["auburn_50mm", "auburn_135mm"])
def test_the_patch_is_cut_from_the_preset_it_names(preset):
    setup = study_setup(5, 7, preset=preset)
    full = load_camera(preset)
    assert setup.camera.main_lens.focal_length == full.main_lens.focal_length
    assert setup.camera.microlens_array.rows == 5 and setup.camera.microlens_array.cols == 7
    b = footprint(setup.camera)
    assert setup.grid.voxel[0] == pytest.approx(b, rel=1e-12)     # one footprint laterally


def test_every_solver_is_scored_on_the_16_mp_cameras_optics():
    out = study(9, 11, [5], densities=(0.1,), progress=lambda *_: None,
                preset="auburn_135mm")
    assert out["camera"].startswith("auburn_135mm patch 9 x 11")
    assert len(out["rows"]) == len(SOLVERS) + len(TUNED)
    for row in out["rows"]:
        assert "error" in row or 0.0 < row["q"]["cell"] <= 1.0


@pytest.mark.parametrize("kind", ["equal_cost_study", "hybrid_study"])
def test_every_study_takes_the_preset(kind, monkeypatch):
    """The equal-cost and hybrid studies cut their patch from the preset they are given."""
    import pipelines.studies.solvers as solvers

    seen = []

    def record(rows, cols, *, preset, subdivision):
        seen.append((preset, subdivision))
        raise RuntimeError("stop after the set-up")

    monkeypatch.setattr(solvers, "study_setup", record)
    with pytest.raises(RuntimeError, match="stop after the set-up"):
        getattr(solvers, kind)(5, 7, [5, 6], densities=(0.1,), progress=lambda *_: None,
                               preset="auburn_135mm", subdivision="auto")
    assert seen == [("auburn_135mm", "auto")]


def test_auto_reconstructs_on_the_working_grid_of_the_defaults_and_scores_the_footprints():
    """``subdivision="auto"``: footprint voxels, the weights of the defaults' working grid."""
    setup = study_setup(7, 9, subdivision="auto")
    default, _ = weights_for(setup.calibration, setup.grid, ReconstructionSettings())
    assert setup.grid.voxel[0] == pytest.approx(footprint(setup.camera), rel=1e-12)
    assert setup.weights.grid == default.grid != setup.grid
    _kz, ky, kx = working_factors(setup.weights.grid, setup.grid)
    assert ky > 1 and kx > 1                  # the defaults subdivide a box this small


def test_the_default_beats_clipped_cgls_on_the_weights_it_reconstructs_with():
    """On the working grid the defaults choose, SMART's volume (as returned, on the footprint
    grid) has a higher Q and finds more particles than clipped CGLS's, and the pair's
    lateral velocity error is a fraction of a voxel (issue #37's claim, one seed at 0.3
    particles per lenslet; docs/validation/solvers.md has every density and seed)."""
    setup = study_setup(21, 31, subdivision="auto")
    pos, img = fields(setup, 0.3, 7)
    pair = second_exposure(setup, pos, 0.3, 7)
    smart, cgls = (run_solver(setup, img, pos, *SOLVERS[name], 10, pair=pair)
                   for name in ("smart (default)", "cgls (line of sight)"))
    assert smart["q"]["cell"] > cgls["q"]["cell"]
    assert smart["detection_rate"] > cgls["detection_rate"]
    assert smart["ghost_rate"] <= cgls["ghost_rate"]
    # lateral PIV of a uniform shift on a resolved grid: about a tenth of a voxel
    assert max(smart["velocity_rms_vox"][:2]) < 0.2
    assert smart["velocity_valid"] > 0.9


def test_the_pairs_error_is_measured_against_the_shift_it_was_given():
    """A volume correlated with itself moved by the pair's shift gives back that shift."""
    from scipy.ndimage import shift as move

    setup = study_setup(21, 31)
    rng = np.random.default_rng(3)
    a = np.zeros(setup.grid.shape, np.float32)
    idx = tuple(rng.integers(2, n - 2, 300) for n in setup.grid.shape)
    a[idx] = 1.0
    a = gaussian_filter(a, 1.0)
    b = move(a, PAIR_SHIFT_VOX[::-1], order=3).astype(np.float32)    # (z, y, x) order
    out = pair_error(setup, a, b)
    assert max(out["velocity_rms_vox"]) < 0.1
    assert np.abs(out["velocity_bias_vox"]).max() < 0.05
