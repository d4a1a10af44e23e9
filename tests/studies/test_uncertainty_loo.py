"""The left-out uncertainty study's pieces: its cases, the other camera, the page."""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.studies.uncertainty_loo import BAND, CASES, DEVELOPMENT, TERMS, markdown, resolve

pytestmark = pytest.mark.study


def test_every_case_is_a_valid_case_and_differs_from_the_development_ones(tmp_path):
    """Each left-out case builds (the other camera written and loadable), none repeats a
    development case, and the other camera differs from the development camera in its
    image distance and lattice."""
    from plenopiv.workflow.vortex_case import case_camera

    development = [resolve(kw, tmp_path) for _, _, kw in DEVELOPMENT]
    for label, _, kw in CASES:
        case = resolve(kw, tmp_path)
        if "development" not in label:
            assert case not in development, label
    other = case_camera(resolve({"camera": "other"}, tmp_path))
    base = case_camera(resolve({}, tmp_path))
    assert other.main_lens.image_distance == pytest.approx(0.105)
    assert base.main_lens.image_distance == pytest.approx(0.100)
    assert other.microlens_array.rotation != base.microlens_array.rotation


def _row(label, left_out, cov, before=None):
    row = {"label": label, "left_out": left_out, "n_vectors": 100, "coverage": cov,
           "rms_error_vox": [0.1, 0.2, 0.3], "gain": [1.0, float("nan"), 0.9],
           "rms_sigma_vox": [0.1, 0.2, 0.3], "ablation": {t: cov for t in TERMS},
           "rms_term_vox": {t: [0.0, 0.0, 0.0] for t in (*TERMS, "correlation")}}
    if before is not None:
        row["before"] = {"coverage": before}
    return row


def test_the_page_counts_the_band_before_and_now_and_keeps_development_apart():
    """The page counts case-components inside the band (inclusive), below and above, now and
    before, for the left-out and the development cases apart, and has an ablation row for
    every case."""
    result = {"band": list(BAND), "terms": list(TERMS), "seconds": 1.0, "cases": [
        _row("A", "orientation", [0.85, 0.99, 0.84], before=[0.80, 0.95, 0.95]),
        _row("B", "density", [0.90, 0.995, 0.95], before=[0.90, 0.95, 0.95]),
        _row("C", "none (development)", [0.95, 0.95, 0.95], before=[0.95, 0.95, 0.95])]}
    page = markdown(result, "NOTES HERE")
    assert "Now: 4 of 6 case-components in the band, 1 below, 1 above." in page
    assert "Before: 5 of 6 case-components in the band, 1 below, 0 above." in page
    assert "Now: 3 of 3 case-components in the band" in page
    assert page.index("## Coverage on the development cases") < page.index("| C |")
    assert sum(line.startswith("| A |") for line in page.splitlines()) == 3
    assert "NOTES HERE" in page and np.isfinite(result["seconds"])
