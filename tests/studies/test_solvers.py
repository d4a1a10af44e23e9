"""The solver study (pipelines/studies/solvers.py) on a patch of any preset camera."""

from __future__ import annotations

import pytest

from pipelines.studies.field_quality import footprint, study_setup
from pipelines.studies.solvers import SOLVERS, TUNED, study
from plenopiv.camera.model import load_camera


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

    def record(rows, cols, *, preset):
        seen.append(preset)
        raise RuntimeError("stop after the set-up")

    monkeypatch.setattr(solvers, "study_setup", record)
    with pytest.raises(RuntimeError, match="stop after the set-up"):
        getattr(solvers, kind)(5, 7, [5, 6], densities=(0.1,), progress=lambda *_: None,
                               preset="auburn_135mm")
    assert seen == ["auburn_135mm"]
